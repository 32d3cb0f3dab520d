"""``train-many``: several runs at once give the weights lone ``train`` runs give, bit for bit; its
folder rules, locks and one-line errors; the throughput table's arithmetic."""

import json
import os
from pathlib import Path

import pytest
import torch

from geodepth_lite import cli, utils
from geodepth_lite.data import analytic
from geodepth_lite.training import checkpoint, config, train_many


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory) -> Path:
    return analytic.write_dataset(tmp_path_factory.mktemp("many") / "data", {"train": 8, "val": 2, "test": 2},
                                  size=32)


def _settings(root) -> list[str]:
    return ["--profile", "smoke", "--dataset", str(root), "--image-size", "32", "--epochs", "1", "--device", "cpu"]


def _weights(folder: Path) -> dict:
    return torch.load(folder / checkpoint.CHECKPOINT_NAME, weights_only=False, map_location="cpu")


def _differing(a: dict, b: dict) -> list[str]:
    return [k for k in a["model"] if not torch.equal(a["model"][k], b["model"][k])]


def test_two_runs_together_give_the_weights_of_two_lone_runs(tiny_root, tmp_path, capsys):
    out = tmp_path / "together"
    assert cli.main(["train-many", *_settings(tiny_root), "--seeds", "0", "1", "--concurrency", "2",
                     "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "case 4 seed 0: epoch 1 done" in said and "case 4 seed 1: completed" in said
    record = json.loads((out / "train_many.json").read_text())
    assert record["concurrency"] == 2 and [r["status"] for r in record["runs"]] == ["completed"] * 2
    a0, a1 = record["runs"]
    assert a0["started_at"] < a1["ended_at"] and a1["started_at"] < a0["ended_at"]  # the two trained at the same time
    for seed in (0, 1):  # apart: the lone train command, one after the other
        assert cli.main(["train", *_settings(tiny_root), "--seed", str(seed), "--no-progress",
                         "--run-dir", str(tmp_path / f"apart{seed}")]) == 0
        together, apart = _weights(out / f"case4_seed{seed}"), _weights(tmp_path / f"apart{seed}")
        assert _differing(together, apart) == []
        assert config.config_hash(together["cfg"]) == config.config_hash(apart["cfg"]) == record["runs"][seed][
            "config_hash"]
        assert sorted(p.name for p in (out / f"case4_seed{seed}").iterdir()) == sorted(
            p.name for p in (tmp_path / f"apart{seed}").iterdir())
    # the comparison can fail: another seed's weights differ
    assert len(_differing(_weights(out / "case4_seed0"), _weights(tmp_path / "apart1"))) > 10
    # again: a finished run is refused without --resume, skipped with it (no process started)
    before = (out / "case4_seed0" / checkpoint.CHECKPOINT_NAME).stat().st_mtime_ns
    assert cli.main(["train-many", *_settings(tiny_root), "--seeds", "0", "1", "--out", str(out)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert cli.main(["train-many", *_settings(tiny_root), "--seeds", "0", "1", "--resume", "--out", str(out)]) == 0
    assert capsys.readouterr().out.count("finished before, skipped") == 2
    assert (out / "case4_seed0" / checkpoint.CHECKPOINT_NAME).stat().st_mtime_ns == before


def test_a_run_whose_folder_is_in_use_fails_alone_naming_the_holder(tiny_root, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / train_many.MARKER).write_text("")  # a folder of an earlier train-many
    with utils.FolderLock(out / "case4_seed0"):  # a lone train on that run's folder
        assert cli.main(["train-many", *_settings(tiny_root), "--out", str(out)]) == 1
    record = json.loads((out / "train_many.json").read_text())
    status = record["runs"][0]["status"]
    assert status.startswith("failed (exit 2): error: ") and f"in use by process {os.getpid()}" in status
    assert not (out / "case4_seed0" / checkpoint.CHECKPOINT_NAME).exists()


def test_a_folder_it_did_not_write_is_refused_and_kept(tiny_root, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert cli.main(["train-many", *_settings(tiny_root), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and str(out) in err and "did not write" in err and len(err.splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_a_second_command_on_the_same_folder_is_refused_naming_the_first(tiny_root, tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / train_many.MARKER).write_text("")
    with utils.FolderLock(out, "train-many folder", remove_file=True):  # the first command, still running
        assert cli.main(["train-many", *_settings(tiny_root), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"in use by process {os.getpid()}" in err and len(err.splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == [train_many.MARKER]


@pytest.mark.parametrize("device, words", [("gpu0", "--device 'gpu0' is not a device"),
                                           ("meta", "trains on cpu, cuda or cuda:N"),
                                           ("cuda:0", "no CUDA device")])
def test_a_bad_device_is_one_line_and_writes_nothing(tiny_root, tmp_path, capsys, device, words):
    if device.startswith("cuda") and torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    argv = ["train-many", "--profile", "smoke", "--dataset", str(tiny_root), "--device", device,
            "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and words in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_bad_settings_are_refused_before_anything_is_written(tiny_root, tmp_path, capsys):
    argv = ["train-many", *_settings(tiny_root), "--image-size", "33", "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 2
    assert "image_size must be a multiple of 32" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_the_throughput_table_divides_steps_by_time():
    """Known answers: 10 steps per epoch, 20 frames per epoch at 4 frames/s = 5 s of training."""

    def run(rows):
        r = train_many.Run(4, 0, Path("f"), [], Path("l"), "h")
        r.rows, r.status = rows, "completed"
        return r

    one = train_many.level_row(1, [run([{"epoch": 1, "epoch_s": 6, "train_frames_per_s": 4.0}])], 8.0, 10, 20)
    two = train_many.level_row(2, [run([{"epoch": 1, "epoch_s": 9, "train_frames_per_s": 2.5}])] * 2, 10.0, 10, 20)
    record = {"levels": [one, two, {"k": 4, "status": ["not run"]}]}
    train_many._speedups(record)
    assert one["steps_per_s_wall"] == 10 / 8 and one["steps_per_s_training"] == 10 / 5
    assert two["steps_per_s_wall"] == 20 / 10 and two["steps_per_s_training"] == 2 * 10 / 8
    assert two["speedup_wall"] == pytest.approx(2.0 / 1.25) and two["speedup_training"] == pytest.approx(2.5 / 2)
    assert two["time_vs_one"] == 10 / 8 and one["speedup_wall"] == 1.0
    record.update(profile="smoke", case=4, device="cpu", epochs=1, steps_per_epoch=10, image_size=32,
                  batch_size=2, threads=1, cpu_count=2)
    table = train_many.throughput_markdown(record)
    assert "| 2 | 10.0 | 1.25 | 2.00 | 1.60 | 2.50 | 1.25 | 2 of 2 |" in table and "| 4 | - |" in table


def test_default_concurrency_fills_the_cores_at_the_profiles_threads():
    cpu = torch.device("cpu")
    cores = os.cpu_count() or 1
    assert train_many.default_concurrency(cpu, {"threads": 1}, 64) == cores
    assert train_many.default_concurrency(cpu, {"threads": 1}, 1) == 1
    assert train_many.default_concurrency(cpu, {"threads": None}, 8) == 1
    assert train_many.default_concurrency(torch.device("cuda"), {"threads": None}, 20) == 8


def test_resume_continues_an_interrupted_run(tiny_root, tmp_path, capsys):
    from geodepth_lite.training import train

    out = tmp_path / "out"
    out.mkdir()
    (out / train_many.MARKER).write_text("")
    cfg = config.make_config("smoke", 4, 0, dataset=str(tiny_root), image_size=32, epochs=2)
    train.fit(cfg, out / "case4_seed0", progress=False, stop_after=1)  # stopped after epoch 1 of 2
    argv = ["train-many", *_settings(tiny_root), "--epochs", "2", "--out", str(out)]
    assert cli.main(argv) == 2 and "--resume" in capsys.readouterr().err  # not overwritten unasked
    assert _weights(out / "case4_seed0")["epoch"] == 1
    assert cli.main([*argv, "--resume"]) == 0
    ckpt = _weights(out / "case4_seed0")
    assert ckpt["epoch"] == 2 and ckpt["complete"] and [r["epoch"] for r in ckpt["history"]] == [1, 2]
    assert "resuming" in (out / "logs" / "case4_seed0.txt").read_text()


def test_a_level_that_was_not_run_does_not_stop_the_next_estimate():
    """After K = 4 was skipped for want of time, K = 8 is estimated from K = 2, the last that ran (the
    last level without a wall time raised a KeyError and lost the throughput table)."""
    levels = [{"k": 1, "wall_s": 20.0}, {"k": 2, "wall_s": 30.0}, {"k": 4, "status": ["not run"]}]
    assert train_many.time_needed(levels, 8) == pytest.approx(120.0)
    assert train_many.time_needed(levels[:1], 2) == pytest.approx(40.0)
    assert train_many.time_needed([], 1) == 0.0

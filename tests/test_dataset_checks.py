"""Dataset checks: verify on an unfinished dataset, synth's rendered/kept report, one-line file errors,
the checksum check before train and evaluate (and --no-verify)."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import save_untrained_checkpoint

from geodepth_lite import cli
from geodepth_lite.data import integrity, synth
from geodepth_lite.data import manifest as mf
from geodepth_lite.data.images import encode_npy
from geodepth_lite.training import config
from geodepth_lite.utils import FileProblem


def _complete_frames(root: Path, split: str) -> int:
    """Frames of a split with both files on disk, counted from the folder listings."""
    rgb = {p.stem for p in (root / split / "rgb").glob("*.png")}
    depth = {p.stem for p in (root / split / "depth").glob("*.npy")}
    return len(rgb & depth)


def _one_error_line(err: str) -> str:
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.fixture
def interrupted(tmp_path, monkeypatch):
    """scenario_smoke generated into tmp_path/ds and killed part-way (in the middle of the val split)."""
    m = mf.load_manifest("scenario_smoke")
    calls = {"n": 0}
    real = synth.write_files_atomic

    def dying_writer(files):
        calls["n"] += 1
        if calls["n"] == 15:  # a frame's two files are one write: train's 12 frames, val's 0 and 1, then val 2 dies
            raise KeyboardInterrupt
        real(files)

    monkeypatch.setattr(synth, "write_files_atomic", dying_writer)
    with pytest.raises(KeyboardInterrupt):
        synth.generate(m, tmp_path / "ds", progress=False)
    monkeypatch.setattr(synth, "write_files_atomic", real)
    return m, tmp_path / "ds"


def test_verify_and_synth_report_an_interrupted_dataset(interrupted, capsys):
    m, root = interrupted
    have = {split: _complete_frames(root, split) for split in m["splits"]}
    assert 0 < sum(have.values()) < sum(m["splits"].values()) and have["val"] == 2
    half = root / "val" / "depth" / f"{have['val']:06d}.npy"
    assert not half.exists()  # the interrupted frame left neither of its files
    half.write_bytes(encode_npy(np.zeros((4, 4))))  # a half frame, as a kill between the two renames leaves
    assert _complete_frames(root, "val") == have["val"]  # not counted
    assert cli.main(["verify", str(root)]) == 1
    out = capsys.readouterr().out
    assert "incomplete:" in out and "run synth again" in out
    for split, n in m["splits"].items():
        assert f"{split} {have[split]}/{n}" in out
    # (b) running synth again renders the rest and keeps what is there
    assert cli.main(["synth", "--manifest", "scenario_smoke", "--out", str(root), "--no-progress"]) == 0
    out = capsys.readouterr().out
    kept = sum(have.values())
    assert f"synth: rendered {sum(m['splits'].values()) - kept} frames, kept {kept} from an earlier run" in out
    assert str(root) in out
    assert cli.main(["verify", str(root)]) == 0


def test_verify_names_a_missing_or_unreadable_manifest(tmp_path):
    (tmp_path / "empty").mkdir()
    problems = integrity.verify(tmp_path / "empty")
    assert len(problems) == 1 and problems[0].startswith("missing: manifest.json")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "manifest.json").write_text("{not json")
    problems = integrity.verify(tmp_path / "bad")
    assert len(problems) == 1 and problems[0].startswith("unreadable: manifest.json (not valid JSON")
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(FileProblem, match="a_file"):
        integrity.verify(tmp_path / "a_file")


def test_synth_out_that_is_a_file_or_under_one_is_a_one_line_error(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("not a folder")
    assert cli.main(["synth", "--manifest", "scenario_smoke", "--out", str(f), "--no-progress"]) == 2
    err = _one_error_line(capsys.readouterr().err)
    assert str(f) in err and "a file of that name exists" in err
    assert cli.main(["synth", "--manifest", "scenario_smoke", "--out", str(f / "sub"), "--no-progress"]) == 2
    err = _one_error_line(capsys.readouterr().err)
    assert str(f / "sub") in err and "not a directory" in err.lower()
    assert f.read_text() == "not a folder"


def test_check_dataset_names_five_problems_then_counts_the_rest(smoke_root, tmp_path):
    root = Path(shutil.copytree(smoke_root, tmp_path / "ds"))
    integrity.check_dataset(root)  # intact: no error
    for i in range(7):
        (root / "train" / "rgb" / f"{i:06d}.png").unlink()
    with pytest.raises(ValueError) as exc:
        integrity.check_dataset(root)
    msg = str(exc.value)
    assert "\n" not in msg and "and 2 more" in msg and "--no-verify" in msg and "synth" in msg
    assert "missing: train/rgb/000004.png" in msg and "000005.png" not in msg


def test_check_dataset_looks_at_the_splits_that_are_used(smoke_root, tmp_path):
    root = Path(shutil.copytree(smoke_root, tmp_path / "ds"))
    (root / "test" / "rgb" / "000000.png").write_bytes(b"garbage")
    integrity.check_dataset(root, ("train", "val"))  # training reads no test frame
    with pytest.raises(ValueError, match="changed: test/rgb/000000.png"):
        integrity.check_dataset(root, ("test",))
    # a held-out set put together by hand (manifest and one split, no checksums): complete, so usable
    heldout = tmp_path / "heldout"
    heldout.mkdir()
    shutil.copy(smoke_root / "manifest.json", heldout / "manifest.json")
    shutil.copytree(smoke_root / "test", heldout / "test")
    integrity.check_dataset(heldout, ("test",))
    with pytest.raises(ValueError, match="incomplete: train 0/12 frames, val 0/6, test 6/6"):
        integrity.check_dataset(heldout)
    (heldout / "test" / "rgb" / "000005.png").unlink()
    with pytest.raises(ValueError, match="test 5/6"):
        integrity.check_dataset(heldout, ("test",))


def test_train_refuses_a_changed_dataset_and_synth_repairs_it(smoke_root, tmp_path, capsys):
    root = Path(shutil.copytree(smoke_root, tmp_path / "ds"))
    bad = root / "train" / "rgb" / "000003.png"
    bad.write_bytes(b"garbage, not a PNG")
    run_dir = tmp_path / "run"
    args = ["train", "--profile", "smoke", "--dataset", str(root), "--run-dir", str(run_dir), "--no-progress"]
    assert cli.main(args) == 2
    err = _one_error_line(capsys.readouterr().err)
    assert "changed: train/rgb/000003.png" in err and "--no-verify" in err
    assert not run_dir.exists()
    # with --no-verify the check is skipped: the damaged image itself stops training, named
    assert cli.main(args + ["--no-verify"]) == 2
    err = _one_error_line(capsys.readouterr().err)
    assert "failed verification" not in err and str(bad) in err
    # the fix the message gives: synth renders the changed frame again, byte-identical
    assert cli.main(["synth", "--manifest", str(root / "manifest.json"), "--out", str(root), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "rendered 1 frame, kept 23 from an earlier run (1 changed file rendered again)" in out
    assert bad.read_bytes() == (smoke_root / "train" / "rgb" / "000003.png").read_bytes()
    assert integrity.verify(root) == []


def test_evaluate_refuses_a_changed_dataset_unless_no_verify(smoke_root, tmp_path, capsys):
    root = Path(shutil.copytree(smoke_root, tmp_path / "ds"))
    npy = root / "test" / "depth" / "000001.npy"
    data = bytearray(npy.read_bytes())
    data[-1] ^= 0x01  # still a valid depth map, only one value changed
    npy.write_bytes(bytes(data))
    cfg = config.make_config("smoke", 4, 0, dataset=str(root), image_size=32)
    ckpt = save_untrained_checkpoint(tmp_path / "checkpoint.pt", cfg)
    out = tmp_path / "eval"
    args = ["evaluate", "--checkpoint", str(ckpt), "--dataset", str(root), "--split", "test", "--out", str(out),
            "--error-maps", "0", "--no-baselines", "--no-progress"]
    assert cli.main(args) == 2
    err = _one_error_line(capsys.readouterr().err)
    assert "changed: test/depth/000001.npy" in err and "--no-verify" in err
    assert not out.exists()
    assert cli.main(args + ["--no-verify"]) == 0, capsys.readouterr().err
    assert (out / "metrics.json").is_file()

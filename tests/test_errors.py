"""Failures as one line naming the file (exit 2, no traceback), durable and readable outputs.

One test per fault a user met: read-only and full disks, a corrupt / truncated image, a
garbage depth file, an all-NaN ground-truth frame, a NaN checkpoint, stale temporary files,
and the permissions of everything written under umask 022.
"""

import errno
import json
import os
import shutil
import stat
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import one_line_error, save_nan_checkpoint

from geodepth_lite import cli, utils
from geodepth_lite.data import bounds, datasets, synth
from geodepth_lite.data import manifest as mf
from geodepth_lite.evaluation import baselines, evaluate
from geodepth_lite.training import checkpoint, config, train


@pytest.fixture
def smoke_copy(smoke_root, tmp_path):
    """A private copy of the smoke dataset, safe to damage."""
    return Path(shutil.copytree(smoke_root, tmp_path / "smoke"))


def _first(root: Path, split: str) -> dict:
    return json.loads((root / split / "frames.jsonl").read_text().splitlines()[0])


def _fail_with(monkeypatch, code: int, where: str = "fsync"):
    """Every atomic write fails with OSError ``code`` (at the data flush, or at the temp file's creation)."""
    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    if where == "fsync":
        monkeypatch.setattr(utils.os, "fsync", fail)
    else:
        monkeypatch.setattr(utils.tempfile, "mkstemp", fail)


# --------------------------------------------------------------------------- full and read-only disks


@pytest.mark.parametrize("code, reason, where", [(errno.EROFS, "read-only file system", "mkstemp"),
                                                 (errno.ENOSPC, "no space left on device", "fsync")])
def test_synth_on_a_read_only_or_full_disk(tmp_path, monkeypatch, capsys, code, reason, where):
    _fail_with(monkeypatch, code, where)
    out = tmp_path / "data"
    assert cli.main(["synth", "--manifest", "scenario_smoke", "--out", str(out), "--no-progress"]) == 2
    one_line_error(capsys, "error: cannot write", str(out), reason)


@pytest.mark.parametrize("code, reason, where", [(errno.EROFS, "read-only file system", "mkstemp"),
                                                 (errno.ENOSPC, "no space left on device", "fsync")])
def test_train_on_a_read_only_or_full_disk(smoke_root, tmp_path, monkeypatch, capsys, code, reason, where):
    run = tmp_path / "run"
    _fail_with(monkeypatch, code, where)
    argv = ["train", "--profile", "smoke", "--dataset", str(smoke_root), "--image-size", "32", "--run-dir", str(run),
            "--no-progress", "--no-verify"]
    assert cli.main(argv) == 2
    # read-only: found by the probe before any work; full: at the flush of the run folder's mark, written first
    one_line_error(capsys, "error: cannot write", str(run if where == "mkstemp" else run / checkpoint.RUN_MARK),
                   reason)
    assert not (run / "checkpoint.pt").exists()
    if where == "fsync":  # a folder marked before: at the first checkpoint's flush
        run.mkdir()  # (the refused run removed the folder it made)
        (run / checkpoint.RUN_MARK).write_text("written by python -m geodepth_lite train\n")
        assert cli.main(argv) == 2
        one_line_error(capsys, "error: cannot write", str(run / "checkpoint.pt"), reason)
        assert not (run / "checkpoint.pt").exists()


def test_train_into_a_run_dir_that_is_a_file_stops_before_training(smoke_root, tmp_path, capsys):
    run = tmp_path / "run"
    run.write_text("keep me")
    argv = ["train", "--profile", "smoke", "--dataset", str(smoke_root), "--image-size", "32", "--run-dir", str(run),
            "--no-progress", "--no-verify"]
    assert cli.main(argv) == 2
    one_line_error(capsys, "cannot create folder", str(run), "a file of that name exists")
    assert run.read_text() == "keep me"


def test_predict_on_a_read_only_disk_and_into_a_file(smoke_root, tmp_path, monkeypatch, capsys, untrained_checkpoint):
    images = smoke_root / "test" / "rgb"
    not_a_folder = tmp_path / "out.txt"
    not_a_folder.write_text("keep me")
    argv = ["predict", "--checkpoint", str(untrained_checkpoint), "--input", str(images), "--no-progress"]
    assert cli.main(argv + ["--out", str(not_a_folder)]) == 2
    one_line_error(capsys, "cannot create folder", str(not_a_folder), "a file of that name exists")
    assert not_a_folder.read_text() == "keep me"
    _fail_with(monkeypatch, errno.EROFS, "mkstemp")
    out = tmp_path / "pred"
    assert cli.main(argv + ["--out", str(out)]) == 2
    one_line_error(capsys, "error: cannot write", str(out), "read-only file system")


def test_debug_shows_the_traceback(tmp_path, capsys, monkeypatch):
    not_a_folder = tmp_path / "f"
    not_a_folder.write_text("")
    argv = ["predict", "--checkpoint", str(tmp_path / "none.pt"), "--input", str(tmp_path), "--out", str(tmp_path)]
    assert cli.main(argv) == 2
    assert "Traceback" not in capsys.readouterr().err
    monkeypatch.setenv(cli.DEBUG_ENV, "1")
    assert cli.main(argv) == 2
    assert "Traceback" in capsys.readouterr().err
    monkeypatch.delenv(cli.DEBUG_ENV)
    assert cli.main(["predict", "--debug", *argv[1:]]) == 2
    assert "Traceback" in capsys.readouterr().err


# --------------------------------------------------------------------------- damaged dataset files


def _damage(root: Path, kind: str) -> Path:
    rec = _first(root, "train")
    if kind == "garbage png":
        path = root / rec["rgb"]
        path.write_bytes(b"this is not a PNG at all" * 20)
    elif kind == "truncated png":
        path = root / rec["rgb"]
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 3])
    else:  # garbage npy
        path = root / rec["depth"]
        path.write_bytes(b"\x00garbage" * 50)
    return path


@pytest.mark.parametrize("kind, reason", [("garbage png", "not an image file"),
                                          ("truncated png", "truncated"),
                                          ("garbage npy", "not a .npy file")])
def test_a_damaged_dataset_file_is_named(smoke_copy, tmp_path, capsys, kind, reason):
    bad = _damage(smoke_copy, kind)
    with pytest.raises(utils.FileProblem, match=reason) as info:  # whoever reads it: the Dataset
        datasets.SyntheticDepthDataset(smoke_copy, "train")[0]
    assert info.value.path == bad
    run = tmp_path / "run"
    argv = ["train", "--profile", "smoke", "--dataset", str(smoke_copy), "--image-size", "32", "--run-dir", str(run),
            "--no-progress"]
    assert cli.main(argv + ["--no-verify"]) == 2  # read during training
    one_line_error(capsys, "error: cannot read", str(bad), reason)
    assert cli.main(argv) == 2  # caught before training, by the checksums
    one_line_error(capsys, bad.name, "--no-verify")
    assert not (run / "checkpoint.pt").exists()


@pytest.mark.parametrize("huge", [np.full((1,), 2**63, np.uint64), np.full((1,), 1e30, np.float32),
                                  np.full((1,), -1e300, np.float64), np.full((1,), 1.5e6, np.float32)])
def test_a_depth_map_with_a_depth_beyond_its_bound_is_named(smoke_copy, tmp_path, capsys, huge):
    """A finite depth beyond bounds.MAX_DEPTH_VALUE is refused in one line naming the file: before, a uint64
    2^63 trained a whole run on a loss of 3.5e18 and reported it as finished. NaN and inf still pass (they
    mark pixels without depth), and so does a depth just inside the bound."""
    rec = _first(smoke_copy, "train")
    path = smoke_copy / rec["depth"]
    shape = np.load(path).shape
    depth = np.ones(shape, huge.dtype)
    depth[0, :1] = huge
    np.save(path, depth)
    with pytest.raises(utils.FileProblem, match="beyond the 1e\\+06 a depth map may hold") as info:
        datasets.SyntheticDepthDataset(smoke_copy, "train")[0]
    assert info.value.path == path
    with pytest.raises(utils.FileProblem, match="beyond the 1e\\+06"):
        baselines.fit_mean_depth_map(smoke_copy, "train")
    run = tmp_path / "run"
    argv = ["train", "--profile", "smoke", "--dataset", str(smoke_copy), "--image-size", "32", "--run-dir", str(run),
            "--no-progress", "--no-verify"]
    assert cli.main(argv) == 2
    one_line_error(capsys, "error: cannot use", str(path), "beyond the 1e+06")
    assert not (run / "checkpoint.pt").exists()
    depth = np.ones(shape, np.float32)
    depth[0, :3] = [np.nan, np.inf, bounds.MAX_DEPTH_VALUE]
    np.save(path, depth)
    assert float(datasets.SyntheticDepthDataset(smoke_copy, "train")[0]["depth"][0, 0, 2]) == 1e6


def test_a_damaged_public_dataset_file_is_named(tmp_path):
    folder = tmp_path / "T1_L1_1_resized"
    folder.mkdir()
    rgb = np.full((16, 16, 3), 120, np.uint8)
    from PIL import Image

    Image.fromarray(rgb).save(folder / "FrameBuffer_0000.png")
    (folder / "Depth_0000.png").write_bytes(b"garbage, not a PNG")
    ds = datasets.open_dataset("colondepth", tmp_path)
    with pytest.raises(utils.FileProblem, match="Depth_0000.png") as info:
        ds[0]
    assert info.value.path == folder / "Depth_0000.png"


# --------------------------------------------------------------------------- evaluation per frame


def test_an_all_nan_ground_truth_frame_is_skipped_and_named(smoke_copy, tmp_path):
    rec = _first(smoke_copy, "test")
    shape = np.load(smoke_copy / rec["depth"]).shape
    np.save(smoke_copy / rec["depth"], np.full(shape, np.nan, np.float32))
    ds = evaluate.open_eval_dataset(str(smoke_copy), split="test")
    with pytest.warns(UserWarning, match=rf"skipping frame 0 \({rec['rgb']}\): no valid ground-truth pixel"):
        result = evaluate.evaluate_predictor(lambda x: torch.ones(x.shape[0], *x.shape[-2:]), ds,
                                             out_dir=tmp_path / "eval", error_maps=0, name="constant")
    assert result["n"] == len(ds) - 1 and result["skipped"] == [f"0 ({rec['rgb']})"]
    assert np.isfinite(result["overall"]["abs_rel"])
    rows = (tmp_path / "eval" / "frames.csv").read_text().splitlines()
    assert len(rows) == len(ds) + 1 and rows[1].endswith("no valid ground-truth pixel")
    assert "1 skipped (no valid ground-truth pixel)" in (tmp_path / "eval" / "tables.md").read_text()
    for line in (smoke_copy / "test" / "frames.jsonl").read_text().splitlines():  # every frame NaN: an error
        np.save(smoke_copy / json.loads(line)["depth"], np.full(shape, np.nan, np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match=f"no frame of the {len(ds)} evaluated has a valid ground-truth pixel"):
            evaluate.evaluate_predictor(lambda x: torch.ones(x.shape[0], *x.shape[-2:]),
                                        evaluate.open_eval_dataset(str(smoke_copy), split="test"), error_maps=0)


# --------------------------------------------------------------------------- non-finite models


def test_a_nan_checkpoint_is_refused_and_nothing_is_written(smoke_root, tmp_path, capsys):
    ckpt = save_nan_checkpoint(tmp_path / "nan.pt")
    with pytest.raises(ValueError, match="non-finite weights"):
        checkpoint.load_model(ckpt)
    out = tmp_path / "pred"
    argv = ["predict", "--checkpoint", str(ckpt), "--input", str(smoke_root / "test" / "rgb"), "--out", str(out),
            "--no-progress"]
    assert cli.main(argv) == 2
    one_line_error(capsys, str(ckpt), "non-finite weights")
    assert not out.exists() or not any(out.iterdir())
    argv = ["evaluate", "--checkpoint", str(ckpt), "--dataset", str(smoke_root), "--out", str(tmp_path / "eval"),
            "--no-progress", "--no-verify"]
    assert cli.main(argv) == 2
    one_line_error(capsys, str(ckpt), "non-finite weights")
    assert not (tmp_path / "eval").exists()


def test_a_model_that_predicts_nan_writes_nothing(smoke_root, tmp_path, capsys, monkeypatch, untrained_checkpoint):
    from geodepth_lite.apps import predict

    monkeypatch.setattr(predict, "predict_frames",
                        lambda m, frames, s, flips="none": [np.full(f.shape[:2], np.nan) for f in frames])
    out = tmp_path / "pred"
    argv = ["predict", "--checkpoint", str(untrained_checkpoint), "--input", str(smoke_root / "test" / "rgb"),
            "--out", str(out), "--no-progress"]
    assert cli.main(argv) == 2
    one_line_error(capsys, str(untrained_checkpoint), "non-finite depth")
    assert not list(out.glob("*"))
    ds = evaluate.open_eval_dataset(str(smoke_root), split="test")
    with pytest.raises(evaluate.NonFiniteDepth, match="non-finite depth"):
        evaluate.evaluate_predictor(lambda x: torch.full((x.shape[0], *x.shape[-2:]), float("nan")), ds,
                                    out_dir=tmp_path / "eval", error_maps=0, name="nan")
    assert not (tmp_path / "eval").exists()


# --------------------------------------------------------------------------- interrupted writes, resume


def test_stale_checkpoint_temp_files_are_removed_and_resume_names_its_epoch(smoke_root, tmp_path, capsys):
    cfg = config.make_config("smoke", 1, 0, dataset=str(smoke_root), image_size=32, epochs=2)
    run = tmp_path / "run"
    train.fit(cfg, run, progress=False, stop_after=1)
    stale = run / ".geodepth-4194305-checkpoint.pt.k1ll3d.tmp"  # no process can have PID 2**22 + 1
    stale.write_bytes(b"\x00" * 4096)  # what a kill during torch.save leaves
    capsys.readouterr()
    train.fit(cfg, run, resume=True, progress=False)
    out = capsys.readouterr().out
    assert not stale.exists() and not list(run.glob(utils.TEMP_GLOB))
    assert "removed 1 half-written temporary file" in out and "after epoch 1/2" in out
    assert checkpoint.read_checkpoint(run / "checkpoint.pt")["epoch"] == 2


def test_atomic_writes_flush_the_data_then_the_folder(tmp_path, monkeypatch):
    synced = []
    real_fsync = os.fsync

    def spy(fd):
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        real_fsync(fd)

    monkeypatch.setattr(utils.os, "fsync", spy)
    utils.write_bytes_atomic(tmp_path / "a.bin", b"data")
    assert synced == [False, True]  # the file before the rename, its folder after
    assert (tmp_path / "a.bin").read_bytes() == b"data"


# --------------------------------------------------------------------------- permissions


def test_outputs_are_readable_by_others_under_umask_022(smoke_root, tmp_path, untrained_checkpoint):
    old = os.umask(0o022)
    try:
        data = Path(synth.generate(mf.load_manifest("scenario_smoke"), tmp_path / "data", progress=False))
        cfg = config.make_config("smoke", 1, 0, dataset=str(smoke_root), image_size=32)
        run = tmp_path / "run"
        train.fit(cfg, run, progress=False)
        pred = tmp_path / "pred"
        assert cli.main(["predict", "--checkpoint", str(untrained_checkpoint), "--input",
                         str(smoke_root / "test" / "rgb"), "--out", str(pred), "--no-progress"]) == 0
    finally:
        os.umask(old)
    files = [p for folder in (data, run, pred) for p in folder.rglob("*") if p.is_file()]
    assert len(files) > 30
    modes = {p: stat.S_IMODE(p.stat().st_mode) for p in files}
    assert {oct(m) for m in modes.values()} == {"0o644"}, {str(p): oct(m) for p, m in modes.items() if m != 0o644}

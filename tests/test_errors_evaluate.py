"""``evaluate`` under hostile conditions: one ``error:`` line naming the file (exit 2), nothing unpickled,
--out checked before any work, and its result files written as one set or none.

One test per fault a review found: a pickled training depth file read by the mean-depth-map
baseline, --out checked only after the evaluation, metrics.json left without frames.csv on a
full disk, "file exists: X" / "read-only file system: X" outside the one-line format, and a
crafted checkpoint.
"""

import csv
import errno
import json
import os
import pickle
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
from conftest import one_line_error

from geodepth_lite import cli, utils
from geodepth_lite.evaluation import baselines, evaluate, tables
from geodepth_lite.training import checkpoint


class RunsCode:
    """Unpickling this creates the folder ``marker``: proof that a loader ran code from a file."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.mkdir, (str(self.marker),)


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every entry under ``folder`` (hidden ones too): {relative path: bytes, or "<dir>" for folders}."""
    return {str(p.relative_to(folder)): (b"<dir>" if p.is_dir() else p.read_bytes())
            for p in sorted(folder.rglob("*"))}


def _evaluate_argv(ckpt: Path, root: Path, out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--checkpoint", str(ckpt), "--dataset", str(root), "--split", "test", "--out", str(out),
            "--no-progress", "--no-verify", *extra]


def _fail_nth_file_flush(monkeypatch, n: int, code: int = errno.ENOSPC) -> list:
    """The ``n``-th fsync of a regular file (the flush of the n-th file written) fails with ``code``."""
    real_fsync = os.fsync
    files = []

    def fsync(fd):
        if not stat.S_ISDIR(os.fstat(fd).st_mode):
            files.append(fd)
            if len(files) == n:
                raise OSError(code, os.strerror(code))
        real_fsync(fd)

    monkeypatch.setattr(utils.os, "fsync", fsync)
    return files


def _no_model_loading(monkeypatch):
    """Loading a model fails the test: the command had to stop before it."""
    def refuse(*args, **kwargs):
        raise AssertionError("the model was loaded before --out was checked")

    monkeypatch.setattr(checkpoint, "load_model", refuse)


@pytest.fixture
def smoke_copy(smoke_root, tmp_path):
    """A private copy of the smoke dataset, safe to damage."""
    return Path(shutil.copytree(smoke_root, tmp_path / "smoke"))


# --------------------------------------------------------------------------- 1. pickled depth files


def _pickled_depth(path: Path, kind: str, marker: Path) -> None:
    """Replace a depth file by pickled data that would create ``marker`` if unpickled."""
    if kind == "object array in a .npy":
        np.save(path, np.array([RunsCode(marker), 1.0], dtype=object), allow_pickle=True)
    else:  # a plain pickle saved under the .npy name: what np.load calls "pickled (object) data"
        path.write_bytes(pickle.dumps(RunsCode(marker)))


@pytest.mark.parametrize("kind, reason", [("object array in a .npy", "it holds pickled Python objects, never loaded"),
                                          ("plain pickle", "not a .npy file")])
def test_a_pickled_train_depth_file_is_named_and_never_unpickled(smoke_copy, untrained_checkpoint, tmp_path, capsys,
                                                                  kind, reason):
    rec = json.loads((smoke_copy / "train" / "frames.jsonl").read_text().splitlines()[0])
    bad, marker = smoke_copy / rec["depth"], tmp_path / "code-ran"
    _pickled_depth(bad, kind, marker)
    with pytest.raises(utils.FileProblem, match=reason) as info:  # the mean-depth-map baseline reads it
        baselines.fit_mean_depth_map(smoke_copy, "train")
    assert info.value.path == bad
    out = tmp_path / "eval"
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_copy, out, "--error-maps", "0")) == 2
    line = one_line_error(capsys, f"error: cannot read {bad}: {reason}")
    assert "unsafe" not in line and "pickle.load" not in line, line  # no invitation to load it unsafely
    assert not marker.exists()
    assert not out.exists()  # the folder checked before the work is removed again


# --------------------------------------------------------------------------- 2 and 4. --out checked first


def test_out_that_is_a_file_is_refused_before_the_model_loads(smoke_root, untrained_checkpoint, tmp_path,
                                                               monkeypatch, capsys):
    _no_model_loading(monkeypatch)
    out = tmp_path / "results.txt"
    out.write_text("keep me")
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out)) == 2
    one_line_error(capsys, f"error: cannot write {out}: a file of that name exists")
    assert out.read_text() == "keep me"
    inside = out / "eval"  # a folder under a file: not "not a directory: ..." outside the format either
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, inside)) == 2
    one_line_error(capsys, f"error: cannot write {inside}: ")
    assert out.read_text() == "keep me"


@pytest.mark.parametrize("existing", [False, True], ids=["new folder", "existing folder"])
def test_a_read_only_out_is_refused_before_the_model_loads(smoke_root, untrained_checkpoint, tmp_path,
                                                           monkeypatch, capsys, existing):
    out = tmp_path / "a" / "eval"
    if existing:  # an earlier evaluation's folder
        out.mkdir(parents=True)
        (out / "metrics.json").write_text("{}\n")
        (out / tables.MARKER).write_text("written by python -m geodepth_lite evaluate\n")
    _no_model_loading(monkeypatch)
    monkeypatch.setattr(utils.tempfile, "mkstemp", lambda *a, **k: (_ for _ in ()).throw(
        OSError(errno.EROFS, os.strerror(errno.EROFS))))  # root ignores chmod: a read-only disk simulated
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out)) == 2
    one_line_error(capsys, f"error: cannot write {out}: read-only file system")
    if existing:
        assert _snapshot(out) == {"metrics.json": b"{}\n",
                                  tables.MARKER: b"written by python -m geodepth_lite evaluate\n"}
    else:
        assert not (tmp_path / "a").exists()  # no empty folder left behind


def test_a_full_disk_is_refused_before_the_model_loads(smoke_root, untrained_checkpoint, tmp_path, monkeypatch,
                                                       capsys):
    _no_model_loading(monkeypatch)
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=2**20))  # 1 MB free
    out = tmp_path / "eval"
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "4")) == 2
    line = one_line_error(capsys, f"error: cannot write {out}: no space left on device", "1.0 MB free")
    assert f"{tables.output_bytes_needed(4) / 2**20:.1f} MB needed" in line
    assert not out.exists()


def test_a_run_that_fails_later_removes_the_folder_it_created_only(smoke_root, tmp_path, capsys):
    missing = tmp_path / "missing.pt"
    out = tmp_path / "new" / "eval"
    assert cli.main(_evaluate_argv(missing, smoke_root, out)) == 2
    one_line_error(capsys, "checkpoint not found", str(missing))
    assert not (tmp_path / "new").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    assert cli.main(_evaluate_argv(missing, smoke_root, kept)) == 2
    assert kept.is_dir()  # the user's own (empty) folder stays


# --------------------------------------------------------------------------- 3. one set of files, or none


def _frames_mean(out: Path, metric: str = "abs_rel") -> float:
    rows = list(csv.DictReader((out / "frames.csv").open()))
    return float(np.mean([float(r[metric]) for r in rows if not r["skipped"]]))


def test_a_full_disk_at_the_second_file_leaves_no_partial_set(smoke_root, untrained_checkpoint, tmp_path,
                                                               monkeypatch, capsys):
    out = tmp_path / "eval"
    flushed = _fail_nth_file_flush(monkeypatch, 2)
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "2")) == 2
    one_line_error(capsys, f"error: cannot write {out / 'frames.csv'}: no space left on device")
    assert len(flushed) == 2  # metrics.json was written (into staging), frames.csv failed
    assert not out.exists()  # not metrics.json alone, nor a hidden staging folder, nor an empty folder


@pytest.mark.parametrize("nth", [2, 4, 5], ids=["frames.csv", "first error map", "last error map"])
def test_a_failed_run_keeps_the_earlier_set_whole(smoke_root, untrained_checkpoint, tmp_path, monkeypatch, capsys,
                                                  nth):
    out = tmp_path / "eval"
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "1", "--no-baselines")) == 0
    (out / "notes.txt").write_text("the user's own file")
    before = _snapshot(out)
    assert len(list((out / "error_maps").glob("*.png"))) == 1
    capsys.readouterr()
    _fail_nth_file_flush(monkeypatch, nth)  # a different run: two error maps, with baselines
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "2")) == 2
    one_line_error(capsys, f"error: cannot write {out}", "no space left on device")
    assert _snapshot(out) == before  # byte for byte, and no hidden staging folder


def test_a_new_set_replaces_the_old_one_whole(smoke_root, untrained_checkpoint, tmp_path, capsys):
    out = tmp_path / "eval"
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "3", "--no-baselines")) == 0
    old = json.loads((out / "metrics.json").read_text())
    (out / "notes.txt").write_text("the user's own file")
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "1", "--flips", "hv")) == 0
    new = json.loads((out / "metrics.json").read_text())
    assert new["overall"]["abs_rel"] != old["overall"]["abs_rel"] and "baselines" in new and "baselines" not in old
    assert new["overall"]["abs_rel"] == pytest.approx(_frames_mean(out), rel=1e-5)  # the files belong together
    assert "baseline: constant" in (out / "tables.md").read_text()
    assert len(list((out / "error_maps").glob("*.png"))) == 1  # none of the old run's three maps is left
    assert sorted(p.name for p in out.iterdir()) == [tables.MARKER, "error_maps", "frames.csv", "metrics.json",
                                                     "notes.txt", "tables.md"]


def test_a_folder_evaluate_did_not_write_is_refused_and_kept(smoke_root, untrained_checkpoint, tmp_path,
                                                             monkeypatch, capsys):
    """A user's folder holding files of evaluate's names (metrics.json, error_maps/), or any other file: exit 2
    before the model loads, nothing in it changed; a killed run's hidden staging folder does not count."""
    _no_model_loading(monkeypatch)
    theirs = tmp_path / "mine"
    (theirs / "error_maps").mkdir(parents=True)
    (theirs / "metrics.json").write_text("my own numbers")
    (theirs / "error_maps" / "holiday.png").write_bytes(b"a photo")
    before = _snapshot(theirs)
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, theirs)) == 2
    one_line_error(capsys, f"error: cannot write into {theirs}: the folder holds files evaluate did not write "
                           "(error_maps, ...)")
    assert _snapshot(theirs) == before
    tracked = utils.checkout_path("notebooks", "gallery")  # a folder of the checkout's tracked files
    before = _snapshot(tracked)
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, tracked)) == 2
    one_line_error(capsys, f"error: cannot write into {tracked}: the folder holds files evaluate did not write")
    assert _snapshot(tracked) == before
    left = tmp_path / "killed"
    (left / f"{tables.STAGING_PREFIX}x1").mkdir(parents=True)
    monkeypatch.undo()
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, left, "--no-baselines")) == 0
    assert (left / tables.MARKER).is_file() and (left / "metrics.json").is_file()


def test_a_failed_swap_puts_the_earlier_set_back(smoke_root, untrained_checkpoint, tmp_path, monkeypatch, capsys):
    out = tmp_path / "eval"
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "2", "--no-baselines")) == 0
    before = _snapshot(out)
    capsys.readouterr()
    real_replace = os.replace
    swapped = []

    def replace(src, dst, **kwargs):  # the second rename of a new file into --out fails
        if Path(src).parent.name.startswith(tables.STAGING_PREFIX) and Path(dst).parent == out:
            swapped.append(dst)
            if len(swapped) == 2:
                raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real_replace(src, dst, **kwargs)

    monkeypatch.setattr(utils.os, "replace", replace)
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_root, out, "--error-maps", "1", "--flips", "h")) == 2
    one_line_error(capsys, f"error: cannot write {out}: input/output error", "the previous results are kept")
    assert _snapshot(out) == before


def test_write_results_for_the_notebooks_is_one_set_too(smoke_root, tmp_path, monkeypatch):
    import torch

    ds = evaluate.open_eval_dataset(str(smoke_root), split="test")
    out = tmp_path / "eval"

    def constant(x):
        return torch.ones(x.shape[0], *x.shape[-2:])

    _fail_nth_file_flush(monkeypatch, 3)  # tables.md
    with pytest.raises(utils.FileProblem, match="no space left on device") as info:
        evaluate.evaluate_predictor(constant, ds, out_dir=out, error_maps=1, name="constant")
    assert info.value.path == out / "tables.md"
    assert not out.exists()
    monkeypatch.undo()
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("keep me")
    with pytest.raises(utils.FileProblem, match=f"cannot write {not_a_folder}: a file of that name exists"):
        evaluate.evaluate_predictor(constant, ds, out_dir=not_a_folder, error_maps=0)
    assert not_a_folder.read_text() == "keep me"


# --------------------------------------------------------------------------- 5. checkpoints


@pytest.mark.parametrize("kind", ["torch.save", "plain pickle"])
def test_a_crafted_checkpoint_runs_no_code(smoke_root, tmp_path, monkeypatch, capsys, kind):
    import torch

    marker = tmp_path / "code-ran"
    ckpt = tmp_path / "checkpoint.pt"
    payload = {"model": {}, "cfg": {"image_size": 32}, "evil": RunsCode(marker)}
    if kind == "torch.save":
        torch.save(payload, ckpt)
    else:
        ckpt.write_bytes(pickle.dumps(payload))
    read = []
    real_read = checkpoint.read_checkpoint
    monkeypatch.setattr(checkpoint, "read_checkpoint", lambda path, **kw: read.append(Path(path)) or real_read(path,
                                                                                                                **kw))
    out = tmp_path / "eval"
    assert cli.main(_evaluate_argv(ckpt, smoke_root, out)) == 2
    one_line_error(capsys, f"checkpoint {ckpt}")
    assert read == [ckpt]  # evaluate reads checkpoints through checkpoint.read_checkpoint only
    assert not marker.exists()
    assert not out.exists()

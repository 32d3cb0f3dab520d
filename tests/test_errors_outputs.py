"""What the commands write: never the user's files, one writer per output folder, and a class bundle
checked before it is read and read before anything is written.

One test per finding of a review: ``exercises --out notebooks`` replacing the solutions, a student's
edited notebook overwritten, two writers in one output folder (evaluate, predict, unbundle,
exercises, train; reproduce waits), a zip bomb or a 4 GiB bundle.json read whole, a refused bundle
leaving files behind, logs replaced, a killed unpack's temporary file surviving, a member name that
reads ./pyproject.toml, ``.notes.tmp`` deleted, and tracebacks instead of one ``error:`` line.
Every hostile file is built here.
"""

import errno
import functools
import hashlib
import io
import json
import os
import struct
import subprocess
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import one_line_error
from PIL import Image

from geodepth_lite import cli, utils
from geodepth_lite.apps import bundle
from geodepth_lite.core.model import DepthNet
from geodepth_lite.evaluation import tables
from geodepth_lite.training import checkpoint
from geodepth_lite.workbook import exercises

DEAD_PID = 2**22 + 1  # above Linux's largest pid_max: no process can have it
RUN = "case1_seed0-0123abcd"


@functools.lru_cache(maxsize=None)
def _ckpt_bytes(value: float = 0.0) -> bytes:
    """A checkpoint that ``checkpoint.read_checkpoint`` accepts and that fits DepthNet (``unbundle`` checks
    both): a seeded untrained network whose first weight tensor is filled with ``value``."""
    torch.manual_seed(0)
    state = DepthNet().state_dict()
    next(v for v in state.values() if v.is_floating_point()).fill_(value)
    buf = io.BytesIO()
    torch.save({"model": state, "cfg": {"image_size": 32}, "epoch": 1, "complete": True}, buf)
    return buf.getvalue()


def _bundle(path: Path, members: dict[str, bytes], *, profile="smoke", runs=None, index=None,
            compression=zipfile.ZIP_STORED) -> Path:
    """A bundle of ``members`` with a matching bundle.json (or ``index`` as given)."""
    if runs is None:
        runs = sorted({n.split("/")[1] for n in members if n.startswith("checkpoints/")})
    if index is None:
        index = {"format": bundle.BUNDLE_FORMAT, "profile": profile, "runs": runs,
                 "files": {n: hashlib.sha256(b).hexdigest() for n, b in members.items()}}
    with zipfile.ZipFile(path, "w", compression=compression) as zf:
        for name, blob in members.items():
            zf.writestr(name, blob)
        zf.writestr(bundle.INDEX, index if isinstance(index, bytes) else json.dumps(index))
    return path


def _patch_central(path: Path, name: str, offset: int, fmt: str, value: int) -> None:
    """Overwrite a field of ``name``'s entry in the zip's central directory (the data stays as it is)."""
    data = bytearray(path.read_bytes())
    pos = data.find(b"PK\x01\x02")
    while pos >= 0:
        n = struct.unpack_from("<H", data, pos + 28)[0]
        if bytes(data[pos + 46:pos + 46 + n]) == name.encode():
            struct.pack_into(fmt, data, pos + offset, value)
            path.write_bytes(bytes(data))
            return
        pos = data.find(b"PK\x01\x02", pos + 4)
    raise AssertionError(f"{name} not in the central directory")


def _runs(home_root: Path) -> Path:
    return home_root / "runs" / "smoke" / "checkpoints"


@pytest.fixture
def home(tmp_path, monkeypatch) -> Path:
    h = tmp_path / "student"
    monkeypatch.setenv("GEODEPTH_LITE_HOME", str(h))
    return h


@pytest.fixture
def streamed(monkeypatch) -> list[str]:
    """The names of the bundle members unbundle reads (every read goes through ``bundle._stream``)."""
    names, real = [], bundle._stream

    def spy(zf, info, path, sink=None):
        names.append(info.filename)
        return real(zf, info, path, sink)

    monkeypatch.setattr(bundle, "_stream", spy)
    return names


def _good_members(value=0.0) -> dict[str, bytes]:
    return {f"checkpoints/{RUN}/checkpoint.pt": _ckpt_bytes(value), f"checkpoints/{RUN}/log.json": b'{"epochs": []}\n'}


# --------------------------------------------------------------------------- 1. exercises --out


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_exercises_never_writes_into_the_notebooks_folder_even_with_force(capsys):
    before = _tree(exercises.NOTEBOOK_DIR)
    for extra in ([], ["--force"]):
        assert cli.main(["exercises", "--out", str(exercises.NOTEBOOK_DIR), *extra]) == 2
        one_line_error(capsys, str(exercises.NOTEBOOK_DIR), "notebooks folder")
    assert cli.main(["exercises", "--out", str(exercises.NOTEBOOK_DIR / "student")]) == 2  # nor inside it
    one_line_error(capsys, "notebooks folder")
    assert _tree(exercises.NOTEBOOK_DIR) == before and not (exercises.NOTEBOOK_DIR / "student").exists()


def test_exercises_never_writes_into_a_folder_of_tracked_files(capsys):
    root = utils.project_root()
    if root is None or subprocess.run(["git", "-C", str(root), "ls-files", "--", "docs"], capture_output=True,
                                      text=True).stdout.strip() == "":
        pytest.skip("not a git checkout")
    before = _tree(root / "docs")
    assert cli.main(["exercises", "--out", str(root / "docs"), "--force"]) == 2
    one_line_error(capsys, str(root / "docs"), "tracked by git")
    assert _tree(root / "docs") == before


def test_exercises_keeps_a_students_edited_notebook_unless_forced(tmp_path, capsys):
    out = tmp_path / "release"
    out.mkdir()
    name = exercises.notebook_paths()[0].name
    (out / name).write_text("my answers")
    assert cli.main(["exercises", "--out", str(out)]) == 2
    one_line_error(capsys, str(out), "not empty", "--force")
    assert (out / name).read_text() == "my answers" and sorted(os.listdir(out)) == [name]
    exercises.check_release_folder(out, force=True)  # --force: an earlier release may be replaced


# --------------------------------------------------------------------------- 2. one writer per output folder


@pytest.fixture
def held(tmp_path):
    """Hold ``utils.FolderLock`` on folders from this process (as another command would): call it with a
    folder; every lock is released at the end. The holder's PID is this process's."""
    locks = []

    def hold(folder: Path) -> int:
        locks.append(utils.FolderLock(folder).acquire())
        return os.getpid()

    yield hold
    for lock in locks:
        lock.release()


def test_a_second_evaluate_into_one_folder_is_refused_and_the_first_ones_files_stay(
        held, untrained_checkpoint, tmp_path, capsys):
    out = tmp_path / "eval"
    out.mkdir()
    (out / "metrics.json").write_text('{"earlier": 1}')
    utils.mark_folder(out, tables.MARKER, "evaluate")  # the first evaluation's folder
    pid = held(out)
    argv = ["evaluate", "--checkpoint", str(untrained_checkpoint), "--dataset", str(tmp_path / "data"),
            "--out", str(out), "--no-progress", "--no-verify"]
    assert cli.main(argv) == 2
    one_line_error(capsys, str(out), f"in use by process {pid}")
    assert (out / "metrics.json").read_text() == '{"earlier": 1}'


def test_a_second_predict_into_one_folder_is_refused(held, untrained_checkpoint, tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    Image.fromarray(np.zeros((24, 24, 3), np.uint8)).save(src / "a.png")
    out = tmp_path / "out"
    pid = held(out)
    theirs = out / f".geodepth-{pid}-a_depth.npy.inflight.tmp"  # the holder's write in progress
    theirs.write_bytes(b"\x00" * 64)
    assert cli.main(["predict", "--checkpoint", str(untrained_checkpoint), "--input", str(src), "--out", str(out),
                     "--no-progress"]) == 2
    one_line_error(capsys, str(out), f"in use by process {pid}")
    assert theirs.exists() and sorted(p.name for p in out.iterdir()) == sorted([".lock", theirs.name])


def test_unbundle_into_a_run_folder_held_by_train_is_refused(held, home, tmp_path, capsys):
    good = _bundle(tmp_path / "b.zip", _good_members())
    run = _runs(home) / RUN
    pid = held(run)  # what checkpoint.run_folder takes for a training run
    assert cli.main(["unbundle", str(good)]) == 2
    one_line_error(capsys, str(run), f"in use by process {pid}")
    assert sorted(os.listdir(run)) == [".lock"]


def test_a_second_exercises_into_one_folder_is_refused(held, tmp_path, capsys):
    out = tmp_path / "release"
    pid = held(out)
    assert cli.main(["exercises", "--out", str(out)]) == 2
    one_line_error(capsys, str(out), f"in use by process {pid}")
    assert sorted(os.listdir(out)) == [".lock"]


def test_a_second_train_into_one_run_folder_is_refused(held, tmp_path, capsys):
    run = tmp_path / "run"
    pid = held(run)
    assert cli.main(["train", "--profile", "smoke", "--case", "1", "--dataset", str(tmp_path / "data"),
                     "--run-dir", str(run), "--no-progress", "--no-verify"]) == 2
    one_line_error(capsys, str(run), f"in use by process {pid}")


def test_a_second_reproduce_waits_for_the_first_then_gives_up_after_the_longest_wait(
        held, home, capsys, monkeypatch):
    folder = home / "runs" / "smoke"
    pid = held(folder)
    monkeypatch.setenv(utils.LOCK_WAIT_ENV, "0.3")
    assert cli.main(["reproduce", "--profile", "smoke", "--no-progress"]) == 2
    captured = capsys.readouterr()
    assert f"waiting for reproduce (PID {pid}) holding {folder.resolve()}" in captured.out
    errors = [line for line in captured.err.splitlines() if line.strip()]
    assert len(errors) == 1 and errors[0].startswith("error: ") and f"in use by process {pid}" in errors[0], errors
    assert sorted(os.listdir(folder)) == [".lock"]  # nothing ran


def test_a_waiting_writer_goes_on_once_the_holder_lets_go(tmp_path, capsys):
    first = utils.FolderLock(tmp_path / "runs").acquire()
    threading.Timer(0.3, first.release).start()
    second = utils.wait_for_lock(utils.FolderLock(tmp_path / "runs"), "reproduce", max_wait=10, poll=0.05)
    try:
        assert (tmp_path / "runs" / ".lock").read_text().strip() == str(os.getpid())
        assert capsys.readouterr().out.count("waiting for reproduce") == 1
    finally:
        second.release()


def test_output_folder_locks_leave_no_lock_file(tmp_path):
    lock = utils.FolderLock(tmp_path / "out", "output folder", remove_file=True).acquire()
    assert (tmp_path / "out" / ".lock").exists()
    lock.release()
    assert os.listdir(tmp_path / "out") == []


# --------------------------------------------------------------------------- 3. unbundle: bounded, checked, written


def test_a_member_declaring_4_gib_is_refused_before_it_is_read(home, tmp_path, capsys, streamed):
    bomb = _bundle(tmp_path / "bomb.zip", _good_members())
    name = f"checkpoints/{RUN}/checkpoint.pt"
    _patch_central(bomb, name, 24, "<I", 0xFFFFFFF0)  # uncompressed size: 4 GiB, nothing stored
    assert cli.main(["unbundle", str(bomb)]) == 2
    one_line_error(capsys, str(bomb), name, "declares 4096.0 MB")
    assert name not in streamed and not (home / "runs").exists()


def test_a_highly_compressed_member_is_refused_as_a_zip_bomb(home, tmp_path, capsys, streamed):
    members = {**_good_members(), f"checkpoints/{RUN}/log.csv": bytes(8 * 2**20)}  # 8 MB of zeros: ~8 KB packed
    bomb = _bundle(tmp_path / "bomb.zip", members, compression=zipfile.ZIP_DEFLATED)
    assert zipfile.ZipFile(bomb).getinfo(f"checkpoints/{RUN}/log.csv").compress_size < 2**17
    assert cli.main(["unbundle", str(bomb)]) == 2
    one_line_error(capsys, str(bomb), "log.csv", "zip bomb")
    assert streamed == [bundle.INDEX] and not (home / "runs").exists()  # the small index only


def test_a_4_gib_bundle_json_is_refused_before_it_is_read(home, tmp_path, capsys, streamed):
    big = _bundle(tmp_path / "big.zip", _good_members())
    _patch_central(big, bundle.INDEX, 24, "<I", 0xFFFFFFF0)
    assert cli.main(["unbundle", str(big)]) == 2
    one_line_error(capsys, str(big), "bundle.json", "declares")
    assert not streamed and not (home / "runs").exists()


def test_a_refused_checkpoint_leaves_nothing_behind(home, tmp_path, capsys):
    members = {f"checkpoints/{RUN}/checkpoint.pt": b"not a checkpoint at all",
               f"checkpoints/{RUN}/log.json": b"{}"}
    bad = _bundle(tmp_path / "bad.zip", members)
    assert cli.main(["unbundle", str(bad)]) == 2
    one_line_error(capsys, str(bad), "checkpoint.pt is refused")
    assert not (_runs(home) / RUN).exists()  # no log, no checkpoint, no lock: a later `bundle` finds nothing


def test_a_bundle_of_logs_only_never_replaces_a_runs_logs(home, tmp_path, capsys):
    run = _runs(home) / RUN
    run.mkdir(parents=True)
    (run / "checkpoint.pt").write_bytes(_ckpt_bytes(1.0))
    (run / "log.json").write_text("mine")
    logs = _bundle(tmp_path / "logs.zip", {f"checkpoints/{RUN}/log.json": b"theirs"})
    assert cli.main(["unbundle", str(logs)]) == 2
    one_line_error(capsys, str(logs), "has no checkpoint.pt")
    assert (run / "log.json").read_text() == "mine"


def test_a_run_with_the_same_checkpoint_keeps_its_own_logs(home, tmp_path, capsys):
    members = _good_members()
    run = _runs(home) / RUN
    run.mkdir(parents=True)
    (run / "checkpoint.pt").write_bytes(members[f"checkpoints/{RUN}/checkpoint.pt"])
    (run / "log.json").write_text("mine")
    assert cli.main(["unbundle", str(_bundle(tmp_path / "b.zip", members))]) == 0
    assert "already in place" in capsys.readouterr().out
    assert (run / "log.json").read_text() == "mine"


def test_a_log_without_the_bundles_checkpoint_is_never_replaced(home, tmp_path, capsys):
    run = _runs(home) / RUN
    run.mkdir(parents=True)
    (run / "log.json").write_text("mine")
    good = _bundle(tmp_path / "b.zip", _good_members())
    assert cli.main(["unbundle", str(good)]) == 2
    one_line_error(capsys, str(run / "log.json"), "never replaces a log")
    assert (run / "log.json").read_text() == "mine" and not (run / "checkpoint.pt").exists()


def test_a_too_long_run_name_is_refused_before_anything_is_written(home, tmp_path, capsys):
    long = "case1_seed0-" + "x" * 300
    bad = _bundle(tmp_path / "long.zip", {**_good_members(), f"checkpoints/{long}/checkpoint.pt": _ckpt_bytes()})
    assert cli.main(["unbundle", str(bad)]) == 2
    one_line_error(capsys, str(bad), "is not a run folder's name")
    assert not (home / "runs").exists()


def test_a_killed_unbundles_temporary_file_goes_on_the_next_run(home, tmp_path, capsys):
    run = _runs(home) / RUN
    run.mkdir(parents=True)
    other = _runs(home) / "case4_seed0-ffffffff"
    other.mkdir()
    left = [run / f".geodepth-{DEAD_PID}-checkpoint.pt.k1ll3d.tmp", other / f".geodepth-{DEAD_PID}-log.json.x.tmp"]
    for p in left:
        p.write_bytes(bytes(23 * 1024))
    assert cli.main(["unbundle", str(_bundle(tmp_path / "b.zip", _good_members()))]) == 0
    assert not any(p.exists() for p in left)
    assert sorted(os.listdir(run)) == [".lock", checkpoint.RUN_MARK, "checkpoint.pt", "log.json"]


def test_a_member_named_after_a_checkout_file_is_refused(home, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(utils.project_root() or tmp_path)
    for name, needle in (("manifests/pyproject.toml.json", "not a manifest's name"),
                         ("manifests/no_such_recipe.json", "this checkout does not have")):
        bad = _bundle(tmp_path / "m.zip", {**_good_members(), name: b"{}"})
        assert cli.main(["unbundle", str(bad)]) == 2
        one_line_error(capsys, str(bad), name, needle)
    assert not (home / "runs").exists()


def test_a_manifest_that_is_not_json_is_named(home, tmp_path, capsys):
    bad = _bundle(tmp_path / "m.zip", {**_good_members(), "manifests/scenario_smoke.json": b"\xff not json"})
    assert cli.main(["unbundle", str(bad)]) == 2
    one_line_error(capsys, str(bad), "manifests/scenario_smoke.json is not valid JSON")


def test_a_good_bundle_still_unpacks(home, tmp_path, capsys):
    members = {**_good_members(), "manifests/scenario_smoke.json": (utils.manifests_dir() / "scenario_smoke.json")
               .read_bytes()}
    assert cli.main(["unbundle", str(_bundle(tmp_path / "b.zip", members, compression=zipfile.ZIP_DEFLATED))]) == 0
    run = _runs(home) / RUN
    assert (run / "checkpoint.pt").read_bytes() == members[f"checkpoints/{RUN}/checkpoint.pt"]
    assert not list(run.glob(utils.TEMP_GLOB))


# --------------------------------------------------------------------------- 4. the user's .*.tmp files


def test_predict_keeps_the_users_tmp_files_and_removes_only_its_own(untrained_checkpoint, tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    Image.fromarray(np.zeros((24, 24, 3), np.uint8)).save(src / "a.png")
    out = tmp_path / "out"
    out.mkdir()
    for name in (".notes.tmp", ".thesis.tmp"):
        (out / name).write_text("the user's")
    ours = out / f".geodepth-{DEAD_PID}-a_depth.npy.k1ll3d.tmp"
    ours.write_bytes(bytes(100))
    assert cli.main(["predict", "--checkpoint", str(untrained_checkpoint), "--input", str(src), "--out", str(out),
                     "--no-progress", "--ply", "none"]) == 0
    assert "removed 1 half-written temporary file" in capsys.readouterr().out
    assert not ours.exists() and (out / ".notes.tmp").read_text() == (out / ".thesis.tmp").read_text() == "the user's"
    assert not (out / ".lock").exists()


def test_train_keeps_the_users_tmp_files(tmp_path, capsys, smoke_root):
    run = tmp_path / "run"
    run.mkdir()
    (run / ".notes.tmp").write_text("the user's")
    ours = run / f".geodepth-{DEAD_PID}-checkpoint.pt.k1ll3d.tmp"
    ours.write_bytes(bytes(100))
    (run / "checkpoint.pt").write_bytes(b"a run")  # refused without --resume, after the clean-up
    assert cli.main(["train", "--profile", "smoke", "--case", "1", "--dataset", str(smoke_root), "--image-size", "32",
                     "--epochs", "1", "--run-dir", str(run), "--no-progress", "--no-verify"]) == 2
    one_line_error(capsys, "pass --resume")
    assert not ours.exists() and (run / ".notes.tmp").read_text() == "the user's"


def test_train_refuses_a_run_dir_holding_someone_elses_files_and_owns_the_folders_it_made(tmp_path, capsys,
                                                                                          smoke_root):
    """--run-dir naming a folder of the user's (their own log.csv, which the run's logs would replace) or a
    checkout's tracked folder: one line, exit 2, nothing written there, not even the lock file. A new or
    empty folder is the run's, marked at once, so a run killed before its first checkpoint may start
    again there."""
    args = ["train", "--profile", "smoke", "--case", "1", "--dataset", str(smoke_root), "--image-size", "32",
            "--epochs", "1", "--no-progress", "--no-verify", "--run-dir"]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "log.csv").write_text("epoch,my own measurements\n")
    (mine / "notes.md").write_text("the user's")
    before = {p.name: p.read_bytes() for p in mine.iterdir()}
    assert cli.main([*args, str(mine)]) == 2
    one_line_error(capsys, str(mine), "did not write (log.csv, ...); choose a new or empty --run-dir")
    assert {p.name: p.read_bytes() for p in mine.iterdir()} == before
    tracked = Path(__file__).resolve().parents[1] / "data_manifests"
    listing = sorted(os.listdir(tracked))
    assert cli.main([*args, str(tracked)]) == 2
    one_line_error(capsys, str(tracked), "did not write")
    assert sorted(os.listdir(tracked)) == listing
    killed = tmp_path / "killed"  # what a run killed (kill -9) before its first checkpoint leaves
    killed.mkdir()
    utils.mark_folder(killed, checkpoint.RUN_MARK, "train")
    (killed / utils.LOCK_NAME).write_text(str(DEAD_PID))
    assert cli.main([*args, str(killed)]) == 0 and (killed / "checkpoint.pt").is_file()
    assert cli.main([*args, str(tmp_path / "new")]) == 0
    assert (tmp_path / "new" / checkpoint.RUN_MARK).is_file() and (tmp_path / "new" / "checkpoint.pt").is_file()
    assert cli.main([*args, str(tmp_path / "new"), "--resume"]) == 0  # its own folder, again


def test_only_a_gone_writers_temporary_files_are_stale(tmp_path):
    names = {"user": ".notes.tmp", "dead": f".geodepth-{DEAD_PID}-x.tmp", "alive": f".geodepth-{os.getppid()}-x.tmp",
             "mine": f".geodepth-{os.getpid()}-x.tmp"}
    for n in names.values():
        (tmp_path / n).write_text("x")
    assert utils.remove_stale_temps(tmp_path) == 1
    assert sorted(os.listdir(tmp_path)) == sorted(n for k, n in names.items() if k != "dead")
    assert utils.remove_stale_temps(tmp_path, locked=True) == 1  # under the lock: any other writer's
    assert sorted(os.listdir(tmp_path)) == sorted([names["user"], names["mine"]])
    with utils.atomic_path(tmp_path / "f.txt") as tmp:
        assert tmp.name.startswith(f".geodepth-{os.getpid()}-f.txt.") and tmp.name.endswith(".tmp")
        tmp.write_text("done")
    assert (tmp_path / "f.txt").read_text() == "done"



def _named_failure(writer, files: dict, named: Path, what: str) -> list[str]:
    """[] when ``writer(files)`` raises a FileProblem naming ``named``; else what it did instead."""
    try:
        writer(files)
    except utils.FileProblem as exc:
        return [] if exc.path == named else [f"{what} named {exc.path}"]
    return [f"{what} raised nothing"]


def _set_write_problems(writer, folder: Path, monkeypatch) -> list[str]:
    """What goes wrong when ``writer`` writes the set {a, b, c} over an earlier set: once with the disk
    full at the second file's flush, once with a folder in the way of the third file's name (Linux:
    the flushed file is told by its name in /proc)."""
    problems = []
    folder.mkdir()
    old = {folder / n: f"old {n}".encode() for n in "abc"}
    new = {path: f"new {path.name}".encode() for path in old}
    for path, data in old.items():
        path.write_bytes(data)
    real_fsync = os.fsync

    def full_at_b(fd):  # the disk fills while the second file's data is flushed
        if os.readlink(f"/proc/self/fd/{fd}").startswith(str(folder / utils.temp_prefix("b"))):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(utils.os, "fsync", full_at_b)
    problems += _named_failure(writer, new, folder / "b", "a full disk")
    monkeypatch.setattr(utils.os, "fsync", real_fsync)
    if {p: p.read_bytes() for p in old} != old:
        problems.append("a full disk changed the earlier set")
    (folder / "c").unlink()
    (folder / "c").mkdir()  # in the way of the last rename
    problems += _named_failure(writer, new, folder / "c", "a folder in the way")
    if sorted(os.listdir(folder)) != ["c"]:
        problems.append(f"a failed rename left {sorted(os.listdir(folder))}")
    return problems


def test_a_set_of_files_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    files = {tmp_path / "ok" / n: n.encode() * 3 for n in ("x.npy", "x.png", "x.ply")}
    utils.write_files_atomic(files)
    assert {p: p.read_bytes() for p in files} == files and sorted(os.listdir(tmp_path / "ok")) == sorted(
        p.name for p in files)
    assert _set_write_problems(utils.write_files_atomic, tmp_path / "set", monkeypatch) == []


def test_the_set_check_catches_files_written_one_by_one(tmp_path, monkeypatch):
    """Each file atomic on its own (the former way) is not a set: the full disk leaves a new ``a`` beside
    the old ``b`` and ``c``, and the folder in the way leaves the new ``a`` and ``b``."""
    def one_by_one(files):
        for path, data in files.items():
            utils.write_bytes_atomic(path, data)

    assert _set_write_problems(one_by_one, tmp_path / "set", monkeypatch) == [
        "a full disk changed the earlier set", "a failed rename left ['a', 'b', 'c']"]


# --------------------------------------------------------------------------- 5. one line, not a traceback


def _damage_first_data_byte(path: Path, name: str) -> None:
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(name)
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    data[start + 10] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("fault,needle", [
    ("crc", "damaged (Bad CRC-32"),
    ("compression", "compression method 99"),
    ("encrypted", "is encrypted"),
    ("profile_list", "names profile ['smoke']"),
    ("nested", "nested too deeply"),
    ("not_json", "bundle.json is not valid JSON"),
])
def test_a_hostile_bundle_is_one_error_line(home, tmp_path, capsys, fault, needle):
    name = f"checkpoints/{RUN}/checkpoint.pt"
    members = _good_members()
    index = None
    if fault == "profile_list":
        index = {"format": 1, "profile": ["smoke"], "runs": [RUN],
                 "files": {n: hashlib.sha256(b).hexdigest() for n, b in members.items()}}
    elif fault == "nested":
        index = b"[" * 100_000 + b"]" * 100_000
    elif fault == "not_json":
        index = b"\x00\x01 not json"
    path = _bundle(tmp_path / f"{fault}.zip", members, index=index)
    if fault == "crc":
        _damage_first_data_byte(path, name)
    elif fault == "compression":
        _patch_central(path, name, 10, "<H", 99)
    elif fault == "encrypted":
        _patch_central(path, name, 8, "<H", 0x1)
    assert cli.main(["unbundle", str(path)]) == 2
    one_line_error(capsys, str(path), needle)
    assert not (home / "runs").exists()
    assert cli.main(["--debug", "unbundle", str(path)]) == 2  # --debug keeps the traceback
    assert "Traceback" in capsys.readouterr().err


def _notebook(cells) -> dict:
    return {"cells": cells, "metadata": {}, "nbformat": 4, "nbformat_minor": 5}


def _answer(source: str, grade_id="ex01-1-answer", **nbgrader) -> dict:
    return {"cell_type": "code", "source": source, "outputs": [], "execution_count": None,
            "metadata": {"nbgrader": {"grade_id": grade_id, "solution": True, **nbgrader}}}


@pytest.mark.parametrize("fault,needle", [
    ("truncated", "not valid JSON"),
    ("no_cells", "no list of cells"),
    ("unmatched", "unmatched solution markers"),
    ("points", "not a number"),
    ("metadata", "damaged nbgrader metadata"),
    ("nested", "not a notebook (RecursionError)"),
])
def test_a_damaged_or_tampered_notebook_is_one_error_line(tmp_path, capsys, monkeypatch, fault, needle):
    nb = tmp_path / "01_tampered.ipynb"
    good = _answer("### BEGIN SOLUTION\nx = 1\n### END SOLUTION\n")
    text = {
        "truncated": json.dumps(_notebook([good]))[:-20],
        "no_cells": json.dumps({"cells": "none"}),
        "unmatched": json.dumps(_notebook([_answer("### BEGIN SOLUTION\nx = 1\n")])),
        "points": json.dumps(_notebook([_answer("x", grade_id="ex01-1-check", points="many")])),
        "metadata": json.dumps(_notebook([{**good, "metadata": {"nbgrader": ["x"]}}])),
        "nested": "[" * 100_000 + "]" * 100_000,
    }[fault]
    nb.write_text(text)
    monkeypatch.setattr(exercises, "notebook_paths", lambda folder=None: [nb])
    out = tmp_path / "release"
    assert cli.main(["exercises", "--out", str(out)]) == 2
    one_line_error(capsys, str(nb), needle)
    assert not out.exists()

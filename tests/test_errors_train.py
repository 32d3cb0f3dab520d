"""Hostile and careless use of checkpoints, run folders and training, one test per fault.

Checkpoints are data, never code: a crafted ``checkpoint.pt`` or plain pickle runs nothing in any
command or in the notebooks' loader. One writer per run folder. Diverged training, a wrong
config number, a data folder holding another dataset, and the smaller gaps each stop with one
line naming what is wrong (exit 2), losing nothing already written.
"""

import functools
import json
import multiprocessing.util
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import one_line_error, save_untrained_checkpoint

from geodepth_lite import cli, utils
from geodepth_lite.data import integrity, synth
from geodepth_lite.training import checkpoint, config, train
from geodepth_lite.workbook import reproduce


def _smoke_cfg(root, **kw):
    kw.setdefault("epochs", 2)
    kw.setdefault("image_size", 32)
    return config.make_config("smoke", 1, 0, dataset=str(root), **kw)


def _train_argv(root, run, *extra):
    return ["train", "--profile", "smoke", "--case", "1", "--dataset", str(root), "--image-size", "32",
            "--epochs", "2", "--run-dir", str(run), "--no-progress", "--no-verify", *extra]


# --------------------------------------------------------------------------- checkpoints run no code


class _Payload:
    """Unpickling this calls ``os.system`` and leaves a marker file: what an attacker would ship."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _crafted_files(tmp_path) -> tuple[Path, dict[str, Path]]:
    marker = tmp_path / "code-ran"
    ckpt_dir = tmp_path / "crafted"
    ckpt_dir.mkdir()
    model = save_untrained_checkpoint(tmp_path / "good.pt")
    state = torch.load(model, weights_only=True)
    crafted = ckpt_dir / "checkpoint.pt"  # a real checkpoint with one poisoned entry
    torch.save({**state, "cfg": {"image_size": 32}, "history": [_Payload(marker)]}, crafted)
    plain = tmp_path / "plain.pt"  # not a torch file at all: a bare pickle
    plain.write_bytes(pickle.dumps({"model": _Payload(marker), "cfg": {}}))
    return marker, {"crafted": crafted, "plain": plain}


def test_the_crafted_files_would_run_code_if_unpickled(tmp_path):
    """The check below means something: loading these files unsafely does run their code."""
    marker, files = _crafted_files(tmp_path)
    pickle.loads(files["plain"].read_bytes())
    assert marker.exists()
    marker.unlink()
    torch.load(files["crafted"], weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("kind", ["crafted", "plain"])
def test_no_command_or_loader_runs_code_from_a_checkpoint(smoke_root, tmp_path, capsys, kind):
    marker, files = _crafted_files(tmp_path)
    ckpt = files[kind]
    commands = {
        "predict": ["predict", "--checkpoint", str(ckpt), "--input", str(smoke_root / "test" / "rgb"),
                    "--out", str(tmp_path / "pred"), "--no-progress"],
        "evaluate": ["evaluate", "--checkpoint", str(ckpt), "--dataset", str(smoke_root), "--out",
                     str(tmp_path / "eval"), "--no-progress", "--no-verify"],
    }
    if kind == "crafted":  # train --resume reads the checkpoint in its run folder
        commands["train --resume"] = _train_argv(smoke_root, ckpt.parent, "--resume")
    for name, argv in commands.items():
        assert cli.main(argv) == 2, name
        one_line_error(capsys, str(ckpt), "refused")
        assert not marker.exists(), name
    # the notebooks' loaders: load_model, and the run cache that reads a finished run's file
    with pytest.raises(ValueError, match="could run code"):
        checkpoint.load_model(ckpt)
    with pytest.raises(ValueError, match="could run code"):
        checkpoint.read_checkpoint(ckpt, for_resume=True)
    assert cli.main(["convert-checkpoint", str(ckpt)]) == 2
    capsys.readouterr()
    assert not marker.exists()
    assert not (tmp_path / "pred").exists() and not (tmp_path / "eval").exists()


def _first_format(path: Path) -> None:
    """Rewrite a checkpoint as the first format did: numpy's RNG state as numpy objects."""
    state = torch.load(path, weights_only=True)
    n, p = state["rng"]["numpy"], state["rng"]["python"]
    state["rng"]["numpy"] = (n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                             n["cached_gaussian"])
    state["rng"]["python"] = (p["version"], tuple(p["internal"]), p["gauss_next"])
    del state["format"]
    torch.save(state, path)


def test_a_first_format_checkpoint_is_refused_then_converted_and_resumes_identically(smoke_root, tmp_path, capsys):
    cfg = _smoke_cfg(smoke_root)
    straight = torch.load(train.fit(cfg, tmp_path / "straight", progress=False), weights_only=True)
    run = tmp_path / "old"
    path = train.fit(cfg, run, progress=False, stop_after=1)
    _first_format(path)
    with pytest.raises(checkpoint.OldCheckpoint, match="convert-checkpoint"):
        checkpoint.read_checkpoint(path)
    assert cli.main(_train_argv(smoke_root, run, "--resume")) == 2
    one_line_error(capsys, str(path), "first checkpoint format", "convert-checkpoint")

    assert cli.main(["convert-checkpoint", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"converted: {path}" in out and "already in the current format" in out  # the straight run's
    resumed = torch.load(train.fit(cfg, run, progress=False, resume=True), weights_only=True)
    for k, v in straight["model"].items():
        assert torch.equal(v, resumed["model"][k]), k


@pytest.fixture(scope="module")
def one_epoch_run(smoke_root, tmp_path_factory) -> Path:
    """A smoke run of Case 1 after its first of two epochs, as a killed run leaves it."""
    run = tmp_path_factory.mktemp("one_epoch") / "run"
    train.fit(_smoke_cfg(smoke_root, epochs=1), run, progress=False)
    state = torch.load(run / checkpoint.CHECKPOINT_NAME, weights_only=True)
    state["cfg"] = dict(state["cfg"], epochs=2)
    state["complete"] = False
    torch.save(state, run / checkpoint.CHECKPOINT_NAME)
    return run


def _groups(change):
    return lambda s: s["optimizer"].update(param_groups=[change(dict(g)) for g in s["optimizer"]["param_groups"]])


def _first_moment(s):
    key = next(iter(s["optimizer"]["state"]))
    s["optimizer"]["state"][key] = dict(s["optimizer"]["state"][key], exp_avg=torch.zeros(3))


RESUME_DAMAGE = {  # an entry of the training state changed -> what the refusal says (torch takes each as it is)
    "epoch a word": (lambda s: s.update(epoch="1"), "its epoch is '1', not a count"),
    "epoch NaN": (lambda s: s.update(epoch=float("nan")), "its epoch is 'nan', not a count"),
    "history a number": (lambda s: s.update(history=5), "its history is not one record of numbers per epoch"),
    "history of numbers": (lambda s: s.update(history=[1]), "its history is not one record of numbers per epoch"),
    "learning rate a word": (_groups(lambda g: {**g, "lr": "x"}), "learning rate, eps, weight decay or betas"),
    "one beta": (_groups(lambda g: {**g, "betas": (0.9,)}), "learning rate, eps, weight decay or betas"),
    "a moment of another shape": (_first_moment, "moments are not shaped like the model's parameters"),
    "schedule step a word": (lambda s: s["schedule"].update(last_epoch="a"), "schedule's step or base rates"),
    "schedule rate a word": (lambda s: s["schedule"].update(base_lrs=["x"]), "schedule's step or base rates"),
}


@pytest.mark.parametrize("damage", sorted(RESUME_DAMAGE))
def test_a_damaged_training_state_is_refused_before_resuming(one_epoch_run, smoke_root, tmp_path, capsys, damage):
    """Each of these ended as "this is a bug" (exit 1) at the first step or before: now one line naming the
    checkpoint and the entry, exit 2, the run folder left as it was."""
    run = Path(shutil.copytree(one_epoch_run, tmp_path / "run"))
    state = torch.load(run / checkpoint.CHECKPOINT_NAME, weights_only=True)
    change, said = RESUME_DAMAGE[damage]
    change(state)
    torch.save(state, run / checkpoint.CHECKPOINT_NAME)
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    assert cli.main(_train_argv(smoke_root, run, "--resume")) == 2
    one_line_error(capsys, f"cannot resume {run / checkpoint.CHECKPOINT_NAME}: ", said)
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before


def test_the_undamaged_training_state_resumes(one_epoch_run, smoke_root, tmp_path, capsys):
    run = Path(shutil.copytree(one_epoch_run, tmp_path / "run"))
    assert checkpoint.training_state_problem(torch.load(run / checkpoint.CHECKPOINT_NAME, weights_only=True)) is None
    assert cli.main(_train_argv(smoke_root, run, "--resume")) == 0
    assert "resuming" in capsys.readouterr().out


def test_a_checkpoint_missing_tensors_is_named(smoke_root, tmp_path, capsys):
    ckpt = save_untrained_checkpoint(tmp_path / "partial.pt")
    state = torch.load(ckpt, weights_only=True)
    dropped = sorted(state["model"])[3]
    del state["model"][dropped]
    torch.save(state, ckpt)
    argv = ["predict", "--checkpoint", str(ckpt), "--input", str(smoke_root / "test" / "rgb"),
            "--out", str(tmp_path / "pred"), "--no-progress"]
    assert cli.main(argv) == 2
    one_line_error(capsys, str(ckpt), "1 missing tensor(s)", dropped)


# --------------------------------------------------------------------------- one writer per run folder


_HOLDER = """
import sys, time
from geodepth_lite import utils
lock = utils.FolderLock(sys.argv[1]).acquire()
print("locked", flush=True)
time.sleep(120)
"""


def _hold_lock(folder: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", _HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_second_writer_is_refused_and_a_killed_holder_frees_the_folder(smoke_root, tmp_path, capsys):
    cfg = _smoke_cfg(smoke_root)
    run = tmp_path / "run"
    train.fit(cfg, run, progress=False, stop_after=1)
    before = (run / "checkpoint.pt").read_bytes()
    holder = _hold_lock(run)
    stale = run / f".geodepth-{holder.pid}-checkpoint.pt.inflight.tmp"  # the holder's save in progress
    stale.write_bytes(b"\x00" * 64)
    try:
        assert cli.main(_train_argv(smoke_root, run, "--resume")) == 2
        one_line_error(capsys, str(run), f"in use by process {holder.pid}")
        assert stale.exists()  # the other writer's temporary file is not touched
        assert (run / "checkpoint.pt").read_bytes() == before
    finally:
        holder.kill()
        holder.wait()
    assert cli.main(_train_argv(smoke_root, run, "--resume")) == 0  # the kernel freed the lock
    assert not stale.exists()
    assert checkpoint.read_checkpoint(run / "checkpoint.pt")["epoch"] == 2


def test_two_train_processes_into_one_folder(smoke_root, tmp_path):
    """Two real ``train`` processes started together: exactly one trains, the other is refused."""
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "geodepth_lite", *_train_argv(smoke_root, run, "--epochs", "1")]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    refused = [err for code, err in results if code == 2]
    if codes == [0, 0]:  # the first finished before the second started: nothing to refuse, nothing lost
        pytest.skip("the two processes did not overlap")
    assert codes == [0, 2], results
    assert "in use by process" in refused[0] and str(run) in refused[0]
    assert checkpoint.read_checkpoint(run / "checkpoint.pt")["complete"]


# --------------------------------------------------------------------------- training that diverges


def test_a_non_finite_config_number_is_refused():
    for key, value in (("lr", float("inf")), ("lr", float("nan")), ("weight_decay", float("inf")),
                       ("lambdas", [1.0, float("inf"), 0.0])):
        with pytest.raises(ValueError, match=key):
            config.make_config("smoke", 4, 0, **{key: value})


def test_diverged_training_stops_at_the_first_non_finite_loss(smoke_root, tmp_path, capsys, monkeypatch):
    cfg = _smoke_cfg(smoke_root)
    run = tmp_path / "run"
    train.fit(cfg, run, progress=False, stop_after=1)
    kept = (run / "checkpoint.pt").read_bytes()
    real = train.compute_losses
    calls = {"n": 0}

    def blow_up(pred, batch, c, *rest):
        loss, terms = real(pred, batch, c, *rest)
        calls["n"] += 1
        if calls["n"] == 3:  # the third training step of the resumed epoch
            terms = {**terms, "smooth": float("nan")}
            loss = loss * float("nan")
        return loss, terms

    monkeypatch.setattr(train, "compute_losses", blow_up)
    monkeypatch.setattr(train, "term_gradient_norms", lambda *a: {})
    assert cli.main(_train_argv(smoke_root, run, "--resume")) == 2
    line = one_line_error(capsys, str(run), "epoch 2, step 3 of", "smooth", "learning rate 0.0001")
    assert "checkpoint.pt (epoch 1) is kept" in line
    assert (run / "checkpoint.pt").read_bytes() == kept


def test_diverged_weights_are_caught_before_validation(smoke_root, tmp_path, capsys, monkeypatch):
    real_step = train.Trainer.step

    def last_step_breaks(self, loss):  # the epoch's last update leaves infinite weights
        real_step(self, loss)
        if self.schedule.last_epoch == len(self.loader):
            for p in self.model.parameters():
                p.data.fill_(float("inf"))

    monkeypatch.setattr(train.Trainer, "step", last_step_breaks)
    run = tmp_path / "run"
    assert cli.main(_train_argv(smoke_root, run)) == 2
    line = one_line_error(capsys, "training diverged", "weights became non-finite", "no checkpoint was written")
    assert "epoch 1, step 3 of 3" in line
    assert not run.exists()  # a run that wrote nothing leaves no folder


# --------------------------------------------------------------------------- fail early, leave nothing


def test_an_unwritable_run_folder_is_found_before_the_dataset_check(smoke_root, tmp_path, capsys, monkeypatch):
    checked = []
    monkeypatch.setattr(integrity, "check_dataset", lambda *a, **k: checked.append(a))

    def read_only(*a, **k):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(utils.tempfile, "mkstemp", read_only)
    run = tmp_path / "run"
    argv = [a for a in _train_argv(smoke_root, run) if a != "--no-verify"]
    assert cli.main(argv) == 2
    one_line_error(capsys, f"cannot write into {run}", "read-only file system")
    assert not checked and not run.exists()


def test_a_full_disk_is_found_before_the_first_epoch(smoke_root, tmp_path, capsys, monkeypatch):
    import collections

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 2**20, 2**20))
    epochs = []
    monkeypatch.setattr(train.Trainer, "run_epoch", lambda self, e: epochs.append(e))
    run = tmp_path / "run"
    assert cli.main(_train_argv(smoke_root, run)) == 2
    one_line_error(capsys, f"cannot write into {run}", "no space left", "1.0 MB free")
    assert not epochs and not run.exists()


def test_resume_without_a_checkpoint_is_refused(smoke_root, tmp_path, capsys):
    run = tmp_path / "empty-run"
    assert cli.main(_train_argv(smoke_root, run, "--resume")) == 2
    one_line_error(capsys, str(run), "no checkpoint to continue")
    assert not run.exists()


def test_a_refused_training_run_leaves_no_folder(tmp_path, capsys):
    run = tmp_path / "nested" / "run"
    missing = tmp_path / "no-such-dataset"
    argv = ["train", "--profile", "smoke", "--dataset", str(missing), "--run-dir", str(run), "--no-progress",
            "--no-verify"]
    assert cli.main(argv) == 2
    capsys.readouterr()
    assert not run.exists() and not (tmp_path / "nested").exists()


def test_the_data_cache_refuses_to_replace_another_dataset(tmp_path, capsys):
    tiny = {"splits": {"train": 2, "val": 1, "test": 1}}
    root = synth.ensure_dataset("scenario_smoke", overrides=tiny, root=tmp_path, progress=False)
    other = tmp_path / "scenario_teach"  # a folder where teach's dataset belongs, holding another one
    shutil.copytree(root, other)
    before = sorted(p.relative_to(other) for p in other.rglob("*"))
    with pytest.raises(FileExistsError) as err:
        synth.ensure_dataset("scenario_teach", root=tmp_path, progress=False)
    message = str(err.value)
    held = json.loads((other / "manifest.json").read_text())["name"]
    assert f"manifest {held!r} with 4 frames" in message and "'scenario_teach'" in message
    assert "--overwrite" in message and "nothing was deleted" in message
    assert sorted(p.relative_to(other) for p in other.rglob("*")) == before


def test_an_interrupted_dataset_of_the_same_manifest_is_completed(tmp_path):
    tiny = {"splits": {"train": 2, "val": 1, "test": 1}}
    root = synth.ensure_dataset("scenario_smoke", overrides=tiny, root=tmp_path, progress=False)
    rgb = next((root / "train" / "rgb").iterdir())
    rgb.unlink()
    (root / "checksums.sha256").unlink()
    assert synth.ensure_dataset("scenario_smoke", overrides=tiny, root=tmp_path, progress=False) == root
    assert rgb.exists() and not integrity.verify(root)


def test_dry_run_refuses_what_the_real_run_refuses(capsys):
    with pytest.raises(ValueError, match="case must be one of"):
        reproduce.reproduce(config.profile("smoke"), notebooks=["04"], params={"case": 9}, dry_run=True)


# --------------------------------------------------------------------------- leftovers


def test_a_failing_multi_worker_run_leaves_no_multiprocessing_temp_folder(smoke_root, tmp_path, capsys):
    tmp = Path(tempfile.mkdtemp(prefix="gd-", dir="/tmp"))  # short: the workers' sockets live in it
    broken = tmp_path / "broken"
    shutil.copytree(smoke_root, broken)
    depth = sorted((broken / "train" / "depth").iterdir())[0]
    depth.write_bytes(b"garbage")
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "geodepth_lite", *_train_argv(broken, run, "--num-workers", "2", "--no-cache")]
    done = subprocess.run(argv, env={**os.environ, "TMPDIR": str(tmp)}, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 2, done.stderr
    assert str(depth) in done.stderr and "Traceback" not in done.stderr
    time.sleep(0.5)
    left = list(tmp.glob("pymp-*"))
    shutil.rmtree(tmp)
    assert not left, left
    assert not run.exists()


class _SlowToStop(torch.utils.data.Dataset):
    """Frame 0 at once; every other frame takes 60 s, so the worker holding one is still busy when
    the loader stops, and the loader kills it (after its 5 s wait) before it can tidy up."""

    def __len__(self):
        return 4

    def __getitem__(self, index):
        multiprocessing.util.get_temp_dir()  # the worker's socket folder, as sending a tensor makes it
        if index > 0:
            time.sleep(60)
        return torch.zeros(1)


def test_the_temp_folder_of_a_killed_worker_is_removed_with_the_runs_worker_folder(monkeypatch):
    base = Path(tempfile.mkdtemp(prefix="gd-", dir="/tmp"))  # short: the workers' sockets live in it
    monkeypatch.setattr(tempfile, "tempdir", str(base))
    try:
        with utils.worker_temp_dir(2) as folder:
            loader = torch.utils.data.DataLoader(_SlowToStop(), batch_size=1, num_workers=2,
                                                 worker_init_fn=functools.partial(utils.worker_init, temp_dir=folder))
            for _ in train.worker_batches(loader):
                break  # as an error in the training step would
            killed = list(Path(folder).glob("pymp-*"))
            assert killed and Path(folder).parent == base  # the killed workers' folders, in the run's folder
        assert not Path(folder).exists() and not list(base.iterdir())
    finally:
        shutil.rmtree(base)
    with utils.worker_temp_dir(0) as none:
        assert none is None


def test_a_temp_folder_too_long_for_worker_sockets_loads_in_the_main_process(smoke_root, tmp_path):
    """Workers send batches over a Unix socket under TMPDIR; with too long a path they cannot, and a
    loader with workers would wait for ever (the timeout here catches that). Training drops the
    workers, says why, and finishes."""
    long_tmp = tmp_path / ("t" * 60) / ("u" * 60)
    long_tmp.mkdir(parents=True)
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "geodepth_lite", *_train_argv(smoke_root, run, "--num-workers", "2", "--no-cache")]
    done = subprocess.run(argv, env={**os.environ, "TMPDIR": str(long_tmp)}, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert "too long for data-loading worker processes" in done.stdout and "instead of 2 worker(s)" in done.stdout
    assert (run / "checkpoint.pt").is_file() and "Traceback" not in done.stderr


def test_worker_count_is_kept_where_the_temp_folder_is_short(monkeypatch, capsys):
    monkeypatch.setattr(tempfile, "tempdir", "/tmp")
    assert utils.workers_fit_temp_dir(3) == 3 and utils.workers_fit_temp_dir(0) == 0
    limit = "/" + "x" * (utils.SOCKET_PATH_MAX - utils.SOCKET_NAME_BYTES - 1)  # exactly at the limit
    monkeypatch.setattr(tempfile, "tempdir", limit)
    assert utils.workers_fit_temp_dir(2) == 2
    monkeypatch.setattr(tempfile, "tempdir", limit + "x")
    assert utils.workers_fit_temp_dir(2) == 0 and "instead of 2 worker(s)" in capsys.readouterr().out


def test_the_early_folder_check_creates_nothing(tmp_path, monkeypatch):
    """train's check before any work: it judges a new folder by its nearest existing parent, so a
    second process checking the same folder never finds it pulled away (it makes none to remove)."""
    run = tmp_path / "a" / "b" / "run"
    assert utils.check_can_create_dir(run) == run
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "a").write_text("keep me")
    with pytest.raises(utils.FileProblem, match=r"cannot create folder .*run: .*a is a file, not a folder"):
        utils.check_can_create_dir(run)
    assert (tmp_path / "a").read_text() == "keep me"
    existing = tmp_path / "existing"
    existing.mkdir()
    assert utils.check_can_create_dir(existing) == existing

    def read_only(*a, **k):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(utils.tempfile, "mkstemp", read_only)
    for folder in (tmp_path / "new", existing):
        with pytest.raises(utils.FileProblem, match="cannot write into .*: read-only file system"):
            utils.check_can_create_dir(folder)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "existing"]

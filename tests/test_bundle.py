"""The class bundle: pack a profile's trained runs, unpack them elsewhere, and refuse what is wrong."""

import hashlib
import json
import os
import shutil
import zipfile
from pathlib import Path

import pytest
import torch

from geodepth_lite import cli, utils
from geodepth_lite.apps import bundle
from geodepth_lite.training import checkpoint, config, run_cache


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory, smoke_root):
    """Two complete smoke runs (the notebooks' cache layout) in a workspace of their own, its
    ``scenario_smoke`` a copy of the session's (the same manifest: found complete, not generated again)."""
    home = tmp_path_factory.mktemp("instructor")
    shutil.copytree(smoke_root, home / "data" / "scenario_smoke")
    old = os.environ.get("GEODEPTH_LITE_HOME")
    os.environ["GEODEPTH_LITE_HOME"] = str(home)
    try:
        paths = [run_cache.ensure_checkpoint(config.profile("smoke").run(c, 0, image_size=32)) for c in (1, 4)]
    finally:
        if old is None:
            os.environ.pop("GEODEPTH_LITE_HOME", None)
        else:
            os.environ["GEODEPTH_LITE_HOME"] = old
    return home, paths


def _use(monkeypatch, home: Path) -> None:
    monkeypatch.setenv("GEODEPTH_LITE_HOME", str(home))


def test_a_bundle_unpacks_to_the_same_weights_without_optimizer_state(smoke_runs, tmp_path, monkeypatch, capsys):
    home, paths = smoke_runs
    _use(monkeypatch, home)
    target = tmp_path / "class.zip"
    assert cli.main(["bundle", "--profile", "smoke", "--out", str(target)]) == 0
    assert "2 trained runs" in capsys.readouterr().out
    index = json.loads(zipfile.ZipFile(target).read("bundle.json"))
    assert index["profile"] == "smoke" and sorted(index["runs"]) == sorted(p.parent.name for p in paths)
    assert "manifests/scenario_smoke.json" in index["files"]

    student = tmp_path / "student"
    _use(monkeypatch, student)
    assert cli.main(["unbundle", str(target)]) == 0
    for path in paths:
        mine = student / "runs" / "smoke" / "checkpoints" / path.parent.name / "checkpoint.pt"
        got, want = checkpoint.read_checkpoint(mine), checkpoint.read_checkpoint(path)
        assert set(got) <= set(bundle.KEEP) and "optimizer" not in got and "rng" not in got
        assert all(torch.equal(got["model"][k], want["model"][k]) for k in want["model"])
        assert (mine.parent / "log.json").read_bytes() == (path.parent / "log.json").read_bytes()
    # the run cache now finds the runs complete: a notebook would load them instead of training
    smoke = config.profile("smoke")
    assert all(run_cache.is_complete(smoke.run(c, 0, image_size=32)) for c in (1, 4))
    assert cli.main(["unbundle", str(target)]) == 0  # again: the same files, nothing refused


def _rewrite(src: Path, dst: Path, edit) -> Path:
    """A copy of bundle ``src`` with ``edit(members)`` applied to its {name: bytes}."""
    with zipfile.ZipFile(src) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    edit(members)
    with zipfile.ZipFile(dst, "w") as zf:
        for n, b in members.items():
            zf.writestr(n, b)
    return dst


def test_a_damaged_or_crafted_bundle_is_refused_before_anything_is_written(smoke_runs, tmp_path, monkeypatch, capsys):
    home, paths = smoke_runs
    _use(monkeypatch, home)
    good = bundle.make_bundle("smoke", tmp_path / "good.zip")
    name = f"checkpoints/{paths[0].parent.name}/checkpoint.pt"

    def flip_a_byte(m):
        blob = bytearray(m[name])
        blob[len(blob) // 2] ^= 1
        m[name] = bytes(blob)

    def add_escape(m):
        m["../../evil.py"] = b"print('hi')"
        index = json.loads(m["bundle.json"])
        index["files"]["../../evil.py"] = hashlib.sha256(m["../../evil.py"]).hexdigest()
        m["bundle.json"] = json.dumps(index).encode()

    cases = {"damaged": (flip_a_byte, "is damaged"), "escape": (add_escape, "refused member"),
             "unlisted": (lambda m: m.__setitem__("checkpoints/x/log.csv", b"x"), "not listed")}
    student = tmp_path / "student"
    _use(monkeypatch, student)
    for label, (edit, needle) in cases.items():
        bad = _rewrite(good, tmp_path / f"{label}.zip", edit)
        assert cli.main(["unbundle", str(bad)]) == 2, label
        err = capsys.readouterr().err
        assert needle in err and str(bad) in err, (label, err)
        assert not (student / "runs").exists(), label
    assert not (tmp_path.parent / "evil.py").exists()
    (tmp_path / "not.zip").write_bytes(b"plain text")
    assert cli.main(["unbundle", str(tmp_path / "not.zip")]) == 2
    assert "not a zip file" in capsys.readouterr().err


def test_unbundling_never_replaces_a_different_checkpoint(smoke_runs, tmp_path, monkeypatch, capsys):
    home, paths = smoke_runs
    _use(monkeypatch, home)
    good = bundle.make_bundle("smoke", tmp_path / "good.zip")
    student = tmp_path / "student"
    _use(monkeypatch, student)
    mine = student / "runs" / "smoke" / "checkpoints" / paths[0].parent.name / "checkpoint.pt"
    mine.parent.mkdir(parents=True)
    mine.write_bytes(b"the student's own run")
    assert cli.main(["unbundle", str(good)]) == 2
    assert "holds a different checkpoint" in capsys.readouterr().err
    assert mine.read_bytes() == b"the student's own run"


def test_a_bundle_of_another_dataset_recipe_is_refused(smoke_runs, tmp_path, monkeypatch, capsys):
    home, _ = smoke_runs
    _use(monkeypatch, home)
    good = bundle.make_bundle("smoke", tmp_path / "good.zip")

    def other_recipe(m):
        man = json.loads(m["manifests/scenario_smoke.json"])
        man["seed"] = man.get("seed", 0) + 1
        m["manifests/scenario_smoke.json"] = json.dumps(man).encode()
        index = json.loads(m["bundle.json"])
        index["files"]["manifests/scenario_smoke.json"] = hashlib.sha256(m["manifests/scenario_smoke.json"]).hexdigest()
        m["bundle.json"] = json.dumps(index).encode()

    bad = _rewrite(good, tmp_path / "other.zip", other_recipe)
    _use(monkeypatch, tmp_path / "student")
    assert cli.main(["unbundle", str(bad)]) == 2
    assert "another dataset recipe" in capsys.readouterr().err


def test_an_unfinished_run_is_not_bundled(tmp_path, monkeypatch, smoke_root):
    _use(monkeypatch, tmp_path / "home")
    cfg = config.make_config("smoke", 1, 0, dataset=str(smoke_root), image_size=32, epochs=2)
    from geodepth_lite.training import train

    train.fit(cfg, tmp_path / "home" / "runs" / "smoke" / "checkpoints" / "case1_seed0-x", progress=False, stop_after=1)
    with pytest.raises(FileNotFoundError, match="no complete run"):
        bundle.make_bundle("smoke", tmp_path / "b.zip")


def test_bundle_replaces_only_a_bundle_and_packs_only_manifests(smoke_runs, tmp_path, monkeypatch, capsys):
    """--out over a user's file (a README, notes, a zip of theirs) is refused unchanged; over an earlier
    bundle it is replaced. A run whose configuration names no dataset, or a file that is no manifest,
    is one line naming it: the file is never packed."""
    home, paths = smoke_runs
    _use(monkeypatch, home)
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    theirs = tmp_path / "theirs.zip"
    with zipfile.ZipFile(theirs, "w") as zf:
        zf.writestr("holiday.txt", "photos")
    for target in (notes, theirs):
        before = target.read_bytes()
        assert cli.main(["bundle", "--profile", "smoke", "--out", str(target)]) == 2
        assert "is not a class bundle" in capsys.readouterr().err and target.read_bytes() == before
    made = tmp_path / "class.zip"
    assert cli.main(["bundle", "--profile", "smoke", "--out", str(made)]) == 0
    assert bundle.is_bundle(made) and not bundle.is_bundle(theirs) and not bundle.is_bundle(tmp_path)
    assert cli.main(["bundle", "--profile", "smoke", "--out", str(made)]) == 0  # an earlier bundle: replaced
    capsys.readouterr()

    real = checkpoint.read_checkpoint
    for dataset, needle in ((None, "its configuration names no dataset"), (str(notes), "manifest notes.txt is not")):
        def crafted(path, *args, dataset=dataset, **kwargs):
            ckpt = real(path, *args, **kwargs)
            return {**ckpt, "cfg": {k: v for k, v in ckpt["cfg"].items() if k != "dataset"}
                    | ({} if dataset is None else {"dataset": dataset})}

        monkeypatch.setattr(bundle.checkpoint, "read_checkpoint", crafted)
        out = tmp_path / f"crafted-{dataset is None}.zip"
        assert cli.main(["bundle", "--profile", "smoke", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and "this is a bug" not in err[0], err
        assert not out.exists()


def test_a_bundle_into_a_folder_another_writer_holds_is_refused_unwritten(smoke_runs, tmp_path, monkeypatch, capsys):
    """While another process writes the folder (its lock held: a second bundle, train, synth), bundle is
    refused in one line naming that process, and writes nothing; once it is free, the bundle is written
    and the lock file is gone."""
    home, _ = smoke_runs
    _use(monkeypatch, home)
    out = tmp_path / "shared"
    out.mkdir()
    target = out / "class.zip"
    with utils.FolderLock(out, "folder of the bundle"):
        assert cli.main(["bundle", "--profile", "smoke", "--out", str(target)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"in use by process {os.getpid()}" in err[0] and str(out) in err[0], err
        assert sorted(p.name for p in out.iterdir()) == [utils.LOCK_NAME]
    assert cli.main(["bundle", "--profile", "smoke", "--out", str(target)]) == 0
    assert bundle.is_bundle(target) and sorted(p.name for p in out.iterdir()) == ["class.zip"]

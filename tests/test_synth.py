"""Dataset generation: byte-identical regeneration, verify, bad manifests, refusal to overwrite, resume."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from geodepth_lite import cli
from geodepth_lite.data import integrity, synth
from geodepth_lite.data import manifest as mf
from geodepth_lite.data.datasets import SyntheticDepthDataset

TINY = {"camera": {"width": 32, "height": 32}, "splits": {"train": 4, "test": 2}, "frames_per_scene": 2}


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _tiny(**extra):
    return mf.load_manifest("scenario_smoke", dict(TINY, **extra))


def test_same_manifest_gives_byte_identical_files(tmp_path):
    m = _tiny()
    a = synth.generate(m, tmp_path / "a", progress=False)
    b = synth.generate(m, tmp_path / "b", progress=False)
    fa, fb = _files(a), _files(b)
    assert len(fa) == 2 + (1 + 2 * 4) + (1 + 2 * 2)  # manifest, checksums; per split: jsonl, rgb + depth
    assert fa == fb
    assert integrity.verify(a) == []
    # frames.jsonl carries what the issue asks for
    rec = json.loads((a / "train" / "frames.jsonl").read_text().splitlines()[0])
    for key in ("rgb", "depth", "K", "T_world_cam", "organ", "lights", "group", "tint", "view", "lumen_share",
                "appearance"):
        assert key in rec
    assert np.asarray(rec["T_world_cam"]).shape == (4, 4) and np.asarray(rec["K"]).shape == (3, 3)
    depth = np.load(a / rec["depth"])
    assert depth.dtype == np.float32 and depth.shape == (32, 32)
    assert 0.01 <= depth[depth > 0].min() and depth.max() <= 100.0


def test_verify_names_a_flipped_byte_a_missing_and_an_unreadable_file(tmp_path, capsys):
    root = synth.generate(_tiny(), tmp_path / "d", progress=False)
    npy = root / "train" / "depth" / "000001.npy"
    data = bytearray(npy.read_bytes())
    data[-3] ^= 0x01
    npy.write_bytes(bytes(data))
    (root / "test" / "rgb" / "000000.png").unlink()
    (root / "train" / "rgb" / "000002.png").unlink()
    (root / "train" / "rgb" / "000002.png").mkdir()  # cannot be read as a file
    problems = integrity.verify(root)
    assert "changed: train/depth/000001.npy" in problems
    assert "missing: test/rgb/000000.png" in problems
    assert any(p.startswith("unreadable: train/rgb/000002.png") for p in problems)
    assert len(problems) == 3
    assert cli.main(["verify", str(root)]) == 1
    out = capsys.readouterr().out
    assert "changed: train/depth/000001.npy" in out and "missing: test/rgb/000000.png" in out


@pytest.mark.parametrize("bad, field", [
    ({"camera": {"widht": 64}}, "camera.widht"),
    ({"colour": 1}, "colour"),
    ({"seed": "zero"}, "seed"),
    ({"camera": {"width": 64.5}}, "camera.width"),
    ({"organ_presets": {"colon": {"radius": -1.0}}}, "organ_presets.colon.radius"),
    ({"camera": {"fov_x_deg": 180.0}}, "camera.fov_x_deg"),
    ({"camera": {"fov_x_deg": 200}}, "camera.fov_x_deg"),
    ({"splits": {"train": 0}}, "splits.train"),
    ({"splits": {"train": 5, "holdout": 3}}, "splits.holdout"),
    ({"textures": ["velvet"]}, "velvet"),
    ({"camera_path": {"p_wall": 0.5}}, "camera_path.p_wall"),
    ({"camera_path": {"views": {"selfie": 1.0}}}, "camera_path.views"),
    ({"camera_path": {"views": {"closeup": -1.0}}}, "camera_path.views.closeup"),
    ({"camera_path": {"views": {"closeup": 0.0}}}, "camera_path.views"),
    ({"camera_path": {"views_by_split": {"holdout": {"lumen": 1}}}}, "camera_path.views_by_split.holdout"),
    ({"camera_path": {"closeup_distance": [0.0, 1.0]}}, "camera_path.closeup_distance"),
    ({"organ_presets": {"small_intestine": {"papillae": [2, 1]}}}, "organ_presets.small_intestine.papillae"),
    ({"appearance": {"gamma": [1.2, 0.9]}}, "appearance.gamma"),
    ({"appearance": {"p_jpeg": 1.5}}, "appearance.p_jpeg"),
])
def test_bad_manifest_values_are_one_line_errors_naming_the_field(bad, field):
    with pytest.raises(ValueError) as err:
        mf.resolve_manifest(dict(bad, name="x"))
    msg = str(err.value)
    assert field in msg and "\n" not in msg


def test_cli_reports_a_bad_manifest_and_refuses_to_mix_datasets(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"name": "bad", "organ_presets": {"colon": {"radius": -2.0}}}))
    assert cli.main(["synth", "--manifest", str(bad), "--out", str(tmp_path / "x"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "organ_presets.colon.radius" in err and err.count("\n") == 1
    # an existing, different dataset is refused unless --overwrite
    small = tmp_path / "small.json"
    small.write_text(json.dumps(dict(json.loads(mf.manifest_path("scenario_smoke").read_text()), **TINY)))
    other = tmp_path / "other.json"
    other.write_text(json.dumps(dict(json.loads(small.read_text()), seed=99)))
    out = tmp_path / "ds"
    assert cli.main(["synth", "--manifest", str(small), "--out", str(out), "--no-progress"]) == 0
    assert cli.main(["synth", "--manifest", str(other), "--out", str(out), "--no-progress"]) == 2
    assert "different dataset" in capsys.readouterr().err
    assert json.loads((out / "manifest.json").read_text())["seed"] == 1  # untouched
    assert cli.main(["synth", "--manifest", str(other), "--out", str(out), "--no-progress", "--overwrite"]) == 0
    assert json.loads((out / "manifest.json").read_text())["seed"] == 99
    assert cli.main(["verify", str(out)]) == 0


def test_interrupted_generation_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    m = _tiny()
    reference = _files(synth.generate(m, tmp_path / "ref", progress=False))
    calls = {"n": 0}
    real = synth.write_files_atomic

    def dying_writer(files):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt  # as if killed in the middle of the run, at the fourth frame
        real(files)

    monkeypatch.setattr(synth, "write_files_atomic", dying_writer)
    with pytest.raises(KeyboardInterrupt):
        synth.generate(m, tmp_path / "run", progress=False)
    monkeypatch.setattr(synth, "write_files_atomic", real)
    assert not (tmp_path / "run" / "checksums.sha256").exists()
    assert integrity.verify(tmp_path / "run") != []
    synth.generate(m, tmp_path / "run", progress=False)
    assert integrity.verify(tmp_path / "run") == []
    assert _files(tmp_path / "run") == reference


def test_killed_process_is_finished_by_the_same_command(tmp_path):
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps(dict(json.loads(mf.manifest_path("scenario_smoke").read_text()),
                                        camera={"width": 48, "height": 48}, splits={"train": 60}, frames_per_scene=30)))
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "geodepth_lite", "synth", "--manifest", str(manifest), "--out", str(out),
           "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while time.time() < deadline and len(list((out / "train" / "rgb").glob("*.png"))) < 5:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "checksums.sha256").exists()
    assert subprocess.run(cmd, capture_output=True).returncode == 0
    assert integrity.verify(out) == []
    assert not list(out.rglob("*.tmp"))  # leftovers of the killed writer are cleaned up


def test_ensure_dataset_and_torch_dataset(tmp_path):
    root = synth.ensure_dataset("scenario_smoke", overrides=TINY, progress=False)
    assert root.parent == tmp_path / "home" / "data" and root.name.startswith("scenario_smoke-")
    mtime = (root / "checksums.sha256").stat().st_mtime_ns
    assert synth.ensure_dataset("scenario_smoke", overrides=TINY, progress=False) == root
    assert (root / "checksums.sha256").stat().st_mtime_ns == mtime  # complete: not regenerated
    ds = SyntheticDepthDataset(root, "train", image_size=16)
    item = ds[3]
    assert item["image"].shape == (3, 16, 16) and item["depth"].shape == (1, 16, 16)
    assert 0.0 <= float(item["image"].min()) and float(item["image"].max()) <= 1.0
    assert item["organ"] in ("colon", "small_intestine", "stomach") and "-" in item["group"]
    full = SyntheticDepthDataset(root, "train")[3]
    assert np.allclose(item["K"].numpy()[0, 0], full["K"].numpy()[0, 0] / 2)
    assert np.allclose(item["K"].numpy()[0, 2], (full["K"].numpy()[0, 2] + 0.5) / 2 - 0.5)
    # nearest-exact: every resized depth value is one of the rendered ones
    assert np.isin(item["depth"].numpy(), full["depth"].numpy()).all()
    with pytest.raises(FileNotFoundError, match="no split 'val'"):
        SyntheticDepthDataset(root, "val")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        SyntheticDepthDataset(tmp_path / "nowhere", "train")


def test_a_dataset_folder_has_one_writer_and_ensure_dataset_waits_for_it(tmp_path, capsys, smoke_root, monkeypatch):
    """Two notebooks asking for the same missing dataset at once: the second waits for the first, then finds
    it complete and renders nothing; `synth --out` into a folder being written is refused in one line."""
    import os
    import shutil
    import threading

    from conftest import one_line_error

    out = tmp_path / "scenario_smoke"
    held, go, done = threading.Event(), threading.Event(), threading.Event()

    def first_writer():
        lock = synth.dataset_lock(out).acquire()
        held.set()
        go.wait(30)
        shutil.copytree(smoke_root, out, dirs_exist_ok=True)  # the dataset, written while the lock is held
        time.sleep(0.2)
        lock.release()
        done.set()

    threading.Thread(target=first_writer).start()
    assert held.wait(10)
    assert cli.main(["synth", "--manifest", "scenario_smoke", "--out", str(out), "--no-progress"]) == 2
    one_line_error(capsys, str(out), f"in use by process {os.getpid()}")
    assert os.listdir(out) == [".lock"]

    def rendered_again(*args, **kwargs):
        raise AssertionError("the dataset was rendered again")

    def wait_then_let_the_writer_go(lock, *args, **kwargs):  # the writer finishes only once this one waits
        go.set()
        return real_wait(lock, *args, **kwargs)

    real_wait = synth.wait_for_lock
    monkeypatch.setattr(synth, "wait_for_lock", wait_then_let_the_writer_go)
    monkeypatch.setattr(synth, "_generate", rendered_again)
    monkeypatch.setattr(synth, "generate", rendered_again)
    assert synth.ensure_dataset("scenario_smoke", root=tmp_path, progress=False) == out
    assert done.wait(10) and integrity.is_complete_by(out, mf.load_manifest("scenario_smoke"), None)
    assert f"waiting for the process making the dataset (PID {os.getpid()}) holding {out}" in capsys.readouterr().out
    assert not (out / ".lock").exists() and _files(out) == _files(smoke_root)

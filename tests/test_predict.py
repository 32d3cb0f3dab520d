"""``predict``: a folder with a corrupt file, any image sizes, video, intrinsics, and bad input."""

import json

import imageio.v3 as iio
import numpy as np
import pytest

from geodepth_lite import camera, cli, predict, recon


def _cli(argv):
    """``python -m geodepth_lite <argv>`` in-process (exit status)."""
    return cli.main(argv)


@pytest.fixture(scope="module")
def checkpoint(untrained_checkpoint):
    return untrained_checkpoint


def _frame(h, w, seed):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def test_folder_with_a_corrupt_file_processes_the_others_and_names_it(tmp_path, checkpoint, capsys):
    src = tmp_path / "in"
    src.mkdir()
    iio.imwrite(src / "a.png", _frame(40, 56, 0))
    iio.imwrite(src / "b.jpg", _frame(33, 47, 1))
    iio.imwrite(src / "c.png", _frame(64, 64, 2))
    (src / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    (src / "notes.txt").write_text("ignored: not an image")
    out = tmp_path / "out"
    code = _cli(["predict", "--checkpoint", str(checkpoint), "--input", str(src), "--out", str(out),
                     "--batch-size", "2", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert "broken.png" in err and "a.png" not in err
    for name, (h, w) in {"a": (40, 56), "b": (33, 47), "c": (64, 64)}.items():
        depth = np.load(out / f"{name}_depth.npy")
        assert depth.shape == (h, w) and depth.dtype == np.float32 and np.isfinite(depth).all() and (depth > 0).all()
        assert iio.imread(out / f"{name}_depth.png").shape == (h, w, 3)
        ply = recon.load_ply(out / f"{name}.ply")
        assert ply.n_points == h * w
        # the PLY is the depth back-projected with the default intrinsics (about 84 degrees)
        K = camera.intrinsics_from_fov(w, h, predict.DEFAULT_FOV_DEG)
        np.testing.assert_allclose(np.asarray(ply.points),
                                   camera.backproject(depth.astype(np.float64), K).reshape(-1, 3),
                                   rtol=1e-5, atol=1e-6)
    assert not (out / "broken_depth.npy").exists()
    assert not list(out.glob(".*.tmp"))


def test_batching_does_not_change_the_prediction(checkpoint):
    from geodepth_lite.checkpoint import load_model

    model, cfg = load_model(checkpoint)
    frames = [_frame(40, 56, 0), _frame(33, 47, 1), _frame(64, 64, 2)]
    together = predict.predict_frames(model, frames, cfg["image_size"])
    alone = [predict.predict_frames(model, [f], cfg["image_size"])[0] for f in frames]
    for a, b in zip(together, alone):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_predict_averages_the_mirrorings_by_default(tmp_path, checkpoint):
    """The CLI's depth is predict_frames with flips "hv" unless --flips says otherwise."""
    from geodepth_lite.checkpoint import load_model

    model, cfg = load_model(checkpoint)
    src = tmp_path / "in"
    src.mkdir()
    frame = _frame(40, 56, 3)
    iio.imwrite(src / "a.png", frame)
    for flips, args in (("hv", []), ("none", ["--flips", "none"])):
        out = tmp_path / flips
        assert _cli(["predict", "--checkpoint", str(checkpoint), "--input", str(src), "--out", str(out),
                     "--ply", "none", "--no-progress", *args]) == 0
        want = predict.predict_frames(model, [frame], cfg["image_size"], flips)[0]
        np.testing.assert_allclose(np.load(out / "a_depth.npy"), want, rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.load(tmp_path / "hv" / "a_depth.npy"), np.load(tmp_path / "none" / "a_depth.npy"))


def test_video_and_intrinsics_file(tmp_path, checkpoint):
    video = tmp_path / "clip.mp4"
    iio.imwrite(video, np.stack([_frame(48, 64, k) for k in range(3)]), fps=10)
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps({"fx": 100.0, "fy": 110.0, "cx": 63.5, "cy": 47.5, "width": 128, "height": 96}))
    out = tmp_path / "out"
    code = _cli(["predict", "--checkpoint", str(checkpoint), "--input", str(video), "--out", str(out),
                     "--intrinsics", str(calib), "--no-progress"])
    assert code == 0
    assert sorted(p.name for p in out.glob("*.npy")) == [f"clip_{k:06d}_depth.npy" for k in range(3)]
    depth = np.load(out / "clip_000001_depth.npy")
    K = camera.scale_intrinsics(np.array([[100.0, 0, 63.5], [0, 110.0, 47.5], [0, 0, 1]]), 0.5)
    pts = np.asarray(recon.load_ply(out / "clip_000001.ply").points)
    np.testing.assert_allclose(pts, camera.backproject(depth.astype(np.float64), K).reshape(-1, 3),
                               rtol=1e-5, atol=1e-6)


def test_bad_input_gets_a_one_line_error(tmp_path, checkpoint, capsys):
    (tmp_path / "empty").mkdir()
    bad_calib = tmp_path / "k.yaml"
    bad_calib.write_text("fx: 100\nfy: 100\n")
    iio.imwrite(tmp_path / "x.png", _frame(8, 8, 0))
    cases = {
        "--input not found": ["--input", str(tmp_path / "nope")],
        "holds no images": ["--input", str(tmp_path / "empty")],
        "missing cx, cy": ["--input", str(tmp_path / "x.png"), "--intrinsics", str(bad_calib)],
        "--fov must be between 0 and 180": ["--input", str(tmp_path / "x.png"), "--fov", "190"],
    }
    for message, argv in cases.items():
        code = _cli(["predict", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "o"), *argv])
        assert code == 2
        assert message in capsys.readouterr().err

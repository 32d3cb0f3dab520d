"""Each public-dataset loader on a tiny fixture written in the dataset's own layout and encoding."""

import argparse
import json
import re
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile
import torch

from geodepth_lite import utils
from geodepth_lite.core import camera
from geodepth_lite.data import datasets
from geodepth_lite.evaluation import evaluate, evaluate_cli

H, W = 6, 8


def _rgb(seed):
    return np.random.default_rng(seed).integers(0, 256, size=(H, W, 3), dtype=np.uint8)


def _write_endoslam(root, organs=("Colon", "Stomach", "SmallIntestine"), n=3):
    """UnityCam/<Organ>/Frames, 'Pixelwise Depths' (RGBA 8-bit, depth in channel 0), Poses/*.csv."""
    truth = {}
    for o, organ in enumerate(organs):
        d = root / "UnityCam" / organ
        (d / "Frames").mkdir(parents=True)
        (d / "Pixelwise Depths").mkdir()
        (d / "Poses").mkdir()
        rows = ["tX,tY,tZ,rX,rY,rZ,rW,time"]
        for k in range(n):
            iio.imwrite(d / "Frames" / f"image_{k:04d}.png", _rgb(10 * o + k))
            gray = np.full((H, W), 40 + 20 * k + o, dtype=np.uint8)
            gray[0, 0] = 0  # no depth
            aov = np.stack([gray, np.full_like(gray, 200), np.zeros_like(gray), np.full_like(gray, 255)], -1)
            iio.imwrite(d / "Pixelwise Depths" / f"aov_image_{k:04d}.png", aov)
            truth[(organ, k)] = gray.astype(np.float64) / 255.0
            rows.append(f"{k}.0,{2 * k}.0,{3 * k}.0,0,0,0,1,{k / 30:.4f}")
        (d / "Poses" / "poses.csv").write_text("\n".join(rows) + "\n")
    return truth


def test_endoslam_layout_channel0_scaling_invalid_and_poses(tmp_path):
    truth = _write_endoslam(tmp_path)
    ds = datasets.open_dataset("endoslam", tmp_path)
    assert len(ds) == 9 and ds.depth_units == "relative"
    assert ds.counts("organ") == {"colon": 3, "small_intestine": 3, "stomach": 3}
    st = datasets.open_dataset("endoslam", tmp_path / "UnityCam", organ="stomach")
    assert len(st) == 3
    item = st[2]
    assert set(item) == {"image", "depth", "K", "organ", "group", "index", "valid"}
    assert item["image"].shape == (3, H, W) and item["image"].dtype == torch.float32
    assert item["depth"].shape == (1, H, W) and item["valid"].dtype == torch.bool
    np.testing.assert_allclose(item["depth"][0].numpy(), truth[("Stomach", 2)], atol=1e-6)
    assert not item["valid"][0, 0, 0] and item["valid"].sum() == H * W - 1
    np.testing.assert_allclose(item["image"].permute(1, 2, 0).numpy() * 255, _rgb(10 * 1 + 2), atol=1e-3)
    np.testing.assert_allclose(item["K"].numpy(), camera.intrinsics(W, H), rtol=1e-6)
    T = st.frames[2]["T_world_cam"]  # Unity (2, 4, 6), identity rotation -> y flips to OpenCV
    np.testing.assert_allclose(T[:3, 3], [2.0, -4.0, 6.0])
    np.testing.assert_allclose(T[:3, :3], np.eye(3))


def test_image_size_resizes_everything(tmp_path):
    _write_endoslam(tmp_path, organs=("Colon",), n=1)
    ds = datasets.open_dataset("endoslam", tmp_path, image_size=(12, 16))
    item = ds[0]
    assert item["image"].shape == (3, 12, 16) and item["depth"].shape == (1, 12, 16)
    assert item["valid"][0, :2, :2].logical_not().all() and item["valid"].sum() == 12 * 16 - 4
    np.testing.assert_allclose(item["K"].numpy(), camera.scale_intrinsics(camera.intrinsics(W, H), 2.0), rtol=1e-6)


def _write_colondepth(root, groups=((1, 1), (2, 2), (3, 3)), n=2, bits=8):
    truth = {}
    for t, light in groups:
        for k in (1, 2):
            d = root / f"T{t}_L{light}_{k}_resized"
            d.mkdir(parents=True)
            for i in range(n):
                iio.imwrite(d / f"FrameBuffer_{i:04d}.png", _rgb(t * 100 + k * 10 + i))
                if bits == 8:
                    raw = np.arange(H * W, dtype=np.uint8).reshape(H, W) * 5
                    unit = raw / 255.0
                else:
                    raw = (np.arange(H * W, dtype=np.uint16).reshape(H, W) * 1300).astype(np.uint16)
                    unit = raw / 65535.0
                iio.imwrite(d / f"Depth_{i:04d}.png", raw)
                truth[(d.name, i)] = unit * 20.0
    (root / "README.txt").write_text("not a frame folder")
    return truth


@pytest.mark.parametrize("bits", [8, 16])
def test_colondepth_unit_png_to_20cm_groups_and_sequences(tmp_path, bits):
    truth = _write_colondepth(tmp_path, bits=bits)
    ds = datasets.open_dataset("colondepth", tmp_path)
    assert len(ds) == 12 and ds.depth_units == "cm"
    assert ds.counts("group") == {"T1-L1": 4, "T2-L2": 4, "T3-L3": 4}
    sub = datasets.open_dataset("colondepth", tmp_path, group="T2-L2", sequence=["T2_L2_2_resized"])
    assert [f["frame"] for f in sub.frames] == [0, 1]
    item = sub[1]
    np.testing.assert_allclose(item["depth"][0].numpy(), truth[("T2_L2_2_resized", 1)], rtol=1e-6, atol=1e-6)
    assert item["depth"].max() <= 20.0 and not item["valid"][0, 0, 0] and item["valid"].sum() == H * W - 1
    assert item["group"] == "T2-L2" and item["organ"] == "colon"


def _write_simcol3d(root):
    c = root / "SyntheticColon_II"
    for seq in ("Frames_S1", "Frames_B4"):
        (c / seq).mkdir(parents=True)
        for i in range(2):
            iio.imwrite(c / seq / f"FrameBuffer_{i:04d}.png", _rgb(i))
            raw = np.full((H, W), 255 * 256 // 2, dtype=np.uint16)  # 0.5 -> 10 cm
            raw[1, 2] = 0
            raw[2, 3] = 65535  # 65535 / 65280 * 20 cm, a little over 20
            iio.imwrite(c / seq / f"Depth_{i:04d}.png", raw)
    (c / "cam.txt").write_text("227.6 0 240.5\n0 227.6 237.0\n0 0 1\n")
    (c / "SavedPosition_S1.txt").write_text("1.0 2.0 3.0\n4.0 5.0 6.0\n")
    s = np.sqrt(0.5)  # 90 degrees about z
    (c / "SavedRotationQuaternion_S1.txt").write_text(f"0 0 0 1\n0 0 {s} {s}\n")
    return c


def test_simcol3d_16bit_divide_by_255_256_and_cam_txt(tmp_path):
    c = _write_simcol3d(tmp_path)
    for root in (tmp_path, c):
        ds = datasets.open_dataset("simcol3d", root)
        assert len(ds) == 4
        assert ds.counts("sequence") == {"SyntheticColon_II/Frames_B4": 2, "SyntheticColon_II/Frames_S1": 2}
    item = ds[0]
    d = item["depth"][0].numpy()
    assert d[0, 0] == pytest.approx(10.0)
    assert d[2, 3] == pytest.approx(65535 / 65280 * 20.0, rel=1e-6)
    assert d[1, 2] == 0 and not item["valid"][0, 1, 2] and item["valid"].sum() == H * W - 1
    np.testing.assert_allclose(item["K"].numpy(), [[227.6, 0, 240.5], [0, 227.6, 237.0], [0, 0, 1]], rtol=1e-6)
    s1 = [f for f in ds.frames if f["sequence"].endswith("Frames_S1")]
    np.testing.assert_allclose(s1[1]["T_world_cam"][:3, 3], [4.0, -5.0, 6.0])  # y flipped to OpenCV's
    # a Unity rotation of 90 degrees about z becomes -90 degrees about z once y is flipped
    np.testing.assert_allclose(s1[1]["T_world_cam"][:3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert all(f["T_world_cam"] is None for f in ds.frames if f["sequence"].endswith("Frames_B4"))


def _write_c3vd(root, pose_order="column"):
    seq = root / "cecum_t1_a"
    seq.mkdir(parents=True)
    lines = []
    for i in range(3):
        iio.imwrite(seq / f"{i}_color.png", _rgb(i))
        raw = np.full((H, W), 6553 * (i + 1), dtype=np.uint16)
        raw[0, 1] = 0
        raw[3, 3] = 65535
        tifffile.imwrite(seq / f"{i:04d}_depth.tiff", raw)
        T = np.eye(4)
        T[:3, 3] = [i, 10 + i, 100 + i]
        T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
        flat = T.T.ravel() if pose_order == "column" else T.ravel()
        lines.append(",".join(f"{v:g}" for v in flat))
    (seq / "pose.txt").write_text("\n".join(lines) + "\n")
    return seq


@pytest.mark.parametrize("order", ["column", "row"])
def test_c3vd_16bit_tiff_to_100mm_invalid_values_and_poses(tmp_path, order):
    seq = _write_c3vd(tmp_path, order)
    ds = datasets.open_dataset("c3vd", tmp_path, group="cecum")
    assert len(ds) == 3 and ds.depth_units == "mm"
    item = ds[1]
    d = item["depth"][0].numpy()
    assert d[5, 5] == pytest.approx(13106 / 65535 * 100.0, rel=1e-6)
    assert not item["valid"][0, 0, 1] and not item["valid"][0, 3, 3] and item["valid"].sum() == H * W - 2
    assert d[0, 1] == 0 and d[3, 3] == 0
    T = ds.frames[2]["T_world_cam"]
    np.testing.assert_allclose(T[:3, 3], [2, 12, 102])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    # pinhole approximation scaled from 1350x1080 to the fixture's size
    K = item["K"].numpy()
    assert K[0, 0] == pytest.approx(767.4 * W / 1350, rel=1e-4)
    assert len(datasets.open_dataset("c3vd", seq)) == 3


@pytest.mark.parametrize("name", datasets.DATASETS)
def test_missing_empty_and_wrong_layout_roots_say_what_was_expected(tmp_path, name):
    with pytest.raises(FileNotFoundError, match="does not exist; expected"):
        datasets.open_dataset(name, tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="is empty; expected"):
        datasets.open_dataset(name, tmp_path / "empty")
    other = tmp_path / "other"
    (other / "images").mkdir(parents=True)
    iio.imwrite(other / "images" / "a.png", _rgb(0))
    layout = re.escape(datasets.REGISTRY[name].layout[:20])
    with pytest.raises(ValueError, match=rf"holds no {name} frame/depth pairs.*expected .*{layout}"):
        datasets.open_dataset(name, other)


def test_bad_options_are_named(tmp_path):
    _write_colondepth(tmp_path, groups=((1, 1),), n=1)
    with pytest.raises(ValueError, match="unknown dataset 'kitti'"):
        datasets.open_dataset("kitti", tmp_path)
    with pytest.raises(ValueError, match=r"group \['T9-L9'\] matches no frames.*available: T1-L1"):
        datasets.open_dataset("colondepth", tmp_path, group="T9-L9")
    with pytest.raises(ValueError, match="limit"):
        datasets.open_dataset("colondepth", tmp_path, limit=0)
    with pytest.raises(ValueError, match="image_size"):
        datasets.open_dataset("colondepth", tmp_path, image_size=(0, 4))
    # a depth map whose size differs from its frame is named
    iio.imwrite(tmp_path / "T1_L1_1_resized" / "Depth_0000.png", np.ones((3, 3), np.uint8))
    with pytest.raises(ValueError, match="FrameBuffer_0000.png is 8x6 but its depth Depth_0000.png is 3x3"):
        datasets.open_dataset("colondepth", tmp_path)[0]


def test_check_subset_counts_and_reports_mismatches(tmp_path, capsys):
    from geodepth_lite import cli

    _write_colondepth(tmp_path, groups=((1, 1), (2, 2)), n=2)
    manifest = datasets.load_subset_manifest("colondepth")
    assert [s["frames"] for s in manifest["subsets"]] == [364, 364, 364]
    assert [s["frames"] for s in datasets.load_subset_manifest("endoslam")["subsets"]] == [1548, 1257, 1062]
    small = dict(manifest, subsets=[dict(s, frames=4) for s in manifest["subsets"]])
    small["subsets"][1]["frames"] = 3
    rows = datasets.count_subset_frames(small, tmp_path)
    assert [(r["subset"], r["found"], r["status"]) for r in rows] == [
        ("T1-L1", 4, "ok"), ("T2-L2", 4, "more"), ("T3-L3", 0, "missing")]
    path = tmp_path / "m.json"
    path.write_text(json.dumps(dict(small, subsets=small["subsets"][:1])))
    # `evaluate --check`: the subset report without a checkpoint, exit 0 only when every subset matches
    out = subprocess.run([sys.executable, "-m", "geodepth_lite", "evaluate", "--dataset", "colondepth",
                          "--root", str(tmp_path), "--check", str(path)], capture_output=True, text=True)
    assert out.returncode == 0 and "T1-L1" in out.stdout, out.stderr
    assert cli.main(["evaluate", "--dataset", "colondepth", "--root", str(tmp_path), "--check"]) == 1
    report = capsys.readouterr().out
    assert "fewer" in report and "missing" in report and "364" in report


def test_evaluate_check_needs_a_public_dataset_with_subsets_and_a_root(tmp_path, capsys):
    from geodepth_lite import cli

    _write_c3vd(tmp_path)
    assert cli.main(["evaluate", "--dataset", "c3vd", "--root", str(tmp_path), "--check"]) == 2
    assert "c3vd has no evaluation subset manifest" in capsys.readouterr().err
    assert cli.main(["evaluate", "--dataset", "colondepth", "--root", str(tmp_path), "--check", "endoslam"]) == 2
    assert "describes endoslam, not colondepth" in capsys.readouterr().err
    assert cli.main(["evaluate", "--dataset", "colondepth", "--check"]) == 2
    assert "--check needs --root" in capsys.readouterr().err
    assert cli.main(["evaluate", "--dataset", "scenario_teach", "--check"]) == 2
    assert "--check applies to the public datasets" in capsys.readouterr().err
    assert cli.main(["evaluate", "--dataset", "colondepth", "--root", str(tmp_path)]) == 2
    assert "--checkpoint is required" in capsys.readouterr().err


def test_the_registry_is_the_only_list_of_datasets():
    assert datasets.DATASETS == tuple(datasets.REGISTRY) == ("endoslam", "colondepth", "simcol3d", "c3vd")
    for name, cls in datasets.REGISTRY.items():
        assert issubclass(cls, datasets.PublicDepthDataset) and cls is not datasets.PublicDepthDataset
        assert cls.name == name and cls.layout.startswith("ROOT") and cls.__doc__
        assert cls.depth_units in ("relative", "cm", "mm") and cls.max_depth > 0
        for method in ("find_frames", "decode_depth", "intrinsics"):  # each dataset says how it is read
            assert method in vars(cls), f"{cls.__name__} does not override {method}"
        if cls.subset_manifest is not None:
            assert datasets.load_subset_manifest(cls.subset_manifest)["dataset"] == name
    manifests = sorted(p.stem for p in (utils.manifests_dir() / "eval_subsets").glob("*.json"))
    assert manifests == sorted(c.subset_manifest for c in datasets.REGISTRY.values() if c.subset_manifest)
    assert set(WRITERS) == set(datasets.REGISTRY)  # one fixture per registered dataset
    assert not hasattr(evaluate, "PUBLIC_DATASETS")
    parser = argparse.ArgumentParser()
    evaluate_cli.add_arguments_evaluate(parser)
    listed = re.search(r"or one of (\w+(?:, \w+)*)", " ".join(parser.format_help().split())).group(1)
    assert tuple(listed.split(", ")) == tuple(datasets.REGISTRY)
    with pytest.raises(TypeError, match="abstract"):
        datasets.PublicDepthDataset(".", [])


WRITERS = {"endoslam": _write_endoslam, "colondepth": _write_colondepth, "simcol3d": _write_simcol3d,
           "c3vd": _write_c3vd}


@pytest.mark.parametrize("name", datasets.DATASETS)
def test_evaluate_cli_runs_the_protocol_on_each_fixture(tmp_path, name, untrained_checkpoint, capsys,
                                                        monkeypatch):
    from geodepth_lite import cli

    bounds = {}  # the mask's max_depth that the model's and the baselines' rows are scored with

    def recording(fn):
        def wrapper(*args, **kw):
            bounds[fn.__name__] = kw.get("max_depth")
            return fn(*args, **kw)
        return wrapper

    monkeypatch.setattr(evaluate, "evaluate_model", recording(evaluate.evaluate_model))
    monkeypatch.setattr(evaluate, "evaluate_baselines", recording(evaluate.evaluate_baselines))
    root = tmp_path / "data"
    WRITERS[name](root)
    n = len(datasets.open_dataset(name, root))
    out = tmp_path / "eval"
    code = cli.main(["evaluate", "--checkpoint", str(untrained_checkpoint), "--dataset", name, "--root", str(root),
                     "--out", str(out), "--error-maps", "1", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    result = json.loads((out / "metrics.json").read_text())
    assert result["n"] == n
    assert 0.0 < result["overall"]["a3"] <= 1.0 and np.isfinite(result["overall"]["rmse"])
    assert bounds == {"evaluate_model": datasets.REGISTRY[name].max_depth,
                      "evaluate_baselines": datasets.REGISTRY[name].max_depth}


def test_evaluate_as_a_process_and_a_wrong_root_is_named(tmp_path, untrained_checkpoint, capsys):
    from geodepth_lite import cli

    _write_colondepth(tmp_path / "data", groups=((1, 1),), n=1)
    base = ["evaluate", "--checkpoint", str(untrained_checkpoint), "--out", str(tmp_path / "eval"), "--no-progress"]
    ok = subprocess.run([sys.executable, "-m", "geodepth_lite", *base, "--dataset", "colondepth",
                         "--root", str(tmp_path / "data"), "--group", "T1-L1"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert cli.main(base + ["--dataset", "endoslam", "--root", str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err
    assert "holds no endoslam frame/depth pairs" in err and "UnityCam" in err


# The text files of a public dataset (a camera's calibration, poses) crafted against the loaders:
# (dataset, file to spoil, relative to the fixture's root, its new bytes, what the one line says).
SPOILED_TEXT = [
    ("simcol3d", "SyntheticColon_II/cam.txt", b"227.6 abc 240.5 237\n", "cam.txt: 'abc' is not a finite number"),
    ("simcol3d", "SyntheticColon_II/SavedPosition_S1.txt", b"1 2 3\n4 5 nan\n",
     "SavedPosition_S1.txt:2: 'nan' is not a finite number"),
    ("c3vd", "cecum_t1_a/pose.txt", b"0,1,0,0,-1,0,0,0,0,0,1,0,inf,10,100,1\n", "pose.txt:1: 'inf' is not a finite"),
    ("c3vd", "cecum_t1_a/pose.txt", b"\xff\xfe\x00" * 20, "pose.txt: not a UTF-8 text file"),
    ("endoslam", "UnityCam/Colon/Poses/poses.csv", b"tX,tY,tZ,rX,rY,rZ,rW\n1,2,3,0,0,0,1\n1,2,x3,0,0,0,1\n",
     "poses.csv:3: 'x3' is not a finite number"),
]


@pytest.mark.parametrize("name, rel, content, needle", SPOILED_TEXT,
                         ids=[f"{n}-{r.rsplit('/', 1)[-1]}-{i}" for i, (n, r, _, _) in enumerate(SPOILED_TEXT)])
def test_a_spoiled_text_file_of_a_dataset_is_one_line_naming_it(tmp_path, name, rel, content, needle,
                                                                untrained_checkpoint, capsys):
    """Never a bug line (a word where a number belongs) and never a NaN pose or camera taken in: exit 2."""
    from geodepth_lite import cli

    root = tmp_path / "data"
    WRITERS[name](root)
    (root / rel).write_bytes(content)
    code = cli.main(["evaluate", "--checkpoint", str(untrained_checkpoint), "--dataset", name, "--root", str(root),
                     "--out", str(tmp_path / "eval"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0] and str(root / rel) in err[0], (code, err)


def test_a_dataset_text_file_over_the_limit_is_refused_before_it_is_read(tmp_path, monkeypatch):
    from geodepth_lite.data import bounds

    _write_c3vd(tmp_path)
    monkeypatch.setattr(bounds, "MAX_TEXT_BYTES", 100)  # the fixture's pose.txt is about 190 bytes
    with pytest.raises(utils.FileProblem, match="pose.txt: over the limit of 100 bytes"):
        datasets.open_dataset("c3vd", tmp_path)

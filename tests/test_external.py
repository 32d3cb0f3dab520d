"""external: another simulator's sample, checked byte for byte, decoded with known answers, scored."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from geodepth_lite.core import metrics
from geodepth_lite.core.model import DepthNet
from geodepth_lite.data.integrity import file_sha256
from geodepth_lite.evaluation import external


def test_the_simcol3d_manifest_names_ten_pairs_and_their_source():
    m = external.load_sample_manifest("simcol3d_sample")
    assert m["dataset"] == "simcol3d" and len(m["files"]) == 10
    assert m["source"]["commit"] and "CC BY-NC-SA" in m["licence"]
    assert all(len(f["rgb_sha256"]) == len(f["depth_sha256"]) == 64 for f in m["files"])


def test_an_unknown_sample_and_an_empty_folder_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no external sample 'nope'.*simcol3d_sample"):
        external.load_sample_manifest("nope")
    problems = external.check_copy("simcol3d_sample", tmp_path)
    assert len(problems) == 20 and problems[0] == f"{tmp_path / 'FrameBuffer_0000.png'}: missing"
    assert external.check_copy("simcol3d_sample", tmp_path / "absent") == [f"{tmp_path / 'absent'}: not a folder"]


@pytest.fixture
def tiny_sample(tmp_path, monkeypatch):
    """Two 64 x 64 frames in SimCol3D's encoding: the top half at 65280 (20 cm), the bottom half at
    32640 (10 cm), one pixel 0 (invalid); and a manifest naming them with their checksums."""
    root = tmp_path / "frames"
    root.mkdir()
    files = []
    for i in range(2):
        raw = np.full((64, 64), 32640, np.uint16)
        raw[:32] = 65280
        raw[5, 7] = 0
        Image.fromarray(raw).save(root / f"Depth_{i:04d}.png")
        rgb = np.full((64, 64, 3), 40 + 100 * i, np.uint8)
        Image.fromarray(rgb).save(root / f"FrameBuffer_{i:04d}.png")
        files.append({"rgb": f"FrameBuffer_{i:04d}.png", "depth": f"Depth_{i:04d}.png",
                      "rgb_sha256": file_sha256(root / f"FrameBuffer_{i:04d}.png"),
                      "depth_sha256": file_sha256(root / f"Depth_{i:04d}.png")})
    manifest = tmp_path / "tiny.json"
    manifest.write_text(json.dumps({"name": "tiny", "dataset": "simcol3d", "source": {}, "licence": "test",
                                    "files": files}))
    monkeypatch.setattr(external, "sample_manifest_path", lambda name: manifest)
    return root


def test_the_frames_decode_to_known_depths(tiny_sample):
    ds = external.sample_dataset("tiny", tiny_sample)
    assert len(ds) == 2
    item = ds[1]
    depth, valid = item["depth"][0].numpy(), item["valid"][0].numpy()
    assert depth[0, 0] == pytest.approx(20.0) and depth[63, 0] == pytest.approx(10.0)
    assert not valid[5, 7] and valid.sum() == 64 * 64 - 1
    assert item["image"].shape == (3, 64, 64) and float(item["image"][0, 0, 0]) == pytest.approx(140 / 255)


def test_a_changed_file_is_refused_by_name(tiny_sample):
    p = tiny_sample / "Depth_0001.png"
    raw = np.asarray(Image.open(p)).copy()
    raw[0, 0] = 65000
    Image.fromarray(raw).save(p)
    with pytest.raises(ValueError, match="Depth_0001.png: not the file of the manifest"):
        external.sample_dataset("tiny", tiny_sample)


def test_scores_with_known_answers_and_their_round_trip(tiny_sample, tmp_path):
    """A constant depth, median-scaled, is the median of the valid depth everywhere; with 2047
    pixels at 20 and 2048 at 10 cm that is 10, so Abs Rel = (2047 * 0.5 + 2048 * 0) / 4095."""
    torch.manual_seed(0)
    ds = external.sample_dataset("tiny", tiny_sample)
    rows = external.score_sample(ds, DepthNet().eval(), 32, "none", np.full((64, 64), 3.0), "net")
    assert [(r["method"], r["frame"]) for r in rows] == [(m, f) for m in ("net", "baseline: constant",
                                                                          "baseline: mean_depth_map",
                                                                          "baseline: shading_prior")
                                                        for f in (0, 1)]
    const = [r for r in rows if r["method"] == "baseline: constant"]
    assert const[0]["abs_rel"] == pytest.approx(2047 * 0.5 / 4095, rel=1e-6)
    assert all(np.isfinite([r[k] for r in rows for k in metrics.METRIC_NAMES]))
    s = external.summary(rows)
    assert s["baseline: constant"]["frames"] == 2 and s["baseline: constant"]["abs_rel"] == pytest.approx(
        2047 * 0.5 / 4095, rel=1e-6)
    back = external.read_scores(external.write_scores(tmp_path / "s.csv", rows))
    assert [r["method"] for r in back] == [r["method"] for r in rows]
    assert all(b[k] == pytest.approx(r[k], rel=1e-5) for b, r in zip(back, rows) for k in metrics.METRIC_NAMES)


def test_the_committed_scores_are_the_sample_s_ten_frames_for_four_methods():
    rows = external.read_scores(external.committed_scores("simcol3d_sample"))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    assert len(methods) == 4 and methods[1:] == ["baseline: constant", "baseline: mean_depth_map",
                                                  "baseline: shading_prior"]
    assert all(sorted(r["frame"] for r in rows if r["method"] == m) == list(range(10)) for m in methods)

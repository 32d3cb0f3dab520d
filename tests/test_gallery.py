"""gallery: the shipped real frames checked byte for byte; the two numbers against the shading prior
with known answers; a frame through predict's path; a folder of one's own."""

import csv
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from geodepth_lite.core.model import DepthNet
from geodepth_lite.data.integrity import file_sha256
from geodepth_lite.evaluation import gallery


def _prior(h=32, w=32):
    """A positive map with a far (large) disc left of centre on a near (small) ramp."""
    yy, xx = np.mgrid[0:h, 0:w]
    return (1.0 + 0.01 * xx + 3.0 * np.exp(-((xx - 10) ** 2 + (yy - 16) ** 2) / 20.0)).astype(np.float32)


def test_the_shipped_frames_are_all_there_with_their_views_and_licence():
    frames = gallery.gallery_frames()
    assert len(frames) == 17
    views = [f["view"] for f in frames]
    assert {"lumen", "wall", "close-up", "dyed"} <= set(views)
    assert views == sorted(views, key=gallery.VIEW_ORDER.index)  # grouped in VIEW_ORDER
    text = (gallery.gallery_dir() / "ATTRIBUTION.md").read_text()
    assert "CC BY 4.0" in text and "10.1038/s41597-020-00622-y" in text


def test_agreement_and_far_share_have_known_answers():
    prior = _prior()
    mask = np.ones_like(prior, dtype=bool)
    r, share = gallery.compare_to_shading(prior * 7.0, prior, mask)  # the same relief, any scale
    assert r == pytest.approx(1.0) and share == 0.0
    r, share = gallery.compare_to_shading(1.0 / prior, prior, mask)  # far exactly where the image is bright
    assert r == pytest.approx(-1.0) and share == 1.0
    assert share > gallery.BLOB_LIMIT


def test_a_far_blob_in_the_middle_of_a_bright_frame_is_flagged_and_a_lumen_is_not():
    yy, xx = np.mgrid[0:48, 0:48]
    blob = 1.0 + 4.0 * np.exp(-((xx - 24) ** 2 + (yy - 24) ** 2) / 60.0)  # far in the middle
    bright_middle = 1.0 / blob  # the image is brightest (nearest by shading) in the middle
    mask = np.ones((48, 48), dtype=bool)
    assert gallery.compare_to_shading(blob, bright_middle, mask)[1] > gallery.BLOB_LIMIT
    assert gallery.compare_to_shading(blob, blob ** 0.5, mask)[1] == 0.0  # a dark lumen in the middle


def test_the_mask_decides_which_pixels_count():
    prior = _prior()
    depth = prior.copy()
    depth[:, :8] = 1.0 / prior[:, :8]  # wrong only in the left quarter
    mask = np.ones_like(prior, dtype=bool)
    r_all, _ = gallery.compare_to_shading(depth, prior, mask)
    mask[:, :8] = False
    r_in, share_in = gallery.compare_to_shading(depth, prior, mask)
    assert r_in == pytest.approx(1.0) and share_in == 0.0
    assert r_all < 0.99  # the check sees the wrong quarter when it is inside


def test_a_flat_map_gives_nan_not_a_number_that_means_something():
    prior = _prior()
    r, share = gallery.compare_to_shading(np.ones_like(prior), prior, np.ones_like(prior, dtype=bool))
    assert np.isnan(r) and np.isnan(share)


def _folder_with_frames(tmp_path, n=2, size=(40, 52)):
    folder = tmp_path / "mine"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(40, 220, (*size, 3), dtype=np.uint8)).save(folder / f"f{i}.png")
    return folder


def test_a_folder_without_frames_csv_is_unlabelled_and_a_csv_labels_and_checks_it(tmp_path):
    folder = _folder_with_frames(tmp_path)
    frames = gallery.gallery_frames(folder)
    assert [f["view"] for f in frames] == ["unlabelled", "unlabelled"]
    with open(folder / "frames.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["file", "view", "sha256"])
        w.writerow(["f0.png", "wall", file_sha256(folder / "f0.png")])
        w.writerow(["f1.png", "lumen", ""])
    assert [(f["path"].name, f["view"]) for f in gallery.gallery_frames(folder)] == [("f1.png", "lumen"),
                                                                                      ("f0.png", "wall")]
    (folder / "f0.png").write_bytes((folder / "f0.png").read_bytes() + b"x")
    with pytest.raises(ValueError, match="f0.png: SHA-256 differs"):
        gallery.gallery_frames(folder)


def test_a_changed_or_missing_shipped_frame_is_named(tmp_path, monkeypatch):
    copy = tmp_path / "notebooks" / "gallery"
    shutil.copytree(gallery.gallery_dir(), copy)
    monkeypatch.setattr(gallery, "gallery_dir", lambda: copy)
    first = gallery.read_frames_csv(copy / "frames.csv")[0]["file"]
    (copy / first).unlink()
    with pytest.raises(ValueError, match=f"{first}: missing"):
        gallery.gallery_frames()


def test_a_frames_csv_without_view_column_is_refused(tmp_path):
    folder = _folder_with_frames(tmp_path, n=1)
    (folder / "frames.csv").write_text("file,kind\nf0.png,wall\n")
    with pytest.raises(ValueError, match="missing column.*view"):
        gallery.gallery_frames(folder)


def test_a_frame_with_a_black_border_is_scored_inside_its_field_of_view_only(tmp_path):
    torch.manual_seed(0)
    model = DepthNet().eval()
    rng = np.random.default_rng(1)
    rgb = rng.integers(60, 200, (90, 120, 3), dtype=np.uint8)
    yy, xx = np.mgrid[0:90, 0:120]
    rgb[(xx - 60) ** 2 + (yy - 45) ** 2 > 44 ** 2] = 0  # a round window in a black border
    row = gallery.score_frame(model, rgb, 64)
    assert row["image"].shape[:2] == row["depth"].shape == row["mask"].shape == (96, 128)
    assert 0.2 < row["masked"] < 0.5
    assert np.isnan(row["depth"][0, 0]) and np.isnan(row["prior"][0, 0])  # the black corner is out
    assert np.isfinite(row["depth"][48, 64]) and np.isfinite(row["r"])
    assert not np.isnan(row["depth"][row["mask"]]).any()


def test_summary_counts_blobs_per_view():
    rows = [{"file": "a", "view": "close-up", "r": 0.2, "far_share": 0.7},
            {"file": "b", "view": "close-up", "r": 0.6, "far_share": 0.1},
            {"file": "c", "view": "lumen", "r": 0.8, "far_share": 0.0}]
    s = gallery.summary(rows)
    assert list(s) == ["lumen", "close-up"]
    assert s["close-up"] == {"frames": 2, "r": pytest.approx(0.4), "far_share": pytest.approx(0.4), "blobs": ["a"]}

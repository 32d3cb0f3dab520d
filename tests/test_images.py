"""One RGB reader for every command (``images.read_rgb``): a 16-bit image reads the same, scaled
to 8 bits and never clipped, in ``predict``, in ``evaluate``'s datasets, in the gallery and in
another simulator's sample frames."""

import json

import numpy as np
import pytest
from PIL import Image

from geodepth_lite.data import analytic, frames, images
from geodepth_lite.evaluation import evaluate, external, gallery

SIZE = 32


def _grey16(path, size: int = SIZE):
    """A 16-bit grey PNG: left half 26000 (101 in 8 bits), right half 65535 (255)."""
    g = np.full((size, size), 65535, np.uint16)
    g[:, : size // 2] = 26000
    Image.fromarray(g).save(path)
    return path


@pytest.fixture
def frame16(tmp_path):
    return _grey16(tmp_path / "g16.png")


def test_the_reader_scales_16_bits_to_8(frame16):
    rgb = images.read_rgb(frame16)
    assert rgb.shape == (SIZE, SIZE, 3) and rgb.dtype == np.uint8
    assert (rgb[:, : SIZE // 2] == 101).all() and (rgb[:, SIZE // 2:] == 255).all()


def _evaluate_reads(tmp_path, frame16) -> np.ndarray:
    """The frame as ``evaluate`` reads it: a synthetic dataset whose one test frame is ``frame16``."""
    root = analytic.write_dataset(tmp_path / "data", {"test": 1}, size=SIZE)
    rec = json.loads((root / "test" / "frames.jsonl").read_text().splitlines()[0])
    (root / rec["rgb"]).write_bytes(frame16.read_bytes())
    item = evaluate.open_eval_dataset(str(root), split="test")[0]
    return np.rint(item["image"].permute(1, 2, 0).numpy() * 255.0).astype(np.uint8)


def _gallery_reads(monkeypatch, frame16) -> np.ndarray:
    """The frame as the gallery reads it (``score_gallery``), caught where it is scored."""
    seen = []
    monkeypatch.setattr(gallery, "score_frame", lambda model, rgb, size, flips: seen.append(rgb) or {})
    gallery.score_gallery(None, [{"path": frame16, "view": "wall", "description": ""}], SIZE)
    return seen[0]


def _external_reads(monkeypatch, frame16) -> np.ndarray:
    """The frame as another simulator's sample reads it (``sample_dataset``), its copy taken as checked."""
    m = {"name": "one", "dataset": "plain", "files": [{"rgb": frame16.name, "depth": "depth.png"}]}
    monkeypatch.setattr(external, "load_sample_manifest", lambda name: m)
    monkeypatch.setattr(external, "check_copy", lambda name, root: [])
    monkeypatch.setitem(external.DECODERS, "plain", lambda path: (np.ones((SIZE, SIZE)), np.ones((SIZE, SIZE), bool)))
    item = external.sample_dataset("one", frame16.parent)[0]
    return np.rint(item["image"].permute(1, 2, 0).numpy() * 255.0).astype(np.uint8)


def test_a_16_bit_png_reads_the_same_in_predict_evaluate_the_gallery_and_external(tmp_path, monkeypatch, frame16):
    want = images.read_rgb(frame16)
    assert (want[:, : SIZE // 2] == 101).all()  # scaled, not clipped to 255
    reads = {"predict": frames.read_frame(frame16), "evaluate": _evaluate_reads(tmp_path, frame16),
             "gallery": _gallery_reads(monkeypatch, frame16), "external": _external_reads(monkeypatch, frame16)}
    for command, rgb in reads.items():
        assert rgb.shape == want.shape and (rgb == want).all(), (command, np.unique(rgb))


def test_an_8_bit_frame_reads_as_pil_decodes_it(tmp_path):
    """8-bit frames (the gallery's, the datasets') read exactly as PIL's RGB conversion gives them."""
    rgb = np.random.default_rng(0).integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "c.png")
    Image.fromarray(rgb[..., 0]).save(tmp_path / "l.png")
    assert (images.read_rgb(tmp_path / "c.png") == rgb).all()
    assert (images.read_rgb(tmp_path / "l.png") == np.repeat(rgb[..., :1], 3, axis=-1)).all()

"""Files from elsewhere are data, bounded before they are read: one test per fault a review found.

A first-format checkpoint whose numpy arrays hold objects, raw bytes or a shape its data cannot
fill (the interpreter crashed, or 500 MB were allocated from a 1.4 KB file); a conversion that
rewrote its input; dataset files naming paths outside their folder (frames.jsonl, checksums.sha256
naming /dev/zero); manifests claiming 10^12 frames, a ring step of 1e-9 or a NaN field of view;
checkpoint configs asking for a 50000-pixel input; a 12000 x 12000 PNG; a .npy header claiming
37 GiB; malformed frames.jsonl records; deeply nested JSON. Each is refused in one line naming the
file (exit 2), quickly, leaving nothing behind. Every crafted file is built here.
"""

import contextlib
import io
import json
import shutil
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import one_line_error, save_untrained_checkpoint
from numpy._core.multiarray import _reconstruct

from geodepth_lite import cli, utils
from geodepth_lite.data import bounds, datasets, fov, frames, images, integrity
from geodepth_lite.data import manifest as mf
from geodepth_lite.data.datasets import base
from geodepth_lite.training import checkpoint

ROOT = Path(__file__).resolve().parent.parent


def _cli(*argv, timeout: float = 120) -> subprocess.CompletedProcess:
    """``python -m geodepth_lite ARGV`` in a child interpreter: a crash shows as its exit status."""
    env = {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, "-m", "geodepth_lite", *map(str, argv)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=ROOT)


def _one_line(proc: subprocess.CompletedProcess, *needles) -> str:
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    for needle in needles:
        assert str(needle) in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture
def smoke_copy(smoke_root, tmp_path):
    """A private copy of the smoke dataset, safe to damage."""
    return Path(shutil.copytree(smoke_root, tmp_path / "smoke"))


def _records(root: Path, split: str) -> list[dict]:
    return [json.loads(ln) for ln in (root / split / "frames.jsonl").read_text().splitlines() if ln.strip()]


def _write_records(root: Path, split: str, lines: list[str], *, re_sum: bool = True) -> Path:
    """Replace a split's frames.jsonl, and (as a careful attacker would) its checksum line too."""
    path = root / split / "frames.jsonl"
    path.write_text("".join(ln + "\n" for ln in lines))
    if re_sum:
        sums = root / "checksums.sha256"
        rel = f"{split}/frames.jsonl"
        text = "".join(f"{integrity.file_sha256(path)}  {rel}\n" if ln.endswith(f"  {rel}") else ln + "\n"
                       for ln in sums.read_text().splitlines())
        sums.write_text(text)
    return path


def _evaluate_argv(ckpt: Path, root: Path, out: Path, *extra) -> list[str]:
    return ["evaluate", "--checkpoint", str(ckpt), "--dataset", str(root), "--split", "test", "--out", str(out),
            "--no-progress", *extra]


# =========================================================================== 1. first-format checkpoints


class _Array:
    """Pickles as numpy pickles an array (``_reconstruct`` + ``ndarray`` + ``dtype``), with whatever
    dtype, shape and raw bytes it is given: what a hostile file can hold using only those globals."""

    def __init__(self, dtype, shape, raw: bytes):
        self.dtype, self.shape, self.raw = dtype, shape, raw

    def __reduce__(self):
        return _reconstruct, (np.ndarray, (0,), b"b"), (1, self.shape, self.dtype, False, self.raw)


class _Dtype:
    """Pickles as ``numpy.dtype(name, False, True)`` whatever ``name`` is."""

    def __init__(self, name: str):
        self.name = name

    def __reduce__(self):
        return np.dtype, (self.name, False, True)


HOSTILE_ARRAYS = {
    "object dtype": (_Array(np.dtype(object), (4,), b"\x41" * 32), "dtype 'O8'"),
    "void dtype": (_Array(np.dtype("V8"), (4,), b"\x41" * 32), "dtype 'V8'"),
    "structured dtype": (_Array(np.dtype([("a", "<f4"), ("b", "<i4")]), (1,), b"\0" * 8), "dtype 'V8'"),
    "bad dtype": (_Array(_Dtype("zz9"), (1,), b"\0" * 8), "dtype 'zz9'"),
    "500 MB from 8 bytes": (_Array(np.dtype(np.uint8), (500_000_000,), b"\0" * 8), "whose data holds 8 bytes"),
    "impossible shape": (_Array(np.dtype(np.uint8), (-1,), b"\0" * 8), "impossible shape"),
}


def _first_format_file(path: Path, keys) -> Path:
    """A first-format checkpoint (numpy RNG state as a tuple holding an array) with ``keys`` as the array
    (a one-tensor model: the reader checks the file's format, not the network)."""
    torch.save({"model": {"w": torch.arange(4.0)}, "cfg": {"image_size": 32}, "epoch": 1,
                "rng": {"numpy": ("MT19937", keys, 3, 0, 0.0)}}, path)
    return path


def test_an_object_array_checkpoint_is_refused_in_one_line_and_the_interpreter_lives(tmp_path, capsys):
    folder = tmp_path / "run"
    folder.mkdir()
    path = _first_format_file(folder / "checkpoint.pt", HOSTILE_ARRAYS["object dtype"][0])
    # only the globals the first format was allowed: the old converter handed it to numpy, which crashed
    assert set(torch.serialization.get_unsafe_globals_in_checkpoint(path)) <= set(checkpoint.NUMPY_ARRAY_GLOBALS)
    before = path.read_bytes()
    proc = _cli("convert-checkpoint", path)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)  # not -11 / 139 (a crash), not 0
    _one_line(proc, str(path), "refused", "dtype 'O8'")
    assert cli.main(["convert-checkpoint", str(folder)]) == 2  # a folder holding it, in this interpreter
    one_line_error(capsys, str(path), "refused", "dtype 'O8'")
    assert path.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == ["checkpoint.pt"]


@pytest.mark.parametrize("kind", [k for k in HOSTILE_ARRAYS if k != "object dtype"])
def test_a_hostile_first_format_checkpoint_is_refused_in_one_line(tmp_path, capsys, kind):
    array, reason = HOSTILE_ARRAYS[kind]
    path = _first_format_file(tmp_path / "checkpoint.pt", array)
    assert set(torch.serialization.get_unsafe_globals_in_checkpoint(path)) <= set(checkpoint.NUMPY_ARRAY_GLOBALS)
    before = path.read_bytes()
    assert cli.main(["convert-checkpoint", str(path)]) == 2
    one_line_error(capsys, str(path), "refused", reason)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


def test_the_reader_bounds_its_own_memory(tmp_path, monkeypatch):
    """The child reading a first-format file runs under an address-space limit: a request past it
    ends in one line, not in the caller running out of memory."""
    path = _first_format_file(tmp_path / "checkpoint.pt", np.arange(624, dtype=np.uint32))
    checkpoint.read_old_checkpoint(path)  # within the limit: read
    monkeypatch.setattr(checkpoint, "OLD_READ_MEMORY_BYTES", 0)  # no room at all above the parent's size
    monkeypatch.setattr(checkpoint, "_read_old_in_child", lambda p, limits: bytes(2**31))
    with pytest.raises(ValueError, match="needs more than 0 GiB of memory"):
        checkpoint.read_old_checkpoint(path)


def test_predict_points_to_the_conversion_only_for_a_file_it_would_accept(smoke_root, tmp_path, capsys):
    bad = _first_format_file(tmp_path / "bad.pt", HOSTILE_ARRAYS["object dtype"][0])
    good = _first_format_file(tmp_path / "good.pt", np.arange(624, dtype=np.uint32))
    for path, needles in ((bad, ("refused", "dtype 'O8'")), (good, ("first checkpoint format", "convert-checkpoint"))):
        argv = ["predict", "--checkpoint", str(path), "--input", str(smoke_root / "test" / "rgb"),
                "--out", str(tmp_path / "pred"), "--no-progress"]
        assert cli.main(argv) == 2
        line = one_line_error(capsys, str(path), *needles)
        assert path is good or "convert-checkpoint" not in line
        assert not (tmp_path / "pred").exists()


def test_the_conversion_never_rewrites_its_input(tmp_path, capsys):
    path = _first_format_file(tmp_path / "checkpoint.pt", np.arange(624, dtype=np.uint32))
    original = path.read_bytes()
    assert cli.main(["convert-checkpoint", str(path), "--out", str(path)]) == 2  # the output is the input
    one_line_error(capsys, str(path), "never rewrites its input")
    taken = tmp_path / "taken.pt"
    taken.write_bytes(b"someone else's file")
    assert cli.main(["convert-checkpoint", str(path), "--out", str(taken)]) == 2  # an existing file
    one_line_error(capsys, str(taken), "exists already")
    assert taken.read_bytes() == b"someone else's file" and path.read_bytes() == original

    out = tmp_path / "new.pt"
    assert cli.main(["convert-checkpoint", str(path), "--out", str(out)]) == 0
    assert path.read_bytes() == original
    assert torch.equal(checkpoint.read_checkpoint(out)["rng"]["numpy"]["keys"], torch.arange(624))

    assert cli.main(["convert-checkpoint", str(path)]) == 0  # no --out: the original kept beside it
    kept = tmp_path / f"checkpoint.pt{checkpoint.OLD_SUFFIX}"
    assert kept.read_bytes() == original
    assert checkpoint.read_checkpoint(path)["format"] == checkpoint.FORMAT
    capsys.readouterr()
    kept.write_bytes(original[:-1] + bytes([original[-1] ^ 1]))  # another file in the kept copy's place
    path.write_bytes(original)  # again: refused, naming the file in the way, nothing replaced
    assert cli.main(["convert-checkpoint", str(path)]) == 2
    one_line_error(capsys, str(kept), "exists already", "differs")
    assert path.read_bytes() == original and kept.read_bytes() != original


def test_a_junk_checkpoint_says_what_is_wrong(tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x80\x02K\x65.")  # a pickle of the number 101, not a torch file
    assert cli.main(["convert-checkpoint", str(junk)]) == 2
    line = one_line_error(capsys, str(junk), "not a checkpoint written by torch.save")
    assert not line.endswith("101"), line


@pytest.mark.parametrize("size, needles", [(50000, ("'image_size'", "positive multiple of 32", "50000")),
                                           (50016, ("'image_size'", "2048 pixels a side", "GiB")),
                                           (-64, ("'image_size'", "positive multiple of 32", "-64"))])
def test_a_checkpoint_config_asking_too_much_is_refused_naming_the_field(smoke_root, tmp_path, capsys, size, needles):
    ckpt = save_untrained_checkpoint(tmp_path / "checkpoint.pt", cfg={"image_size": size})
    argv = ["predict", "--checkpoint", str(ckpt), "--input", str(smoke_root / "test" / "rgb"),
            "--out", str(tmp_path / "pred"), "--no-progress"]
    assert cli.main(argv) == 2
    one_line_error(capsys, str(ckpt), *needles)
    assert not (tmp_path / "pred").exists()
    checkpoint.read_checkpoint(save_untrained_checkpoint(tmp_path / "ok.pt", cfg={"image_size": 2048}))  # the limit


# =========================================================================== 2. paths a dataset names


@pytest.mark.parametrize("how", ["absolute", "dot-dot", "symlink"])
def test_a_frame_path_outside_the_dataset_is_refused(smoke_copy, untrained_checkpoint, tmp_path, capsys, how):
    recs = _records(smoke_copy, "test")
    outside = tmp_path / "outside.png"
    shutil.copy(smoke_copy / recs[0]["rgb"], outside)
    if how == "absolute":
        recs[0]["rgb"] = str(outside)
    elif how == "dot-dot":
        recs[0]["rgb"] = "../outside.png"
    else:
        (smoke_copy / "test" / "rgb" / "link.png").symlink_to(outside)
        recs[0]["rgb"] = "test/rgb/link.png"
    frames = _write_records(smoke_copy, "test", [json.dumps(r) for r in recs])
    problems = integrity.verify(smoke_copy)  # the checksums agree: verify reads the paths as train does
    assert len(problems) == 1 and problems[0].startswith("unreadable: test/frames.jsonl (") and "line 1" in problems[0]
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_copy, tmp_path / "eval")) == 2
    one_line_error(capsys, str(frames), "line 1", "outside the dataset folder")
    assert not (tmp_path / "eval").exists()


def test_a_frame_file_not_in_the_checksums_is_refused(smoke_copy, capsys):
    recs = _records(smoke_copy, "test")
    extra = smoke_copy / "test" / "rgb" / "extra.png"
    shutil.copy(smoke_copy / recs[0]["rgb"], extra)
    recs[0]["rgb"] = "test/rgb/extra.png"
    frames = _write_records(smoke_copy, "test", [json.dumps(r) for r in recs])
    with pytest.raises(utils.FileProblem, match="not listed in") as info:
        datasets.SyntheticDepthDataset(smoke_copy, "test")
    assert info.value.path == frames


def test_checksums_lines_outside_the_dataset_are_never_read(smoke_copy, tmp_path):
    (tmp_path / "outside.txt").write_text("not part of the dataset\n")
    (smoke_copy / "test" / "zero-link").symlink_to("/dev/zero")
    entries = ["/dev/zero", "../outside.txt", "test/zero-link"]
    with open(smoke_copy / "checksums.sha256", "a") as f:
        f.writelines(f"{'0' * 64}  {entry}\n" for entry in entries)
    proc = _cli("verify", smoke_copy, timeout=60)  # reading /dev/zero would never end
    assert proc.returncode == 1, proc.stderr
    for entry in entries:
        assert f"outside: {entry}" in proc.stdout, proc.stdout
    with pytest.raises(ValueError, match="outside: /dev/zero"):
        integrity.check_dataset(smoke_copy)  # what train and evaluate run first


@contextlib.contextmanager
def _within(seconds: float):
    """Fail with TimeoutError if the block runs longer than ``seconds`` (a hang becomes a failure)."""
    def stop(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def test_a_manifest_claiming_a_trillion_frames_is_refused_quickly(tmp_path, capsys):
    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "manifest.json").write_text(json.dumps({"splits": {"train": 10**12}}))
    with _within(20):  # counting to 10^12 would never end
        assert cli.main(["verify", str(folder)]) == 1
    assert "over the limit of 10000000" in capsys.readouterr().out


# =========================================================================== 2. manifests


def _synth(tmp_path, text: str) -> tuple[Path, Path]:
    path = tmp_path / "hostile.json"
    path.write_text(text)
    return path, tmp_path / "out"


@pytest.mark.parametrize("text, needles", [
    ('{"resolution": {"ring_step": 1e-9}}', ("'resolution.ring_step'", "over the limit of 4000000 points")),
    ('{"camera": {"fov_x_deg": NaN}}', ("'camera.fov_x_deg'", "finite")),
    ('{"camera": {"principal_point": [NaN, 10]}}', ("'camera.principal_point[0]'", "finite")),
    ('{"camera": {"far": 1' + "0" * 400 + '}}', ("'camera.far'", "an integer of 401 digits")),
    ('{"camera": {"principal_point": [1' + "0" * 400 + ', 10]}}', ("'camera.principal_point[0]'", "401 digits")),
    ('{"camera": {"width": 8192, "height": 8192}}', ("'camera.width'", "over the limit of 50000000 pixels")),
    ('{"description": ' + "[" * 100_000 + "]" * 100_000 + "}", ("nested too deep",)),
])
def test_a_manifest_beyond_what_synth_can_serve_is_refused_naming_the_field(tmp_path, capsys, text, needles):
    path, out = _synth(tmp_path, text)
    assert cli.main(["synth", "--manifest", str(path), "--out", str(out)]) == 2
    one_line_error(capsys, str(path), *needles)
    assert not out.exists()


def test_the_shipped_manifests_stay_within_the_bounds():
    for path in sorted(mf.manifests_dir().glob("*.json")):
        m = mf.load_manifest(path)
        assert max(mf.mesh_vertices(m, o) for o in m["organs"]) < mf.MAX_MESH_VERTICES / 10, path


# =========================================================================== 2. images


def _png_of_side(path: Path, side: int) -> Path:
    """A black greyscale PNG of side x side pixels, written row by row: 12000 x 12000 is ~140 KB."""
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    z = zlib.compressobj(1)
    row = b"\0" * (side + 1)
    body = b"".join(z.compress(row) for _ in range(side)) + z.flush()
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))
    return path


@pytest.fixture(scope="module")
def bomb(tmp_path_factory) -> Path:
    return _png_of_side(tmp_path_factory.mktemp("bomb") / "bomb12000.png", 12000)


def test_the_bomb_is_a_real_image_of_that_size(bomb):
    """What the tests below refuse is a valid 144-megapixel PNG, small on disk."""
    assert bomb.stat().st_size < 1_000_000
    assert bounds.image_header_size(bomb) == (12000, 12000)
    from PIL import Image
    with Image.open(_png_of_side(bomb.parent / "small.png", 40)) as im:  # the same writer decodes
        assert im.size == (40, 40) and not np.asarray(im).any()


def test_an_image_over_the_pixel_limit_is_refused_from_its_header(smoke_root, untrained_checkpoint, bomb, tmp_path,
                                                                   capsys):
    for read in (images.read_rgb, frames.read_frame, fov.read_mask, base.read_png_unit, base.read_png_raw):
        with pytest.raises(utils.FileProblem, match="over the limit of 50000000 pixels") as info:
            read(bomb)
        assert info.value.path == bomb
    folder = tmp_path / "frames"
    folder.mkdir()
    shutil.copy(bomb, folder)
    shutil.copy(next((smoke_root / "test" / "rgb").glob("*.png")), folder / "fine.png")
    argv = ["predict", "--checkpoint", str(untrained_checkpoint), "--input", str(folder), "--out", str(tmp_path / "p"),
            "--no-progress", "--ply", "none"]
    assert cli.main(argv) == 2  # the bomb named, the other frame written
    one_line_error(capsys, str(folder / bomb.name), "over the limit")
    assert (tmp_path / "p" / "fine_depth.npy").is_file()
    mask_argv = [*argv[:6], str(tmp_path / "m"), "--no-progress", "--mask", str(bomb)]
    assert cli.main(mask_argv) == 2
    one_line_error(capsys, f"--mask {bomb}", "over the limit")
    assert not (tmp_path / "m").exists()
    assert cli.main([*argv[:6], str(tmp_path / "q"), "--no-progress", "--max-pixels", "100"]) == 2  # the flag
    capsys.readouterr()


def test_a_refused_first_image_does_not_size_the_mask_or_the_run(untrained_checkpoint, bomb, tmp_path, capsys):
    """The frames' size that a ``--mask`` image is held to is that of the first image predict will read:
    a bomb, or a frame too small, sorted first is named on its own line and the others are written."""
    from PIL import Image

    rgb = np.random.default_rng(0).integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
    mask = tmp_path / "mask.png"
    Image.fromarray(np.full((48, 64), 255, dtype=np.uint8)).save(mask)
    for first, made_by in (("a_bomb.png", lambda p: shutil.copy(bomb, p)),
                           ("a_tiny.png", lambda p: Image.fromarray(rgb[:1, :1]).save(p))):
        folder = tmp_path / first.removesuffix(".png")
        folder.mkdir()
        made_by(folder / first)
        Image.fromarray(rgb).save(folder / "b_fine.png")
        out = folder.with_name(folder.name + "_out")
        assert cli.main(["predict", "--checkpoint", str(untrained_checkpoint), "--input", str(folder),
                         "--out", str(out), "--no-progress", "--ply", "none", "--mask", str(mask)]) == 2
        one_line_error(capsys, str(folder / first))
        assert frames.first_frame_size(sorted(folder.iterdir()), "images") == (64, 48)
        assert (out / "b_fine_depth.npy").is_file()


def test_a_dataset_frame_over_the_pixel_limit_is_refused(smoke_copy, bomb):
    rec = _records(smoke_copy, "train")[0]
    shutil.copy(bomb, smoke_copy / rec["rgb"])
    with pytest.raises(utils.FileProblem, match="refused before decoding") as info:
        datasets.SyntheticDepthDataset(smoke_copy, "train")[0]
    assert info.value.path == smoke_copy / rec["rgb"]


# =========================================================================== 3. dataset files


def test_a_npy_header_claiming_37_gib_is_refused_before_reading(smoke_copy):
    rec = _records(smoke_copy, "train")[0]
    path = smoke_copy / rec["depth"]
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False, "shape": (100_000, 100_000)})
    path.write_bytes(buf.getvalue() + b"\0" * 64)
    with pytest.raises(utils.FileProblem, match="claims 40000000000 bytes") as info:
        datasets.SyntheticDepthDataset(smoke_copy, "train")[0]
    assert info.value.path == path


def test_a_depth_map_of_the_wrong_shape_is_named(smoke_copy, untrained_checkpoint, tmp_path, capsys):
    rec = _records(smoke_copy, "test")[0]
    np.save(smoke_copy / rec["depth"], np.ones((10, 7), dtype=np.float32))
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_copy, tmp_path / "eval", "--no-verify")) == 2
    one_line_error(capsys, str(smoke_copy / rec["depth"]), "shape (10, 7)")


@pytest.mark.parametrize("change, needles", [
    (lambda r: r.pop("rgb"), ("line 1", "lacks 'rgb'")),
    (lambda r: r.update(K="zzz"), ("line 1", "'K' must be a pinhole camera's 3x3 matrix")),
    (lambda r: r.update(K=[[10**400, 0, 1], [0, 1, 1], [0, 0, 1]]), ("line 1", "'K' must be a pinhole")),
    (lambda r: r.update(K=[[0, 0, 0], [0, 0, 0], [0, 0, 0]]), ("line 1", "focal lengths positive")),
    (lambda r: r.update(K=[[1e300, 0, 1], [0, 1, 1], [0, 0, 1]]), ("line 1", "'K' must be a pinhole")),
    (lambda r: r.update(index="3"), ("line 1", "'index' must be an integer")),
    (lambda r: r.update(index=2**64), ("line 1", "'index' must be an integer from 0 to 2^63 - 1")),
    (None, ("line 1", "not valid JSON")),
    ("deep", ("line 1", "nested too deep")),
])
def test_a_bad_frames_record_is_named_with_its_file_and_line(smoke_copy, untrained_checkpoint, tmp_path, capsys,
                                                            change, needles):
    recs = _records(smoke_copy, "test")
    if change is None:
        first = '{"rgb": "test/rgb/000000.png",'
    elif change == "deep":
        first = "[" * 100_000 + "]" * 100_000
    else:
        change(recs[0])
        first = json.dumps(recs[0])
    frames = _write_records(smoke_copy, "test", [first, *map(json.dumps, recs[1:])])
    assert cli.main(_evaluate_argv(untrained_checkpoint, smoke_copy, tmp_path / "eval")) == 2
    one_line_error(capsys, str(frames), *needles)
    assert not (tmp_path / "eval").exists()


def test_the_pickled_depth_refusal_still_names_objects(tmp_path):
    """The header check keeps the message a pickled depth file had (never loaded)."""
    path = tmp_path / "d.npy"
    np.save(path, np.array([1.0, None], dtype=object), allow_pickle=True)
    with pytest.raises(utils.FileProblem, match="pickled Python objects, never loaded"):
        bounds.read_npy(path)

"""``predict`` against a hostile user: 16-bit images, frames too small, bad video, full disk,
stale temporary files, --out inside --input, symbolic link loops, refused runs, bad --mask and --intrinsics files.

Every failure is one line ``error: <message naming the file>`` on stderr; a folder run
processes the other files and exits with status 2 if any failed.
"""

import errno
import os
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
from conftest import save_nan_checkpoint
from PIL import Image

from geodepth_lite import cli, utils
from geodepth_lite.data import frames
from geodepth_lite.training import checkpoint
from geodepth_lite.views import depth_files, recon


@pytest.fixture(scope="module")
def ckpt(untrained_checkpoint):
    return untrained_checkpoint


def _run(ckpt, src, out, *extra):
    """``python -m geodepth_lite predict`` in-process; its exit status."""
    return cli.main(["predict", "--checkpoint", str(ckpt), "--input", str(src), "--out", str(out),
                     "--no-progress", *extra])


def _errors(capsys) -> tuple[list[str], str]:
    """(the ``error:`` lines of stderr, stdout); stderr holds nothing else (no traceback, no ffmpeg log)."""
    captured = capsys.readouterr()
    err = [line for line in captured.err.strip().splitlines() if line.strip()]
    errors = [line for line in err if line.startswith("error: ")]
    assert errors == err, err
    return errors, captured.out


def _frame(h, w, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def _folder(root: Path, images: dict) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for name, array in images.items():
        Image.fromarray(array).save(root / name)
    return root


def _outputs(out: Path, name: str) -> list[str]:
    return sorted(p.name for p in out.glob(f"{name}*"))


def _last_line(stdout: str) -> str:
    """The run's summary: stdout's last line (one line per written frame comes before it)."""
    return stdout.strip().splitlines()[-1]


# --------------------------------------------------------------------------- 1. 16-bit images


def _png16_rgb(path: Path, rgb16: np.ndarray) -> Path:
    """A 16-bit RGB PNG written by hand (PIL cannot write one)."""
    h, w, _ = rgb16.shape
    raw = b"".join(b"\x00" + rgb16[y].astype(">u2").tobytes() for y in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)  # bit depth 16, colour type 2 (RGB)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw))
                     + chunk(b"IEND", b""))
    return path


def _grey16(h=12, w=20) -> np.ndarray:
    """Left half 26000 (26000 / 257 = 101.2 -> 101), right half 65535 (-> 255)."""
    a = np.full((h, w), 26000, np.uint16)
    a[:, w // 2:] = 65535
    return a


def _write_16bit(kind: str, folder: Path) -> Path:
    import tifffile

    g = _grey16()
    if kind == "grey PNG (I;16)":
        Image.fromarray(g).save(folder / "g.png")
        return folder / "g.png"
    if kind == "grey TIFF (I;16)":
        tifffile.imwrite(folder / "g.tif", g)
        return folder / "g.tif"
    if kind == "grey in 32 bits (I)":
        tifffile.imwrite(folder / "i.tif", g.astype(np.int32))
        return folder / "i.tif"
    if kind == "RGB PNG 16-bit":
        return _png16_rgb(folder / "c.png", np.repeat(g[..., None], 3, axis=-1))
    if kind == "RGB TIFF 16-bit":
        tifffile.imwrite(folder / "c.tif", np.repeat(g[..., None], 3, axis=-1), photometric="rgb")
        return folder / "c.tif"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["grey PNG (I;16)", "grey TIFF (I;16)", "grey in 32 bits (I)",
                                  "RGB PNG 16-bit", "RGB TIFF 16-bit"])
def test_16_bit_images_are_scaled_to_8_bits_not_clipped(tmp_path, kind):
    rgb = frames.read_frame(_write_16bit(kind, tmp_path))
    assert rgb.shape == (12, 20, 3) and rgb.dtype == np.uint8
    assert (rgb[:, :10] == 101).all(), np.unique(rgb[:, :10])  # PIL's convert("RGB") gave 255
    assert (rgb[:, 10:] == 255).all()


def test_float_images_in_0_1_are_scaled(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "f.tif", np.full((4, 6), 0.4, np.float32))
    assert (frames.read_frame(tmp_path / "f.tif") == 102).all()  # convert("RGB") gave 0


def test_the_cli_colours_a_16_bit_png_by_its_8_bit_values(tmp_path, ckpt, capsys):
    Image.fromarray(np.full((12, 20), 26000, np.uint16)).save(tmp_path / "g16.png")
    out = tmp_path / "out"
    assert _run(ckpt, tmp_path / "g16.png", out) == 0
    assert _errors(capsys)[0] == []
    colours = np.asarray(recon.load_ply(out / "g16.ply").point_data["RGB"])
    assert colours.shape == (240, 3) and (colours == 101).all(), np.unique(colours)


# --------------------------------------------------------------------------- 2, 3. per-file failures


def test_too_small_images_are_refused_by_name_and_the_folder_still_runs(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a_flat.png": _frame(1, 30), "b_thin.png": _frame(30, 1),
                                    "c_ok.png": _frame(20, 24), "d_tiny.png": _frame(2, 2)})
    out = tmp_path / "out"
    assert _run(ckpt, src, out, "--batch-size", "3") == 2
    errors, stdout = _errors(capsys)
    assert errors == [f"error: cannot use image {src / 'a_flat.png'}: 30 x 1 pixels is too small "
                      f"(predict needs at least 2 x 2)",
                      f"error: cannot use image {src / 'b_thin.png'}: 1 x 30 pixels is too small "
                      f"(predict needs at least 2 x 2)"]
    assert stdout.strip().splitlines()[-1] == f"2 frame(s) written to {out}; 2 failed (the error lines above)"
    assert _outputs(out, "a_") == [] and _outputs(out, "b_") == []  # no stray _depth.npy
    assert _outputs(out, "c_") == ["c_ok.ply", "c_ok_depth.npy", "c_ok_depth.png", "c_ok_panel.png"]
    assert np.load(out / "d_tiny_depth.npy").shape == (2, 2)  # the minimum size works


def test_all_frames_written_exits_0_with_no_error_line(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24), "b.png": _frame(16, 16)})
    assert _run(ckpt, src, tmp_path / "out", "--ply", "none") == 0
    errors, stdout = _errors(capsys)
    assert errors == [] and _last_line(stdout) == f"2 frame(s) written to {tmp_path / 'out'}"


def test_a_frame_whose_outputs_cannot_be_made_writes_none_and_keeps_an_earlier_file(tmp_path, ckpt, capsys,
                                                                                    monkeypatch):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24, 0), "b.png": _frame(20, 24, 1), "c.png": _frame(8, 8)})
    out = tmp_path / "out"
    out.mkdir()
    (out / "b.ply").write_text("an earlier run's b.ply")
    real_ply_bytes, calls = recon.ply_bytes, []

    def ply_bytes(poly, binary=True):  # frames go in name order: the second is b's
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("mesh went wrong")
        return real_ply_bytes(poly, binary)

    monkeypatch.setattr(recon, "ply_bytes", ply_bytes)
    assert _run(ckpt, src, out) == 2
    errors, stdout = _errors(capsys)
    assert errors == ["error: cannot write the outputs of b: ValueError: mesh went wrong"]
    assert _outputs(out, "b") == ["b.ply"] and (out / "b.ply").read_text() == "an earlier run's b.ply"  # untouched
    assert _outputs(out, "a") == ["a.ply", "a_depth.npy", "a_depth.png", "a_panel.png"]
    assert _outputs(out, "c") == ["c.ply", "c_depth.npy", "c_depth.png", "c_panel.png"]  # the frame after it ran
    assert "2 frame(s) written" in stdout and not list(out.glob(utils.TEMP_GLOB))


def test_a_frame_whose_file_cannot_be_renamed_leaves_none_of_its_files(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24, 0)})
    out = tmp_path / "out"
    (out / "a_panel.png").mkdir(parents=True)  # a folder in the way of the third file's rename
    (out / "a.ply").write_text("an earlier run's a.ply: it would no longer match a's depth")
    assert _run(ckpt, src, out) == 2
    errors, _ = _errors(capsys)
    assert len(errors) == 1 and errors[0].startswith(f"error: cannot write {out / 'a_panel.png'}: "), errors
    assert _outputs(out, "a") == ["a_panel.png"] and (out / "a_panel.png").is_dir()  # the two renamed: removed
    assert not list(out.glob(utils.TEMP_GLOB))


def test_a_file_that_cannot_be_written_is_named_and_the_others_go_on(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24, 0), "b.png": _frame(20, 24, 1)})
    out = tmp_path / "out"
    (out / "a_depth.png").mkdir(parents=True)  # a folder in the way of one output
    assert _run(ckpt, src, out, "--ply", "none") == 2
    errors, _ = _errors(capsys)
    assert len(errors) == 1 and errors[0].startswith(f"error: cannot write {out / 'a_depth.png'}: "), errors
    assert _outputs(out, "a") == ["a_depth.png"] and (out / "a_depth.png").is_dir()  # a_depth.npy removed
    assert _outputs(out, "b") == ["b_depth.npy", "b_depth.png", "b_panel.png"]


# --------------------------------------------------------------------------- 4. video


def test_a_garbage_video_is_one_line_and_makes_no_folder(tmp_path, ckpt, capsys):
    video = tmp_path / "x.mp4"
    video.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    out = tmp_path / "out"
    assert _run(ckpt, video, out) == 2
    errors, _ = _errors(capsys)  # the only stderr line: no ffmpeg banner, no "frame -1"
    assert errors == [f"error: cannot read video {video}: not a readable video "
                      f"(invalid data found when processing input)"]
    assert not out.exists()


def test_a_video_without_a_video_stream_says_so(tmp_path, ckpt, capsys):
    import imageio_ffmpeg

    audio = tmp_path / "sound.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-f", "lavfi", "-i", "sine", "-t", "0.2",
                    str(audio)], check=True, capture_output=True)
    assert _run(ckpt, audio, tmp_path / "out") == 2
    assert _errors(capsys)[0] == [f"error: cannot read video {audio}: not a readable video (no video stream in it)"]


def test_a_video_that_breaks_midway_names_the_last_good_frame(tmp_path, ckpt, capsys, monkeypatch):
    video = tmp_path / "clip.mp4"
    iio.imwrite(video, np.stack([_frame(48, 64, k) for k in range(5)]), fps=10)
    real_read_video = frames.read_video

    def breaks_after_3(path):
        for k, frame in enumerate(real_read_video(path)):
            if k == 3:  # what imageio_ffmpeg raises when ffmpeg dies mid-stream
                raise RuntimeError("Could not read frame 4:\nEnd of file reached before full frame could be read."
                                   "\n=== stderr ===\nffmpeg version n9\n  built with gcc\n[in#0 @ 0x5] decode error")
            yield frame

    monkeypatch.setattr(frames, "read_video", breaks_after_3)
    out = tmp_path / "out"
    assert _run(ckpt, video, out, "--ply", "none", "--batch-size", "2") == 2
    errors, stdout = _errors(capsys)
    assert errors == [f"error: cannot read video {video} after frame 2: "
                      f"end of file reached before full frame could be read"]
    assert sorted(p.name for p in out.glob("*.npy")) == [f"clip_{k:06d}_depth.npy" for k in range(3)]
    assert _last_line(stdout) == f"3 frame(s) written to {out}; 1 failed (the error lines above)"


# --------------------------------------------------------------------------- 5. full disk


def test_a_full_disk_names_the_file_and_stops(tmp_path, ckpt, capsys, monkeypatch):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24, 0), "b.png": _frame(20, 24, 1)})
    out = tmp_path / "out"

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(utils.os, "fsync", full)  # every atomic write fails at its data flush
    assert _run(ckpt, src, out) == 2
    errors, stdout = _errors(capsys)
    assert errors == [f"error: cannot write {out / 'a_depth.npy'}: no space left on device"]
    assert "no frame written" in stdout and "not processed" in stdout  # b was not tried
    assert not out.exists()  # nothing written: the folder this run made is gone


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE and SIGXFSZ as on Linux")
def test_a_short_write_gives_the_systems_reason(tmp_path, ckpt, capsys):
    """numpy writing a file itself reported a write the system cut short as "4096 requested and
    3040 written"; a file size limit cuts writes short the way a nearly full disk does."""
    import resource
    import signal

    src = _folder(tmp_path / "in", {"a.png": _frame(40, 56)})  # a_depth.npy: 9088 bytes
    out = tmp_path / "out"
    limits = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, limits[1]))
    try:
        code = _run(ckpt, src, out, "--ply", "none")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, old_handler)
    assert code == 2
    assert _errors(capsys)[0] == [f"error: cannot write {out / 'a_depth.npy'}: file too large"]
    assert not out.exists()


def test_no_room_for_one_frame_is_refused_before_the_model_is_loaded(tmp_path, ckpt, capsys, monkeypatch):
    src = _folder(tmp_path / "in", {"a.png": _frame(200, 300)})
    out = tmp_path / "new" / "out"
    monkeypatch.setattr(shutil, "disk_usage", lambda p: SimpleNamespace(total=10**9, used=10**9 - 2**20, free=2**20))
    monkeypatch.setattr(checkpoint, "load_model", lambda *a, **k: pytest.fail("loaded the model"))
    assert _run(ckpt, src, out) == 2
    errors, _ = _errors(capsys)
    want = f"error: cannot write into {out}: no space left on device (1.0 MB free, "
    assert len(errors) == 1 and errors[0].startswith(want), errors
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("ply", ["points", "mesh", "none"])
def test_the_room_asked_for_covers_one_frames_outputs(tmp_path, ckpt, ply):
    src = _folder(tmp_path / "in", {"a.png": _frame(48, 64)})
    assert _run(ckpt, src, tmp_path / "out", "--ply", ply, "--panel", "none") == 0
    written = sum(p.stat().st_size for p in (tmp_path / "out").iterdir())
    assert written <= depth_files.frame_output_bytes(64, 48, ply, panel="none") <= 4 * written + 8192


@pytest.mark.parametrize("panel", ["depth", "prior"])
def test_the_room_asked_for_covers_the_panel(tmp_path, ckpt, panel):
    """The panel's bound is its uncompressed size (a frame of noise hardly compresses); the PNG
    itself is what matplotlib drew, of ``panel_size`` pixels."""
    src = _folder(tmp_path / "in", {"a.png": _frame(48, 64)})
    assert _run(ckpt, src, tmp_path / "out", "--ply", "none", "--panel", panel) == 0
    image = tmp_path / "out" / "a_panel.png"
    assert Image.open(image).size == depth_files.panel_size(64, 48, panel)
    extra = depth_files.frame_output_bytes(64, 48, "none", panel=panel) - depth_files.frame_output_bytes(64, 48, "none",
                                                                                                  panel="none")
    assert image.stat().st_size <= extra == depth_files.png_bytes(*depth_files.panel_size(64, 48, panel))


# --------------------------------------------------------------------------- 6. stale temporary files


def test_stale_temporary_files_in_out_are_removed_and_counted(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    out = tmp_path / "out"
    out.mkdir()
    for name in (".geodepth-4194305-a_depth.npy.k1ll3d.tmp", ".geodepth-4194305-a.ply.x7.tmp"):  # a killed write
        (out / name).write_bytes(b"\x00" * 1000)
    (out / "notes.tmp").write_text("not hidden: not ours")
    assert _run(ckpt, src, out, "--ply", "none") == 0
    _, stdout = _errors(capsys)
    assert f"removed 2 half-written temporary file(s) of an interrupted run from {out}" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["a_depth.npy", "a_depth.png", "a_panel.png", "notes.tmp"]


# --------------------------------------------------------------------------- 7. outputs as inputs


def test_out_is_the_input_folder_is_refused(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    for out in (src, tmp_path / "in" / ".", tmp_path / "in" / ".." / "in"):
        assert _run(ckpt, src, out) == 2
        errors, _ = _errors(capsys)
        assert errors == [f"error: --out {out} is the --input folder: the outputs would be mixed with the images "
                          f"(and read as images by the next run); choose another --out"]
    assert sorted(p.name for p in src.iterdir()) == ["a.png"]


def test_predicts_own_outputs_in_the_input_folder_are_skipped(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24), "scan_depth.png": _frame(20, 24, 1),
                                    "b_panel.png": _frame(20, 24, 2)})
    for old in ("a_depth.png", "a_panel.png"):  # an old run's outputs beside its depth
        (src / old).write_bytes((tmp_path / "in" / "a.png").read_bytes())
    np.save(src / "a_depth.npy", np.ones((20, 24), np.float32))
    files, _ = frames.list_inputs(src)
    # photos named *_depth.png or *_panel.png without their *_depth.npy stay inputs
    assert [f.name for f in files] == ["a.png", "b_panel.png", "scan_depth.png"]
    out = src / "pred"  # --out inside --input: the listing is not recursive
    for _ in range(2):
        assert _run(ckpt, src, out, "--ply", "none", "--panel", "none") == 0
        assert _last_line(_errors(capsys)[1]) == f"3 frame(s) written to {out}"
    assert sorted(p.name for p in out.iterdir()) == ["a_depth.npy", "a_depth.png", "b_panel_depth.npy",
                                                     "b_panel_depth.png", "scan_depth_depth.npy",
                                                     "scan_depth_depth.png"]
    assert _run(ckpt, out, tmp_path / "again", "--ply", "none") == 2  # a run on predict's own folder
    assert "holds no images" in _errors(capsys)[0][0]


# --------------------------------------------------------------------------- 8. symbolic links


def test_a_symbolic_link_loop_and_a_broken_link_are_named(tmp_path, ckpt, capsys):
    (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
    (tmp_path / "broken.png").symlink_to(tmp_path / "moved" / "frame.png")
    cases = {tmp_path / "loop1": f"error: --input {tmp_path / 'loop1'}: a symbolic link loop "
                                 f"(too many levels of symbolic links)",
             tmp_path / "loop1" / "x.png": f"error: --input {tmp_path / 'loop1' / 'x.png'}: a symbolic link loop "
                                           f"(too many levels of symbolic links)",
             tmp_path / "broken.png": f"error: --input {tmp_path / 'broken.png'}: a broken symbolic link to "
                                      f"{tmp_path / 'moved' / 'frame.png'}",
             tmp_path / "nope.png": f"error: --input not found: {tmp_path / 'nope.png'}"}
    for src, line in cases.items():
        assert _run(ckpt, src, tmp_path / "out") == 2
        assert _errors(capsys)[0] == [line]
    assert not (tmp_path / "out").exists()


def test_a_broken_link_in_a_folder_is_named_not_skipped(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    (src / "b.png").symlink_to(tmp_path / "gone.png")
    assert _run(ckpt, src, tmp_path / "out", "--ply", "none") == 2
    assert _errors(capsys)[0] == [f"error: cannot read {src / 'b.png'}: no such file or directory"]
    assert (tmp_path / "out" / "a_depth.npy").exists()


# --------------------------------------------------------------------------- 9. refused runs leave nothing


def test_refused_runs_leave_no_output_folder(tmp_path, ckpt, capsys):
    nan_ckpt = save_nan_checkpoint(tmp_path / "nan.pt")
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    (tmp_path / "bad.mp4").write_bytes(b"not a video" * 100)
    runs = {"non-finite weights": (nan_ckpt, src),  # refused after --out was made: removed again
            "--checkpoint not found": (tmp_path / "none.pt", src),
            "not a readable video": (ckpt, tmp_path / "bad.mp4"),
            "holds no images": (ckpt, tmp_path / "new")}
    (tmp_path / "new").mkdir()
    for needle, (model, inputs) in runs.items():
        assert _run(model, inputs, tmp_path / "new" / "deeper" / "out") == 2
        errors, _ = _errors(capsys)
        assert len(errors) == 1 and needle in errors[0], errors
        assert list((tmp_path / "new").iterdir()) == [], needle


# --------------------------------------------------------------------------- 10. --mask files


def _mask_cases(tmp_path: Path) -> dict:
    """{the words the error must hold: the --mask file}, each refused before any work."""
    from geodepth_lite.data import fov

    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    small = fov.save_mask(np.ones((10, 12), bool), tmp_path / "small.png")
    empty = fov.save_mask(np.zeros((20, 24), bool), tmp_path / "empty.png")
    return {f"--mask not found: {tmp_path / 'nope.png'}": tmp_path / "nope.png",
            f"cannot read --mask {tmp_path / 'corrupt.png'}: not an image file": tmp_path / "corrupt.png",
            f"--mask {small} is 12 x 10 pixels but the frames are 24 x 20": small,
            f"--mask {empty} has no pixel inside the field of view": empty}


def test_a_bad_mask_file_is_refused_by_name_before_any_work(tmp_path, ckpt, capsys, monkeypatch):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    monkeypatch.setattr(checkpoint, "load_model", lambda *a, **k: pytest.fail("loaded the model"))
    for needle, mask in _mask_cases(tmp_path).items():
        assert _run(ckpt, src, tmp_path / "new" / "out", "--mask", str(mask)) == 2
        errors, _ = _errors(capsys)
        assert len(errors) == 1 and needle in errors[0], (needle, errors)
        assert not (tmp_path / "new").exists()


def test_a_bad_mask_file_loses_nothing_already_written(tmp_path, ckpt, capsys):
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    out = tmp_path / "out"
    assert _run(ckpt, src, out) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    for mask in _mask_cases(tmp_path).values():
        assert _run(ckpt, src, out, "--mask", str(mask)) == 2
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_frame_of_another_size_than_the_mask_is_named_and_the_others_go_on(tmp_path, ckpt, capsys):
    from geodepth_lite.data import fov

    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24), "b.png": _frame(30, 24), "c.png": _frame(20, 24, 1)})
    mask = np.zeros((20, 24), bool)
    mask[2:18, 3:21] = True
    mask_file = fov.save_mask(mask, tmp_path / "mask.png")
    out = tmp_path / "out"
    assert _run(ckpt, src, out, "--mask", str(mask_file), "--ply", "none") == 2
    errors, stdout = _errors(capsys)
    assert errors == [f"error: cannot use --mask {mask_file} for b: the mask is 24 x 20 pixels, the frame 24 x 30"]
    assert _outputs(out, "b") == []
    for name in "ac":
        np.testing.assert_array_equal(np.isfinite(np.load(out / f"{name}_depth.npy")), mask)
    assert _last_line(stdout) == f"2 frame(s) written to {out}; 1 failed (the error lines above)"


# --------------------------------------------------------------------------- 11. --intrinsics files


def _intrinsics_cases() -> dict[str, tuple[bytes, str]]:
    """Crafted --intrinsics files: name -> (content, what the one error line must say)."""
    laughs = "a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
        f"{n}: &{n} [{', '.join([f'*{p}'] * 9)}]\n" for p, n in zip("abcdefg", "bcdefgh"))
    return {
        "text.yaml": (b"K: [[a, 0, 1], [0, 1, 1], [0, 0, 1]]\n", "K[0]: 'a' is not a finite number"),
        "word.yaml": (b"fx: abc\nfy: 1\ncx: 1\ncy: 1\n", "fx: 'abc' is not a finite number"),
        "nan.yaml": (b"fx: 10\nfy: 10\ncx: .nan\ncy: 1\n", "cx: nan is not a finite number"),
        "inf.json": (b'{"fx": Infinity, "fy": 10, "cx": 1, "cy": 1}', "fx: inf is not a finite number"),
        "digits.yaml": (b"fx: " + b"9" * 400 + b"\nfy: 1\ncx: 1\ncy: 1\n", "fx: 9999"),
        "ragged.yaml": (b"K: [[1, 0], [0, 1, 1], [0, 0, 1]]\n", "K must be 3x3"),
        "laughs.yaml": ((laughs + "K: [[*h, 0, 0], [0, 1, 0], [0, 0, 1]]\n").encode(),
                        "K[0]: [["),
        "bools.yaml": (b"fx: 10\nfy: 10\ncx: 1\ncy: 1\nwidth: true\nheight: true\n",
                       "width and height must both be positive integers"),
        "binary.yaml": (b"\xff\xfe\x00\x81" * 8, "not a UTF-8 text file"),
        "long.yaml": (b"# " + b"x" * 70_000 + b"\nfx: 1\n", "over the limit of 65536 bytes"),
        "syntax.yaml": (b"fx: [1, 2\n", "cannot parse (ParserError"),
    }


def test_a_bad_intrinsics_file_is_one_line_naming_it_before_any_work(tmp_path, ckpt, capsys):
    """Every crafted calibration is the user's mistake (exit 2, one line naming the file and the value),
    never a bug line, a NaN point cloud or a parse of megabytes; --out is not made."""
    src = _folder(tmp_path / "in", {"a.png": _frame(20, 24)})
    for name, (content, needle) in _intrinsics_cases().items():
        calib = tmp_path / name
        calib.write_bytes(content)
        assert _run(ckpt, src, tmp_path / "out", "--intrinsics", str(calib)) == 2, name
        errors, _ = _errors(capsys)
        assert len(errors) == 1 and str(calib) in errors[0] and needle in errors[0], (name, errors)
        assert not (tmp_path / "out").exists()

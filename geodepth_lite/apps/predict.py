"""``python -m geodepth_lite predict``: zero-shot depth for your own images or video (Section 4.2.3).

The paper's stage II applies the network trained on synthetic frames to clinical images
(Kvasir, clinical videos) and turns each depth map into 3D with the endoscope's intrinsics.
For every frame this writes, into ``--out``:

- ``<name>_depth.npy``: float32 H x W z-depth at the frame's own size, in the training
  set's scene units (relative: monocular depth has no metric scale), NaN outside the
  endoscope's field of view;
- ``<name>_depth.png``: the depth colorized (``viz.colorize_depth``), black outside the field
  of view, its colour range (2nd-98th percentile) taken from the pixels inside;
- ``<name>_panel.png``: frame | depth with its colour bar (near = bright) | with ``--panel prior``
  the shading prior (``baselines.shading_prior``), outside the field of view grey; ``--panel none``
  writes none;
- ``<name>.ply``: the coloured back-projected point cloud (or mesh, ``--ply mesh``) of the
  pixels inside the field of view;

and prints one line on it (``frame_summary``): the share masked, the depth range and median
inside, the PLY's points.

The field of view (``--mask``): real endoscope frames show tissue inside a round or octagonal
window in a black border, with on-screen text. ``auto`` (the default) finds the border and the
text in each frame (``fov.detect_mask``; a frame without a border is all inside), ``none``
takes every pixel as tissue, a path gives one mask image for every frame of the run (nonzero =
inside; read and checked against the frames' size before any work). The network sees the frame
with every pixel outside replaced by its nearest inside pixel (``fov.fill_outside``), so the
border and the text cannot change the depth inside.

Frames of any size from 2 x 2 pixels up are resized to the network's input and the
prediction back to the frame (``inference.predict_depth``); each depth map is the mean of
the network's predictions for the frame and its three mirror images, mirrored back
(``--flips hv``; ``none`` for one pass). Images of 16 bits a sample are scaled to 8 bits
(``images.to_rgb8``), not clipped. Intrinsics come from ``--intrinsics`` (YAML/JSON) or a
horizontal field of view (``--fov``, default: the authors' set, fx = 0.5556 W, about 84
degrees).

Failures: before any work, the inputs (and a ``--mask`` image, an ``--intrinsics`` file: every value a
finite number) are checked and ``--out`` is created, probed for writing and for room for one frame's
outputs (``utils.check_output_dir``); a refused run leaves no folder behind. Half-written temporary
files of an interrupted run are removed from ``--out``. A folder's images that ``predict`` itself
wrote (``<name>_depth.png`` and ``<name>_panel.png`` beside ``<name>_depth.npy``) are skipped, and
``--out`` may not be the ``--input`` folder. An image or video that cannot be read, a frame of
another size than the ``--mask`` image, or a frame whose outputs cannot be made, is reported by
name and the others are still processed; a frame's outputs are written all or none. At the end
each failure is one line ``error: <message naming the file>`` on stderr, followed by the summary,
and the exit status is 2 if anything failed, else 0. A full or read-only disk stops the run at the
first frame it refuses (exit status 2).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds, fov
from geodepth_lite.data.frames import (
    DEFAULT_FOV_DEG,
    MASK_CHOICES,
    Frame,
    first_frame_size,
    frame_intrinsics,
    iter_frames,
    list_inputs,
    load_intrinsics,
    masked_frames,
)
from geodepth_lite.evaluation import baselines
from geodepth_lite.training import checkpoint
from geodepth_lite.training.inference import DEFAULT_BATCH_SIZE, FLIPS, batches, pick_device, predict_frames
from geodepth_lite.views.depth_files import PANELS, frame_output_bytes, panel_image, write_outputs

ROOM_MARGIN = 2**20  # bytes --out must have free beyond one frame's outputs
# a write failure with one of these reasons stops the run: every later frame would fail the same way
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})


@dataclass(frozen=True)
class PredictOptions:
    """Every option of one ``predict`` run, checked once when made (a ``UserError`` names the option that
    cannot work, before anything is read): the command makes it from its arguments (:meth:`from_args`),
    and the run reads only this."""

    checkpoint: Path
    input: Path
    out: Path
    intrinsics: Path | None = None
    fov: float | None = None
    batch_size: int = DEFAULT_BATCH_SIZE
    ply: str = "points"
    ply_stride: int = 1
    device: str | None = None
    flips: str = "hv"
    mask: str = "auto"
    panel: str = "depth"
    max_pixels: int = bounds.MAX_PIXELS
    progress: bool = True

    def __post_init__(self):
        if self.batch_size < 1:
            raise UserError(f"--batch-size must be at least 1, got {self.batch_size}")
        if self.ply_stride < 1:
            raise UserError(f"--ply-stride must be at least 1, got {self.ply_stride}")
        if self.max_pixels < 1:
            raise UserError(f"--max-pixels must be at least 1, got {self.max_pixels}")
        if self.fov is not None and not 0.0 < self.fov < 180.0:
            raise UserError(f"--fov must be between 0 and 180 degrees, got {self.fov}")
        if self.intrinsics is not None and self.fov is not None:
            raise UserError("give either --intrinsics or --fov, not both")
        if self.device is not None:
            utils.parse_device(self.device)  # a bad --device: one line, before any work
        if self.input.is_dir() and self.out.resolve() == self.input.resolve():  # a rerun would read its outputs
            raise UserError(f"--out {self.out} is the --input folder: the outputs would be mixed with the images "
                            f"(and read as images by the next run); choose another --out")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> PredictOptions:
        """The options of the ``predict`` command line (``add_arguments_predict``)."""
        intrinsics = None if args.intrinsics is None else Path(args.intrinsics)
        return cls(checkpoint=Path(args.checkpoint), input=Path(args.input), out=Path(args.out),
                   intrinsics=intrinsics, fov=args.fov, batch_size=args.batch_size, ply=args.ply,
                   ply_stride=args.ply_stride, device=args.device, flips=args.flips, mask=args.mask,
                   panel=args.panel, max_pixels=args.max_pixels, progress=not args.no_progress)


def stops_the_run(exc: BaseException) -> bool:
    """Whether a write failure is the disk's (full, over quota, read-only) rather than one frame's."""
    cause = exc.__cause__ if isinstance(exc, utils.FileProblem) else exc
    return isinstance(cause, OSError) and cause.errno in DISK_ERRNOS


@dataclass
class Tally:
    """What a run did: frames written, one message per failed file or frame, and the write
    failure that stopped it early (None if it ran to the end)."""

    written: int = 0
    failures: list[str] = field(default_factory=list)
    stopped: str | None = None


def _save_frame(out_dir: Path, frame: Frame, depth: np.ndarray, opts: PredictOptions, calib, tally: Tally) -> None:
    """Write one frame's outputs, count it and print its summary line (``frame_summary``); a
    failure is added to ``tally`` (a disk failure as ``tally.stopped``), never raised."""
    H, W = depth.shape
    K = frame_intrinsics(W, H, calib, opts.fov)
    try:
        panel = None
        if opts.panel != "none":
            prior = None
            if opts.panel == "prior":
                x = frame.net_input.transpose(2, 0, 1).astype(np.float32) / 255.0  # 3 x H x W in [0, 1]
                prior = np.where(frame.mask, baselines.shading_prior(x)[0], np.nan)
            panel = panel_image(frame.rgb, depth, frame.mask, prior)
        written = write_outputs(out_dir, frame.name, frame.rgb, depth, K, opts.ply, opts.ply_stride, panel)
    except OSError as exc:  # utils.FileProblem: "cannot write <file>: <reason>"
        if stops_the_run(exc):
            tally.stopped = str(exc)
        else:
            tally.failures.append(str(exc))
        return
    except Exception as exc:  # noqa: BLE001 - a frame the reconstruction cannot handle is that frame's failure
        tally.failures.append(f"cannot write the outputs of {frame.name}: {exc.__class__.__name__}: {exc}")
        return
    tally.written += 1
    tqdm.write(written["summary"], file=sys.stdout)


def _refuse_non_finite(batch, depths, ckpt: Path) -> None:
    """A ValueError if the model predicted NaN or inf for any frame of the batch (nothing of it written)."""
    for frame, depth in zip(batch, depths):
        if not np.isfinite(depth).all():
            raise UserError(f"checkpoint {ckpt} predicts non-finite depth (NaN or inf) for {frame.name}: "
                             f"nothing written for it; the model is unusable")


def predict_into(out_dir: Path, files: list[Path], kind: str, model, cfg: dict, calib, opts: PredictOptions,
                 given_mask: np.ndarray | None = None) -> Tally:
    """Predict and write every frame of ``files`` into ``out_dir``, in batches; stops early only
    when the disk refuses a write (``stops_the_run``). The network sees each frame with its outside
    filled from the inside (``fov.fill_outside``); its depth is NaN outside the field of view."""
    tally = Tally()
    total = len(files) if kind == "images" else None
    read = iter_frames(files, kind, tally.failures, opts.max_pixels)
    frames = masked_frames(read, opts.mask, given_mask, tally.failures)
    with contextlib.closing(read), tqdm(total=total, unit="frame", desc="predict", disable=not opts.progress,
                                        file=sys.stderr) as bar:
        for batch in batches(frames, opts.batch_size):
            depths = predict_frames(model, [f.net_input for f in batch], cfg["image_size"], opts.flips)
            _refuse_non_finite(batch, depths, opts.checkpoint)
            for frame, depth in zip(batch, depths):
                _save_frame(out_dir, frame, np.where(frame.mask, depth, np.float32(np.nan)), opts, calib, tally)
                if tally.stopped:
                    return tally
            bar.update(len(batch))
    return tally


def report(tally: Tally, out_dir: Path) -> int:
    """One ``error:`` line per failure on stderr, then the summary; the exit status (2 if anything failed)."""
    for msg in tally.failures + ([tally.stopped] if tally.stopped else []):
        print(f"error: {msg}", file=sys.stderr)
    summary = f"{tally.written} frame(s) written to {out_dir}" if tally.written else "no frame written"
    if tally.failures:
        summary += f"; {len(tally.failures)} failed (the error lines above)"
    if tally.stopped:
        summary += "; stopped at the write that failed: the frames after it were not processed"
    print(summary)
    return 2 if tally.failures or tally.stopped else 0


def add_arguments_predict(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", required=True, help="a checkpoint written by train (checkpoint.pt)")
    parser.add_argument("--input", required=True,
                        help="an image, a folder of images (PNG/JPG/BMP/TIFF, any size) or a video file")
    parser.add_argument("--out", required=True, help="output folder (created if missing)")
    parser.add_argument("--intrinsics", default=None,
                        help="YAML/JSON with K (3x3) or fx, fy, cx, cy in pixels, optionally width, height "
                             "(the size they refer to); default: --fov")
    parser.add_argument("--fov", type=float, default=None,
                        help=f"horizontal field of view in degrees when no --intrinsics "
                             f"(default {DEFAULT_FOV_DEG:.1f}: the authors' fx = 0.5556 W)")
    parser.add_argument("--batch-size", type=int, default=DEFAULT_BATCH_SIZE,
                        help=f"frames per forward pass (default {DEFAULT_BATCH_SIZE})")
    parser.add_argument("--ply", choices=("points", "mesh", "none"), default="points",
                        help="PLY per frame: coloured point cloud (default), surface mesh, or none")
    parser.add_argument("--ply-stride", type=int, default=1, help="keep every N-th pixel in the PLY (default 1)")
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: CUDA when available)")
    parser.add_argument("--flips", choices=tuple(FLIPS), default="hv",
                        help="test-time flips averaged into each depth map: hv (default; the mean over the four "
                        "mirrorings of the frame, 4 passes of the network), h (left-right, 2 passes) or none (one "
                        "pass, as the paper); see the teach profile's predict_flips for what it gains")
    parser.add_argument("--mask", default="auto",
                        help="the endoscope's field of view: auto (default: black border and on-screen text found "
                        "in each frame, fov.detect_mask), none (every pixel is tissue), or a mask image of the "
                        "frames' size for the whole run (nonzero = inside); pixels outside get no depth (NaN), "
                        "no colour and no 3D point")
    parser.add_argument("--panel", choices=tuple(PANELS), default="depth",
                        help="a side-by-side <name>_panel.png per frame: depth (default: frame | depth with its "
                        "colour bar), prior (and the shading prior 1/sqrt(brightness) beside them) or none")
    parser.add_argument("--max-pixels", type=int, default=bounds.MAX_PIXELS,
                        help="refuse an image, mask or video frame of more pixels than this, read from its "
                             f"header before decoding (default {bounds.MAX_PIXELS})")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_predict(args: argparse.Namespace) -> int:
    """The ``predict`` command: its options made and checked once (``PredictOptions``), then the run."""
    return predict_with(PredictOptions.from_args(args))


def predict_with(opts: PredictOptions) -> int:
    """One ``predict`` run: inputs checked, then --out made and probed, then the model loaded and every
    frame written (the module docstring says what fails how); the exit status."""
    calib = load_intrinsics(opts.intrinsics) if opts.intrinsics else None
    files, kind = list_inputs(opts.input)
    if not opts.checkpoint.is_file():
        raise FileNotFoundError(f"--checkpoint not found: {opts.checkpoint}")
    width, height = first_frame_size(files, kind, opts.max_pixels)
    given_mask = None
    if opts.mask not in MASK_CHOICES:  # one mask image for the run: read and sized before any work
        given_mask = fov.read_mask(opts.mask, (height, width) if width else None, what="--mask",
                                   max_pixels=opts.max_pixels)
    need = frame_output_bytes(width, height, opts.ply, opts.ply_stride, opts.panel) + ROOM_MARGIN
    new_folders = utils.missing_dirs(opts.out)
    out_dir = utils.check_output_dir(opts.out, need)  # creates --out; removes it again if it refuses
    lock = utils.FolderLock(out_dir, "output folder", remove_file=True)  # one writer per --out
    try:
        lock.acquire()
        stale = utils.remove_stale_temps(out_dir, locked=True)
        if stale:
            print(f"removed {stale} half-written temporary file(s) of an interrupted run from {out_dir}")
        model, cfg = checkpoint.load_model(opts.checkpoint, device=pick_device(opts.device))
        tally = predict_into(out_dir, files, kind, model, cfg, calib, opts, given_mask)
    finally:  # a run that wrote nothing leaves no folder it made
        lock.release()
        utils.remove_empty_dirs(new_folders)
    return report(tally, out_dir)

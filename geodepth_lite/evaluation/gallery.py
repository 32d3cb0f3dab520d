"""Real endoscope frames without depth: the gallery of notebook 07 (frame | prediction | shading prior).

Real frames come without ground truth, so the gallery is judged by eye, helped by two numbers per
frame that compare the prediction with the frame's own shading (``baselines.shading_prior``:
with the light at the lens, darker is farther):

- **agreement** ``r``: the correlation of log predicted depth and log shading-prior depth over
  the field of view. 1: the same relief; 0: unrelated.
- **far-blob share**: of the fifth of the field of view that the network puts farthest
  (``FAR_SHARE``), the share that the frame shows bright, i.e. in the nearer half by shading.
  0: the network's far region is dark in the image, as a lumen is; about 0.5: it has nothing to
  do with the image; above ``BLOB_LIMIT`` (0.5): the network puts its far region where the image
  is bright, a far blob that the image does not have.

Shading is a hint, not the truth: blue dye, blood and dark stool darken tissue that is near, and a
bright fold can stand in front of the lumen. The numbers flag frames to look at; the pictures decide.

The frames shipped with the workbook are in ``notebooks/gallery/`` with ``frames.csv`` (file,
view, description, SHA-256) and ``ATTRIBUTION.md`` (source and licence). Any folder of frames
works the same way; its own ``frames.csv`` (columns file and view) labels the views.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import fov
from geodepth_lite.data.frames import list_inputs
from geodepth_lite.data.images import read_rgb
from geodepth_lite.data.integrity import file_sha256
from geodepth_lite.evaluation.baselines import shading_prior
from geodepth_lite.training.inference import predict_frames
from geodepth_lite.views.viz import readable_pt

FAR_SHARE = 0.2  # the farthest fifth of the field of view is the network's "far region"
BLOB_LIMIT = 0.5  # a far region more than half bright in the image is a far blob the image does not have
GRID = 128  # the longer side, in pixels, at which prediction and shading prior are compared
VIEW_ORDER = ("lumen", "wall", "close-up", "dyed", "other", "unlabelled")
COLUMNS = ("file", "view", "description", "sha256")


def gallery_dir() -> Path:
    """``notebooks/gallery/`` of the checkout (the frames shipped with the workbook)."""
    return utils.checkout_path("notebooks", "gallery")


def read_frames_csv(path: str | Path) -> list[dict]:
    """The rows of a gallery's ``frames.csv``: at least the columns file and view."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in ("file", "view") if c not in (reader.fieldnames or [])]
        if missing:
            raise UserError(f"{path}: missing column(s) {', '.join(missing)} (a gallery's frames.csv "
                             f"needs file and view)")
        return list(reader)


def gallery_frames(folder: str | Path | None = None) -> list[dict]:
    """The gallery's frames, each {path, view, description}, in ``VIEW_ORDER`` then file order.

    ``folder`` None: the shipped frames. A folder of your own: its ``frames.csv`` when it has one,
    else every image in it with view "unlabelled". Every frame with a SHA-256 in ``frames.csv`` is
    checked against it first: an error lists every frame that is missing or changed.
    """
    shipped = folder is None
    folder = gallery_dir() if shipped else Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"gallery folder {folder} does not exist")
    table = folder / "frames.csv"
    if table.is_file():
        rows = read_frames_csv(table)
        frames = [{"path": folder / r["file"], "view": r["view"] or "unlabelled",
                   "description": r.get("description", ""), "sha256": r.get("sha256", "")} for r in rows]
    elif shipped:
        raise FileNotFoundError(f"{table} is missing: the shipped gallery is incomplete")
    else:
        files, _ = list_inputs(folder)
        frames = [{"path": p, "view": "unlabelled", "description": "", "sha256": ""} for p in files]
    problems = [f"{f['path'].name}: missing" for f in frames if not f["path"].is_file()]
    problems += [f"{f['path'].name}: SHA-256 differs from frames.csv" for f in frames
                 if f["sha256"] and f["path"].is_file() and file_sha256(f["path"]) != f["sha256"]]
    if problems:
        raise UserError(f"gallery {folder}:\n  " + "\n  ".join(problems))
    rank = {v: i for i, v in enumerate(VIEW_ORDER)}
    return sorted(frames, key=lambda f: (rank.get(f["view"], len(rank)), f["path"].name))


def _resized(a: np.ndarray, size: tuple[int, int], mode: str) -> np.ndarray:
    """An H x W or H x W x C array resized to ``size`` (h, w): bilinear, or nearest for masks."""
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    t = t[None, None] if t.dim() == 2 else t.permute(2, 0, 1)[None]
    kw = {} if mode == "nearest" else {"align_corners": False}
    out = F.interpolate(t, size=size, mode=mode, **kw)[0]
    return out[0].numpy() if a.ndim == 2 else out.permute(1, 2, 0).numpy()


def compare_to_shading(depth: np.ndarray, prior: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(agreement r, far-blob share) of a predicted depth map against the shading-prior depth of
    the same frame, over ``mask`` (module docstring). Both maps positive, the same shape."""
    lp, lq = np.log(depth[mask]), np.log(prior[mask])
    if lp.size < 10 or lp.std() == 0 or lq.std() == 0:
        return float("nan"), float("nan")
    r = float(np.corrcoef(lp, lq)[0, 1])
    far = lp >= np.quantile(lp, 1.0 - FAR_SHARE)
    share = float(np.mean(lq[far] <= np.median(lq)))
    return r, share


def score_frame(model, rgb: np.ndarray, image_size, flips: str = "none") -> dict:
    """One frame through ``predict``'s path (field of view detected, outside filled), compared with
    its shading prior at ``GRID`` px: {image, depth, prior, mask, masked, r, far_share}; the maps are
    at the comparison size, depth NaN outside the field of view."""
    mask = fov.detect_mask(rgb)
    depth = predict_frames(model, [fov.fill_outside(rgb, mask)], image_size, flips)[0]
    H, W = rgb.shape[:2]
    size = (max(8, round(GRID * H / max(H, W))), max(8, round(GRID * W / max(H, W))))
    image = _resized(rgb.astype(np.float32) / 255.0, size, "bilinear").clip(0, 1)
    m = _resized(mask.astype(np.float32), size, "nearest") > 0.5
    d = _resized(depth, size, "bilinear")
    prior = shading_prior(image.transpose(2, 0, 1)[None])[0]
    r, share = compare_to_shading(d, prior, m)
    return {"image": image, "depth": np.where(m, d, np.nan), "prior": np.where(m, prior, np.nan), "mask": m,
            "masked": float(1.0 - mask.mean()), "r": r, "far_share": share}


def score_gallery(model, frames: list[dict], image_size, flips: str = "none", progress: bool = False) -> list[dict]:
    """``score_frame`` for every frame of ``gallery_frames``: one dict per frame with its file and view."""
    rows = []
    for f in tqdm(frames, desc="gallery", unit="frame", disable=not progress):
        rows.append({"file": f["path"].name, "view": f["view"], "description": f["description"],
                     **score_frame(model, read_rgb(f["path"]), image_size, flips)})
    return rows


def summary(rows: list[dict]) -> dict[str, dict]:
    """Per view: frames, median agreement r, median far-blob share, and the frames whose share is
    above ``BLOB_LIMIT`` (far blobs the image does not have)."""
    out = {}
    for view in sorted({r["view"] for r in rows}, key=lambda v: (VIEW_ORDER + (v,)).index(v)):
        rs = [r for r in rows if r["view"] == view]
        out[view] = {"frames": len(rs), "r": float(np.nanmedian([r["r"] for r in rs])),
                     "far_share": float(np.nanmedian([r["far_share"] for r in rs])),
                     "blobs": [r["file"] for r in rs if r["far_share"] > BLOB_LIMIT]}
    return out


def gallery_figure(rows: list[dict], per_row: int = 2):
    """Frame | prediction | shading prior for every row, ``per_row`` frames to a figure row; depth
    shown as log depth with each map's own 2-98% range (near bright, far dark), the field of view
    only; each title gives the view, agreement r and far-blob share."""
    import matplotlib.pyplot as plt  # plotting only

    n_rows = (len(rows) + per_row - 1) // per_row
    fig, axes = plt.subplots(n_rows, 3 * per_row, figsize=(2.1 * 3 * per_row, 2.5 * n_rows), squeeze=False)
    pt = readable_pt(fig.get_figwidth(), least=8.0)  # every title readable where the book shows the figure
    for ax in axes.ravel():
        ax.axis("off")
    for i, row in enumerate(rows):
        a = axes.ravel()[3 * i:3 * i + 3]
        a[0].imshow(row["image"])
        a[0].set_title(f"{row['view']}\n{row['file'][:18]}", fontsize=pt)
        for ax, key, title in ((a[1], "depth", f"prediction\nr {row['r']:.2f}, far {row['far_share']:.2f}"),
                               (a[2], "prior", "shading prior")):
            log = np.log(row[key])
            lo, hi = np.nanquantile(log, [0.02, 0.98])
            ax.imshow(log, cmap="magma_r", vmin=lo, vmax=max(hi, lo + 1e-6))
            ax.set_title(title, fontsize=pt)
    fig.tight_layout()
    return fig

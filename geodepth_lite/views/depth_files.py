"""What ``predict`` writes for one frame: the depth as ``.npy`` and colorized ``.png``, the side-by-side
panel, and the PLY point cloud or mesh (``recon``); their names and their size on disk before they are
written, and the one summary line a frame gets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geodepth_lite import utils
from geodepth_lite.data.frames import OUTPUT_SUFFIX, PANEL_SUFFIX
from geodepth_lite.data.images import encode_npy, encode_png
from geodepth_lite.views import recon, viz

PANELS = {"none": 0, "depth": 2, "prior": 3}  # --panel: columns of the side-by-side PNG
PANEL_TILE_PX = 240  # height of each image in the panel, pixels
PANEL_BAR_PX = 100  # room right of a depth image for its colour bar and labels, pixels
PANEL_PAD_PX, PANEL_TITLE_PX = 8, 22  # margins and the title line, pixels
PANEL_DPI = 100
NEUTRAL = 128  # grey of the pixels outside the field of view in the panel


def png_bytes(width: int, height: int) -> int:
    """An upper bound on an RGB PNG's bytes: uncompressed samples (3 B a pixel), a filter byte a
    row, 5 B a 64 KiB stored deflate block, and the headers."""
    raw = (3 * width + 1) * height
    return raw + 5 * (raw // 65535 + 1) + 1024


def frame_output_bytes(width: int, height: int, ply: str = "points", stride: int = 1, panel: str = "depth") -> int:
    """An upper bound on the bytes of one frame's outputs: .npy (4 B a pixel), the colorized depth
    and the panel as PNG (``png_bytes``; the panel's size from ``panel_size``), PLY (15 B a
    point; a mesh 27 B a point and two 13 B triangles)."""
    points = -(-width // stride) * -(-height // stride)
    ply_bytes = {"points": 15 * points, "mesh": 53 * points, "none": 0}[ply]
    panel_bytes = png_bytes(*panel_size(width, height, panel)) if panel != "none" and width and height else 0
    return 4 * width * height + 128 + png_bytes(width, height) + panel_bytes + ply_bytes + 2048


def output_paths(out_dir: Path, name: str, ply: str = "points", panel: str = "none") -> list[Path]:
    """The files one frame gets: depth .npy, colorized depth .png, the panel .png (unless panel is
    "none") and the .ply (unless ply is "none")."""
    paths = [out_dir / f"{name}_depth.npy", out_dir / f"{name}{OUTPUT_SUFFIX}"]
    paths += [out_dir / f"{name}{PANEL_SUFFIX}"] if panel != "none" else []
    return paths + ([out_dir / f"{name}.ply"] if ply != "none" else [])


def panel_size(width: int, height: int, panel: str = "depth") -> tuple[int, int]:
    """(width, height) in pixels of the side-by-side PNG of a ``width`` x ``height`` frame: each
    image ``PANEL_TILE_PX`` tall (wider than 4:1 or taller than 1:4 frames are drawn squeezed)."""
    tile = round(PANEL_TILE_PX * min(max(width / height, 0.25), 4.0))
    columns = PANELS[panel]
    return (columns * tile + (columns - 1) * PANEL_BAR_PX + 4 * PANEL_PAD_PX,  # the frame has no bar
            PANEL_TILE_PX + PANEL_TITLE_PX + 2 * PANEL_PAD_PX)


def panel_image(rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray, prior: np.ndarray | None = None) -> np.ndarray:
    """The side-by-side view of one frame, H x W x 3 uint8 (``panel_size``): the frame | its depth
    with a colour bar (``viz.show_depth``: near = bright, range from the inside pixels) | the
    shading prior when given; pixels outside the field of view ``mask`` are neutral grey."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # heavy, needed only to draw the panel
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no figure kept alive

    H, W = depth.shape
    panel = "prior" if prior is not None else "depth"
    pw, ph = panel_size(W, H, panel)
    tile = round(PANEL_TILE_PX * min(max(W / H, 0.25), 4.0))
    fig = Figure(figsize=(pw / PANEL_DPI, ph / PANEL_DPI), dpi=PANEL_DPI)
    canvas = FigureCanvasAgg(fig)
    shown = np.where(mask[..., None], rgb, np.uint8(NEUTRAL))
    maps = [("predicted depth", depth, "z-depth")]
    maps += [("shading prior 1/sqrt(brightness)", prior, "prior depth")] if prior is not None else []
    x = PANEL_PAD_PX
    for k, (title, image) in enumerate([("frame", shown)] + [(t, d) for t, d, _ in maps]):
        ax = fig.add_axes((x / pw, PANEL_PAD_PX / ph, tile / pw, PANEL_TILE_PX / ph))
        if k == 0:
            ax.imshow(image, aspect="auto", interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
        else:
            im = viz.show_depth(ax, image, label=maps[k - 1][2], bad=f"#{NEUTRAL:02x}{NEUTRAL:02x}{NEUTRAL:02x}")
            im.set_interpolation("nearest")
            ax.set_aspect("auto")
            ax.set_position((x / pw, PANEL_PAD_PX / ph, tile / pw, PANEL_TILE_PX / ph))
            im.colorbar.ax.set_position(((x + tile + 6) / pw, PANEL_PAD_PX / ph, 10 / pw, PANEL_TILE_PX / ph))
        ax.set_title(title, fontsize=9)
        x += tile + (2 * PANEL_PAD_PX if k == 0 else PANEL_BAR_PX)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def write_outputs(out_dir: Path, name: str, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray,
                  ply: str = "points", stride: int = 1, panel: np.ndarray | None = None) -> dict:
    """The files of one frame (``output_paths``), made in memory first, then written as one set
    (``utils.write_files_atomic``): all or none. A file that cannot be made (a mesh that fails,
    say) writes none of them; one that cannot be written removes the frame's files, those an
    earlier run left under these names too (they would no longer match); either re-raises.

    depth: H x W, NaN outside the field of view (no colour in the PNG, no point in the PLY);
    panel: the side-by-side image (``panel_image``) or None. Returns {"paths": the files,
    "points": vertices in the PLY or None, "triangles": its faces or None, "summary": the frame's
    line (``frame_summary``)}.
    """
    paths = output_paths(out_dir, name, ply, "none" if panel is None else "depth")
    colour = viz.colorize_depth(depth)
    done = {"paths": paths, "points": None, "triangles": None}
    ply_data = None
    if ply != "none":
        poly = (recon.depth_mesh if ply == "mesh" else recon.point_cloud)(depth, K, rgb, stride=stride)
        ply_data = recon.ply_bytes(poly)
        done["points"], done["triangles"] = poly.n_points, (poly.n_cells if ply == "mesh" else None)
    done["summary"] = frame_summary(name, depth, done)
    files = {paths[0]: encode_npy(depth), paths[1]: encode_png(colour)}
    if panel is not None:
        files[paths[2]] = encode_png(panel)
    if ply_data is not None:
        files[paths[-1]] = ply_data
    utils.write_files_atomic(files)
    return done


def frame_summary(name: str, depth: np.ndarray, written: dict) -> str:
    """One line on a frame: share of pixels outside the field of view, depth range and median
    inside it, and what the PLY holds, e.g. ``a: 18.2% masked, depth 0.91-7.4 (median 2.3),
    12 345 points``."""
    inside = depth[np.isfinite(depth)]
    line = f"{name}: {100.0 * (1.0 - inside.size / depth.size):.1f}% masked"
    if inside.size:
        line += f", depth {inside.min():.3g}-{inside.max():.3g} (median {np.median(inside):.3g})"
    if written["points"] is None:
        return line + ", no PLY"
    line += f", {_grouped(written['points'])} points"
    if written["triangles"] is not None:
        line += f", {_grouped(written['triangles'])} triangles"
    return line


def _grouped(n: int) -> str:
    """An integer with its thousands apart: 12345 -> "12 345"."""
    return f"{n:_}".replace("_", " ")

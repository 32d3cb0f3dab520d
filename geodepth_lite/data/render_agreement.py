"""How closely the torch renderer (``render_torch.py``) reproduces the VTK renderer (``render.py``).

Both render the same frames of a manifest: the same tube, texture, pose, lights, tint and
material (the draws of ``synth.render_frame``, exposure rays cast by VTK) and the same
appearance record. Per frame it measures

- ``depth_share``: of the pixels where both see tissue, the share whose depths differ by at
  most DEPTH_TOLERANCE (relative);
- ``coverage_mismatch``: the share of pixels where one sees tissue and the other does not;
- ``mad_raw``: the mean absolute difference of the rendered RGB (8-bit levels, all pixels,
  before the appearance step), ``mad_final``: the same after it (the files a dataset holds);
- per renderer, the final frame's mean level (``brightness``) and the standard deviation of its
  luminance (``contrast``), and the depth's median.

``BOUNDS`` are the limits ``within_bounds`` checks (tests/test_render_torch.py, docs/dataset.md).
Needs VTK (it renders with both).
"""

from __future__ import annotations

import numpy as np

from geodepth_lite.data import appearance as ap
from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render as rd
from geodepth_lite.data import synth
from geodepth_lite.data import tube as tb

DEPTH_TOLERANCE = 0.005  # relative depth difference counted as agreeing
BOUNDS = {
    "depth_share": 0.99,  # at least, per frame: the share of both-tissue pixels within DEPTH_TOLERANCE
    "coverage_mismatch": 0.002,  # at most, per frame
    "mad_raw": 0.5,  # at most, per frame: mean |difference| of the rendered RGB, 8-bit levels
    "mad_final": 2.0,  # at most, per frame: the same after the appearance step (a dataset's files)
}


def pick_frames(m: dict, split: str, count: int) -> list[tuple[dict, int, str]]:
    """``count`` frames of ``split`` spread over its scenes (frame k: scene k x scenes // count, its frame k modulo
    the scene's frames; distinct when ``count`` is at most the split's frames): (planned scene, frame index,
    lighting name) each."""
    plan = synth.scene_plan(m, split)
    out = []
    for k in range(count):
        scene = plan[k * len(plan) // count]
        i, name = scene["frames"][k % len(scene["frames"])]
        out.append((scene, i, name))
    return out


def frame_inputs(m: dict, split: str, count: int) -> list[dict]:
    """The scene and draws of ``pick_frames``' frames: {"tube", "texture", "frame" (render_frame's draws),
    "material", "organ", "index"} each (a tube and texture shared by the frames of one scene)."""
    K, size = mf.intrinsics_of(m), (m["camera"]["width"], m["camera"]["height"])
    path, scenes, out = mf.split_path(m, split), {}, []
    for scene, i, name in pick_frames(m, split, count):
        if scene["scene"] not in scenes:
            preset = m["organ_presets"][scene["organ"]]
            scenes[scene["scene"]] = (tb.build_tube(preset, scene["tube_seed"], m["resolution"]),
                                      synth.scene_texture(m, split, scene))
        tube, texture = scenes[scene["scene"]]
        lighting = m["lighting_sets"][name]
        frame = synth.render_frame(synth.frame_rng(m, split, scene["scene"], i), tube,
                                   float(m["organ_presets"][scene["organ"]]["radius"]), path, lighting,
                                   m["appearance"], K=K, size=size)
        out.append({"tube": tube, "texture": texture, "frame": frame, "organ": scene["organ"], "index": i,
                    "material": {k: lighting[k] for k in rd.MATERIAL_KEYS}})
    return out


def render_with(renderer, inputs: list[dict]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rgb, depth) of every input frame by ``renderer`` (render.Renderer or render_torch.TorchRenderer)."""
    shown, out = None, []
    for item in inputs:
        if item["tube"] is not shown:
            renderer.set_tube(item["tube"], item["texture"])
            shown = item["tube"]
        renderer.set_material(item["material"])
        renderer.set_tint(item["frame"]["tint"])
        out.append(renderer.render(item["frame"]["T_world_cam"], item["frame"]["lights"]))
    return out


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def compare(vtk_frame: tuple, torch_frame: tuple, look: dict) -> dict:
    """The measures of one frame (module docstring) from both renderers' (rgb, depth) and its appearance."""
    (rgb_v, d_v), (rgb_t, d_t) = vtk_frame, torch_frame
    both = (d_v > 0) & (d_t > 0)
    rel = np.abs(d_t[both].astype(np.float64) - d_v[both]) / d_v[both]
    fin_v, fin_t = ap.apply_appearance(rgb_v, look), ap.apply_appearance(rgb_t, look)
    return {
        "depth_share": float(np.mean(rel <= DEPTH_TOLERANCE)) if both.any() else 1.0,
        "coverage_mismatch": float(np.mean((d_v > 0) != (d_t > 0))),
        "mad_raw": float(np.abs(rgb_v.astype(np.int16) - rgb_t).mean()),
        "mad_final": float(np.abs(fin_v.astype(np.int16) - fin_t).mean()),
        "brightness": (float(fin_v.mean()), float(fin_t.mean())),
        "contrast": (float(_luminance(fin_v).std()), float(_luminance(fin_t).std())),
        "depth_median": (float(np.median(d_v[d_v > 0])) if (d_v > 0).any() else 0.0,
                         float(np.median(d_t[d_t > 0])) if (d_t > 0).any() else 0.0),
    }


def agreement(inputs: list[dict], vtk_frames: list, torch_frames: list) -> list[dict]:
    """``compare`` for every frame, with its organ, view kind and index."""
    return [dict(compare(v, t, item["frame"]["appearance"]), organ=item["organ"], index=item["index"],
                 view=item["frame"]["pose"]["view"]) for item, v, t in zip(inputs, vtk_frames, torch_frames)]


def within_bounds(rows: list[dict]) -> list[str]:
    """The frames and measures outside BOUNDS (empty: all within), one line each."""
    problems = []
    for r in rows:
        for key, limit in BOUNDS.items():
            bad = r[key] < limit if key == "depth_share" else r[key] > limit
            if bad:
                problems.append(f"frame {r['index']} ({r['organ']}, {r['view']}): {key} {r[key]:.4f} "
                                f"{'<' if key == 'depth_share' else '>'} {limit}")
    return problems

"""The synthetic "Scenario dataset" (paper Section 3.A): rendering a manifest's frames to disk.

A manifest (``data_manifests/*.json``; schema and validation: ``manifest.py``) is the whole
recipe; the same manifest gives byte-identical files on the same machine, per renderer (below;
docs/dataset.md says what is tested where). Each frame follows
the paper's per-frame pipeline (``render_frame``): camera pose -> auto-exposure distance ->
lighting -> camera appearance -> render, every random draw from the frame's own generator.

Layout of a dataset directory ``DIR``::

    DIR/manifest.json                   the resolved recipe (every parameter)
    DIR/<split>/rgb/NNNNNN.png          RGB uint8
    DIR/<split>/depth/NNNNNN.npy        float32 H x W z-depth (scene units; 0 = invalid)
    DIR/<split>/frames.jsonl            one JSON object per frame (``frame_record``: paths, K, T_world_cam, ...)
    DIR/checksums.sha256                ``sha256sum -c`` format, written last (``integrity.py``)

Two renderers draw the same scene (``--renderer``): VTK (``render.Renderer``, off screen on the
CPU) and torch (``render_torch.TorchRenderer``, any torch device, no VTK; frames agree with
VTK's within the bounds docs/dataset.md states); ``auto`` picks VTK when it can be imported.
A dataset made by torch says so in ``DIR/renderer.json`` (``integrity.renderer_of``); one
without that file was made by VTK. A run never mixes two renderers' frames in one folder.

Every file is written atomically; an interrupted run is finished by running the
same command again (frames already on disk are kept; in a finished dataset, frames that
no longer match checksums.sha256 are rendered again). ``train`` and ``evaluate`` check a
dataset against its checksums first (``integrity.check_dataset``; ``--no-verify`` skips it).

Command: ``python -m geodepth_lite synth --manifest NAME|PATH --out DIR`` (and
``python -m geodepth_lite verify DIR``, in ``integrity.py``).
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import os
import shutil
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from geodepth_lite.core.errors import UserError
from geodepth_lite.data import appearance as ap
from geodepth_lite.data import integrity
from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render as rd
from geodepth_lite.data import render_torch as rt
from geodepth_lite.data import tube as tb
from geodepth_lite.data.bounds import read_npy
from geodepth_lite.data.images import encode_npy, encode_png
from geodepth_lite.utils import (
    LOCK_NAME,
    FileProblem,
    FolderLock,
    data_dir,
    make_dir,
    os_reason,
    remove_stale_temps,
    wait_for_lock,
    write_bytes_atomic,
    write_files_atomic,
    write_json_atomic,
)

LUMEN_RADII = 4.0  # a pixel deeper than this many lumen radii sees down the lumen (frames.jsonl "lumen_share")
RENDERERS = ("vtk", "torch", "auto")  # synth --renderer; auto: vtk when it can be imported, else torch
MAX_PENDING_FRAMES = 512  # torch renderer: rendered frames waiting for their appearance step and files, at most
SCENES_AHEAD = 4  # torch renderer: scenes built ahead (tube, texture, poses), at least; twice the processes if more


# ----------------------------------------------------------------------------- one frame


def render_frame(rng: np.random.Generator, tube, radius: float, path: dict, lighting: dict, look_params: dict, *,
                 K: np.ndarray, size: tuple[int, int], renderer=None, cast_rays=None) -> dict:
    """One frame by the paper's per-frame pipeline: pose -> exposure -> lighting -> appearance -> render.

    The draws come from ``rng`` in that order whether or not the frame is rendered, so they
    never depend on which frames are already on disk. tube: a tube.TubeMesh; radius: its
    organ's lumen radius (light intensity scale); path: a camera path (``manifest.split_path``);
    lighting: one lighting family; look_params: a manifest's ``appearance`` section; K and
    size (W, H): the camera. renderer: a render.Renderer showing ``tube``, or None for the
    draws alone (the record of a frame already on disk). Returns {"K", "T_world_cam", "pose"
    (sample_pose's info), "exposure_distance", "lights", "tint", "appearance"}, and "rgb",
    "depth" when rendered. cast_rays: the exposure rays' caster (``render.exposure_distance``;
    default the tube's, VTK's).
    """
    T, pose = rd.sample_pose(tube, rng, path)                        # pose: where the endoscope looks
    d_ref = rd.exposure_distance(tube, T, K, *size, cast_rays=cast_rays)  # exposure: the auto-gain distance
    frame = _lit_frame(rng, T, pose, d_ref, radius, lighting, look_params, K)
    if renderer is not None:                                          # render: shaded tube, then appearance
        frame["rgb"], frame["depth"] = _shade(renderer, T, lighting, frame["lights"], frame["tint"],
                                              frame["appearance"])
    return frame


def _lit_frame(rng: np.random.Generator, T: np.ndarray, pose: dict, d_ref: float, radius: float, lighting: dict,
               look_params: dict, K: np.ndarray) -> dict:
    """The rest of ``render_frame``'s draws once pose and exposure are known: lighting, then appearance."""
    lights, tint = rd.sample_lighting(lighting, rng, radius, d_ref)   # lighting: lights and mucosa tint
    look = ap.sample_appearance(look_params, rng)                     # appearance: the camera's effects
    return {"K": K, "T_world_cam": T, "pose": pose, "exposure_distance": d_ref, "lights": lights, "tint": tint,
            "appearance": look}


def scene_draws(m: dict, split: str, scene: dict, tube, shown, rngs: list, poses: list) -> list[dict]:
    """``render_frame``'s draws for every frame of a scene (each from its own generator, in the same order),
    given the generators after their poses were drawn (``scene_assets``); the exposure rays of all the
    poses cast in one batch by the torch renderer ``shown``."""
    K, size = mf.intrinsics_of(m), (m["camera"]["width"], m["camera"]["height"])
    radius = float(m["organ_presets"][scene["organ"]]["radius"])
    rays = [rd.exposure_rays(T, K, *size) for T, _ in poses]
    dist = shown.cast_rays_many(np.stack([o for o, _ in rays]), np.stack([d for _, d in rays]))
    return [_lit_frame(rng, T, pose, rd.exposure_from_distances(tube, dist[k]), radius, m["lighting_sets"][name],
                       m["appearance"], K)
            for k, (rng, (T, pose), (_, name)) in enumerate(zip(rngs, poses, scene["frames"]))]


def _shade(renderer, T: np.ndarray, lighting: dict, lights: list, tint, look: dict) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, depth) of the tube seen from ``T``: lit with the family's material, tinted, then the
    camera's appearance effects applied to the RGB (depth untouched)."""
    renderer.set_material({k: lighting[k] for k in rd.MATERIAL_KEYS})
    renderer.set_tint(tint)
    rgb, depth = renderer.render(T, lights)
    return ap.apply_appearance(rgb, look), depth


def frame_record(m: dict, split: str, index: int, scene: dict, lighting_name: str, frame: dict) -> dict:
    """The frames.jsonl record of frame ``index`` of ``split``: ``scene`` as planned by ``scene_plan``,
    ``frame`` as returned by ``render_frame`` (with its "depth", rendered or read back)."""
    pose = frame["pose"]
    return {
        "index": index, "rgb": f"{split}/rgb/{index:06d}.png", "depth": f"{split}/depth/{index:06d}.npy",
        "width": m["camera"]["width"], "height": m["camera"]["height"],
        "K": _round(frame["K"]), "T_world_cam": _round(frame["T_world_cam"]),
        "organ": scene["organ"], "texture": scene["texture"], "lighting": lighting_name,
        "group": f"{scene['texture']}-{lighting_name}", "scene": scene["scene"],
        "tube_seed": scene["tube_seed"], "s": round(pose["s"], 10), "view": pose["view"],
        "tilt_deg": round(pose["tilt_deg"], 10),
        "view_distance": None if pose["distance"] is None else round(pose["distance"], 10),
        "lumen_share": lumen_share(frame["depth"], float(m["organ_presets"][scene["organ"]]["radius"])),
        "tint": _round(frame["tint"]), "exposure_distance": round(frame["exposure_distance"], 10),
        "lights": [{"offset_cam": _round(light.offset), "color": _round(light.color),
                    "intensity": round(light.intensity, 10), "attenuation": [0.0, 0.0, 1.0]}
                   for light in frame["lights"]],
        "appearance": frame["appearance"],
    }


def lumen_share(depth: np.ndarray, radius: float) -> float:
    """Share of a frame's pixels that see down the lumen: deeper than LUMEN_RADII radii, or beyond far (0)."""
    d = np.asarray(depth)
    return round(float(np.mean((d > LUMEN_RADII * radius) | (d <= 0))), 6)


def _round(a) -> list:
    return np.round(np.asarray(a, dtype=np.float64), 10).tolist()


# ----------------------------------------------------------------------------- generation


def scene_plan(m: dict, split: str) -> list[dict]:
    """Scenes of a split: organ, texture, tube seed, and per frame (index, lighting family).

    Organs cycle over scenes and textures over each organ's scenes (so every organ meets
    every texture); lighting families cycle over the frames of a scene, so even a small
    split covers many texture x lighting groups.
    """
    n, per = m["splits"][split], m["frames_per_scene"]
    split_id = mf.SPLITS.index(split)
    n_org, n_tex, n_lit = len(m["organs"]), len(m["textures"]), len(m["lightings"])
    plan = []
    for k in range(math.ceil(n / per)):
        ss = np.random.SeedSequence([m["seed"], split_id, k])
        frames = list(range(k * per, min((k + 1) * per, n)))
        plan.append({"scene": k, "organ": m["organs"][k % n_org],
                     "texture": m["textures"][(k // n_org + split_id) % n_tex],
                     "tube_seed": int(ss.generate_state(1, np.uint32)[0]),
                     "frames": [(i, m["lightings"][(j + k) % n_lit]) for j, i in enumerate(frames)]})
    return plan


def frame_rng(m: dict, split: str, scene: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([m["seed"], mf.SPLITS.index(split), scene, index, 1]))


def _frame_path(out: Path, split: str, index: int, kind: str) -> Path:
    """``out/<split>/rgb/NNNNNN.png`` (kind "rgb") or ``out/<split>/depth/NNNNNN.npy`` (kind "depth")."""
    return out / split / kind / f"{index:06d}.{'png' if kind == 'rgb' else 'npy'}"


def _frame_files(m: dict) -> set[str]:
    """The rgb and depth files of every frame of manifest ``m`` (paths relative to the dataset directory)."""
    return {f for f in integrity.dataset_files(m) if f.endswith((".png", ".npy"))}


def _read_json(path: Path):
    """A JSON file's content, or None when it is missing, unreadable or not valid JSON."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):  # ValueError: json.JSONDecodeError, UnicodeDecodeError
        return None


def _remove(path: Path, what: str = "remove") -> None:
    """Delete a file or folder tree (nothing if it is missing); a FileProblem naming it otherwise."""
    if not path.exists() and not path.is_symlink():  # (unlink would fail on a read-only disk even so)
        return
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
    except OSError as exc:
        raise FileProblem(f"cannot {what} {path}: {os_reason(exc)}", path) from exc


def _check_out_dir(out: Path, m: dict, overwrite: bool) -> None:
    """Refuse to mix two datasets in one directory unless ``overwrite`` (then remove the old one)."""
    mpath = out / "manifest.json"
    if mpath.exists():
        old = _read_json(mpath)
        if old == m:
            return
        if not overwrite:
            raise FileExistsError(f"{out} already holds a different dataset "
                                  f"({old.get('name', '?') if isinstance(old, dict) else 'unreadable manifest'}); "
                                  "choose another --out or pass --overwrite")
        for split in mf.SPLITS:
            if (out / split).is_dir():
                _remove(out / split)
        for f in ("manifest.json", "checksums.sha256", integrity.RENDERER_FILE):
            _remove(out / f)
        return
    try:
        not_empty = out.exists() and any(p.name != LOCK_NAME for p in out.iterdir())  # the lock is this run's
    except OSError as exc:
        raise FileProblem(f"cannot read folder {out}: {os_reason(exc)}", out) from exc
    if not_empty and not overwrite:
        raise FileExistsError(f"{out} is not empty and holds no dataset manifest; "
                              "choose another --out or pass --overwrite")


def _remove_changed_frames(out: Path, m: dict) -> int:
    """Delete the frame files that a finished dataset of ``m`` in ``out`` no longer matches its
    checksums.sha256 with, so that this run renders them again (byte-identical). Returns how many."""
    if not (out / "checksums.sha256").is_file() or _read_json(out / "manifest.json") != m:
        return 0
    frames = _frame_files(m)
    problems = (p.partition(": ") for p in integrity.verify(out))
    changed = [rel for kind, _, rel in problems if kind == "changed" and rel in frames]
    for rel in changed:
        _remove(out / rel)
    return len(changed)


def _check_renderer(out: Path, m: dict, record: dict, overwrite: bool) -> None:
    """Refuse to add one renderer's frames to another's in ``out`` (with ``overwrite``: remove the old frames)."""
    try:
        old = integrity.renderer_of(out)
    except FileProblem:
        old = {"renderer": "unknown (renderer.json unreadable)"}
    if old == record or not any(have for have, _ in integrity.frame_counts(out, m).values()):
        return
    if not overwrite:
        raise FileExistsError(f"{out} holds frames of this manifest made by the {old['renderer']} renderer"
                              f"{' on ' + old['device'] if 'device' in old else ''}, not by {record['renderer']}"
                              f"{' on ' + record['device'] if 'device' in record else ''}; one dataset never mixes "
                              "two renderers: choose another --out, the same --renderer, or pass --overwrite")
    for split in mf.SPLITS:
        if (out / split).is_dir():
            _remove(out / split)
    for f in ("checksums.sha256", integrity.RENDERER_FILE):
        _remove(out / f)


def _prepare_out_dir(out: Path, m: dict, overwrite: bool, record: dict | None = None) -> int:
    """Make ``out`` ready for ``m``'s frames by the renderer of ``record`` (``renderer_record``; None: VTK):
    refuse (or with ``overwrite`` remove) another dataset, or another renderer's frames, delete changed frame
    files, the checksums and half-written temporaries, write manifest.json (and renderer.json but for VTK).
    Returns the number of changed frame files deleted (to be rendered again)."""
    record = dict(integrity.VTK_RECORD) if record is None else record
    make_dir(out)  # a file in the way, or a folder that cannot be created: a FileProblem naming it
    _check_out_dir(out, m, overwrite)
    _check_renderer(out, m, record, overwrite)
    replaced = _remove_changed_frames(out, m)
    _remove(out / "checksums.sha256")  # re-written last: its presence marks completion
    try:  # half-written files of a killed run (never under a final name)
        remove_stale_temps(out, recursive=True)
    except OSError as exc:
        raise FileProblem(f"cannot remove temporary files in {out}: {os_reason(exc)}", out) from exc
    write_json_atomic(out / "manifest.json", m)
    if record == integrity.VTK_RECORD:
        _remove(out / integrity.RENDERER_FILE)  # (a run of another renderer that wrote no frame yet)
    else:
        write_json_atomic(out / integrity.RENDERER_FILE, record)
    return replaced


def resolve_renderer(name: str) -> str:
    """"vtk" or "torch" for a ``--renderer`` choice (RENDERERS); auto: vtk when vtk and pyvista import."""
    if name not in RENDERERS:
        raise UserError(f"--renderer must be one of {', '.join(RENDERERS)}, got {name!r}")
    if name != "auto":
        return name
    try:
        import pyvista  # noqa: F401  (VTK: heavy; imported here only to see whether it can be)
        import vtk  # noqa: F401  (VTK: as pyvista above)
    except ImportError:
        return "torch"
    return "vtk"


def torch_device(device):
    """The torch device of ``--device`` (None: CUDA when available, else the CPU); ValueError naming the flag."""
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise UserError(f"--device: not a torch device: {device!r}") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {device}: no CUDA device is available (try --device cpu)")
    return dev


def renderer_record(renderer: str, device=None) -> dict:
    """What a dataset records of the renderer that made it (renderer.json; VTK: integrity.VTK_RECORD, no file)."""
    if renderer == "vtk":
        return dict(integrity.VTK_RECORD)
    return {"renderer": renderer, "device": torch_device(device).type, "torch": torch.__version__}


class _LazyRenderer:
    """The one renderer of a ``generate`` call, opened for the first frame to render (a dataset whose
    frames are all on disk opens none). kind: "vtk" (render.Renderer) or "torch" (render_torch.TorchRenderer
    on ``device``)."""

    def __init__(self, m: dict, kind: str = "vtk", device=None):
        self.m, self.renderer, self.kind, self.device = m, None, kind, device

    def showing(self, tube, texture: np.ndarray | None):
        if self.renderer is None:
            c = self.m["camera"]
            if self.kind == "torch":
                self.renderer = rt.TorchRenderer(c["width"], c["height"], mf.intrinsics_of(self.m), near=c["near"],
                                                 far=c["far"], device=torch_device(self.device))
            else:
                self.renderer = rd.Renderer(c["width"], c["height"], mf.intrinsics_of(self.m), near=c["near"],
                                            far=c["far"])
        self.renderer.set_tube(tube, texture)
        return self.renderer

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()


def _render_scene(m: dict, out: Path, split: str, scene: dict, renderer: _LazyRenderer, bar) -> tuple[list, int]:
    """Render the frames of one planned scene that are not on disk yet (both files). Returns (the
    frames.jsonl records of all its frames, how many frames were rendered)."""
    preset = m["organ_presets"][scene["organ"]]
    tube = tb.build_tube(preset, scene["tube_seed"], m["resolution"])
    todo = [i for i, _ in scene["frames"]
            if not (_frame_path(out, split, i, "rgb").exists() and _frame_path(out, split, i, "depth").exists())]
    shown = None
    if todo:
        shown = renderer.showing(tube, scene_texture(m, split, scene))
    camera = {"K": mf.intrinsics_of(m), "size": (m["camera"]["width"], m["camera"]["height"])}
    path = mf.split_path(m, split)
    records = []
    for i, lighting_name in scene["frames"]:
        frame = render_frame(frame_rng(m, split, scene["scene"], i), tube, float(preset["radius"]), path,
                             m["lighting_sets"][lighting_name], m["appearance"], **camera,
                             renderer=shown if i in todo else None)
        if i in todo:
            write_frame_files(out, split, i, frame["rgb"], frame["depth"])
        else:
            frame["depth"] = read_npy(_frame_path(out, split, i, "depth"))
        records.append(frame_record(m, split, i, scene, lighting_name, frame))
        bar.update(1)
    return records, len(todo)


def scene_texture(m: dict, split: str, scene: dict) -> np.ndarray:
    """The texture of a planned scene (its own generator, as every renderer draws it)."""
    tex_rng = np.random.default_rng(np.random.SeedSequence([m["seed"], mf.SPLITS.index(split), scene["scene"], 2]))
    return rd.make_texture(m["texture_sets"][scene["texture"]], tex_rng)


def _finish_frame(out: Path, split: str, index: int, rgb: np.ndarray, depth: np.ndarray, look: dict) -> None:
    """Apply a rendered frame's appearance and write both its files (a worker thread's share)."""
    write_frame_files(out, split, index, ap.apply_appearance(rgb, look), depth)


def write_frame_files(out: Path, split: str, index: int, rgb: np.ndarray, depth: np.ndarray) -> None:
    """A frame's two files, its depth (``.npy``) and its colour image (PNG, fast and lossless), written
    as one set (``utils.write_files_atomic``): both are on disk under temporary names before either is
    renamed, so only a kill between the two renames can leave one without the other (``verify`` counts
    such a frame as missing and ``synth`` renders it again)."""
    write_files_atomic({_frame_path(out, split, index, "depth"): encode_npy(depth),
                        _frame_path(out, split, index, "rgb"): encode_png(rgb, compress_level=1)})


def scene_assets(m: dict, out: Path, split: str, scene: dict) -> tuple:
    """(tube, frame indices not on disk, texture or None when there are none, the frames' generators after
    their poses were drawn, the poses (``render.sample_pose``)) of a planned scene: the CPU's share of a
    scene, run ahead in worker threads or processes (all of it picklable)."""
    tube = tb.build_tube(m["organ_presets"][scene["organ"]], scene["tube_seed"], m["resolution"])
    todo = {i for i, _ in scene["frames"]
            if not (_frame_path(out, split, i, "rgb").exists() and _frame_path(out, split, i, "depth").exists())}
    path = mf.split_path(m, split)
    rngs = [frame_rng(m, split, scene["scene"], i) for i, _ in scene["frames"]]
    poses = [rd.sample_pose(tube, rng, path) for rng in rngs]
    return tube, todo, scene_texture(m, split, scene) if todo else None, rngs, poses


def _render_scene_batched(m: dict, out: Path, split: str, scene: dict, renderer: _LazyRenderer, bar,
                          pool: ThreadPoolExecutor, assets) -> tuple[list, int, list]:
    """``_render_scene`` for the torch renderer: every draw of the scene first (the same per-frame pipeline
    and generators), then the frames not on disk rendered in one batch on the device; appearance and
    writing go to ``pool``. assets: a future of ``scene_assets`` (built ahead in ``pool``). Returns
    (records, frames rendered, the pool's futures)."""
    tube, todo, texture, rngs, poses = assets.result()
    shown = renderer.showing(tube, texture)  # (also its rays: the exposure)
    frames = scene_draws(m, split, scene, tube, shown, rngs, poses)
    batch = [k for k, (i, _) in enumerate(scene["frames"]) if i in todo]
    if batch:
        rgbs, depths = shown.render_batch(
            [frames[k]["T_world_cam"] for k in batch], [frames[k]["lights"] for k in batch],
            [frames[k]["tint"] for k in batch],
            [{key: m["lighting_sets"][scene["frames"][k][1]][key] for key in rd.MATERIAL_KEYS} for k in batch])
        rgbs, depths = rgbs.cpu().numpy(), depths.cpu().numpy()
    records, futures, rendered = [], [], dict(zip(batch, range(len(batch))))
    for k, (i, lighting_name) in enumerate(scene["frames"]):
        frame = frames[k]
        if k in rendered:
            frame["depth"] = depths[rendered[k]]
            futures.append(pool.submit(_finish_frame, out, split, i, rgbs[rendered[k]], frame["depth"],
                                       frame["appearance"]))
        else:
            frame["depth"] = read_npy(_frame_path(out, split, i, "depth"))
        records.append(frame_record(m, split, i, scene, lighting_name, frame))
        bar.update(1)
    return records, len(batch), futures


def _process_pool(processes: int | None) -> tuple:
    """(the worker processes that build scenes ahead for the torch renderer, or None; how many scenes ahead).
    ``generate``'s ``processes``; started by spawning (never forked from a process that may hold CUDA)."""
    processes = processes or 0
    if processes < 0:
        raise UserError(f"processes must be >= 0, got {processes}")
    if not processes:
        return None, SCENES_AHEAD
    return ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")), max(SCENES_AHEAD,
                                                                                               2 * processes)


def _render_split(m: dict, out: Path, split: str, renderer: _LazyRenderer, bar, pool, ahead=None,
                  n_ahead: int = SCENES_AHEAD) -> int:
    """Render a split's frames not on disk yet and write its frames.jsonl. Returns how many were rendered.
    pool: the torch renderer's worker threads (None: VTK); ahead: the executor building scenes ahead
    (``scene_assets``; None: ``pool``), ``n_ahead`` scenes ahead."""
    ahead = pool if ahead is None else ahead
    records, pending, rendered = [], [], 0
    plan = scene_plan(m, split)
    assets = []  # torch: the next scenes' tubes and textures, built ahead in the pool
    for k, scene in enumerate(plan):
        if pool is None:
            scene_records, n_rendered = _render_scene(m, out, split, scene, renderer, bar)
        else:
            while len(assets) < min(k + n_ahead, len(plan)):
                assets.append(ahead.submit(scene_assets, m, out, split, plan[len(assets)]))
            scene_records, n_rendered, futures = _render_scene_batched(m, out, split, scene, renderer, bar, pool,
                                                                       assets[k])
            assets[k] = None
            pending += futures
            while len(pending) > MAX_PENDING_FRAMES:  # bounds the frames held in memory
                pending.pop(0).result()
        records += scene_records
        rendered += n_rendered
    for future in pending:
        future.result()  # every frame file written (or the worker's error raised here)
    body = "".join(json.dumps(r, sort_keys=True) + "\n" for r in records)
    write_bytes_atomic(out / split / "frames.jsonl", body.encode())
    return rendered


def generate(m: dict, out: str | Path, *, overwrite: bool = False, progress: bool = True,
             counts: dict | None = None, renderer: str = "auto", device=None, workers: int | None = None,
             processes: int | None = None) -> Path:
    """Render the dataset of resolved manifest ``m`` into ``out`` (resuming any earlier partial run).

    Frames already on disk (both files) are kept; in a finished dataset, frame files that no
    longer match its checksums.sha256 are rendered again. ``counts``, a dict, receives
    "rendered" (frames rendered by this call), "kept" (frames reused from an earlier run) and
    "replaced" (changed frame files rendered again). A file that cannot be read or written
    raises ``utils.FileProblem`` naming it. renderer: "vtk", "torch" or "auto" (vtk when it
    imports); device: the torch renderer's (None: CUDA when available); workers: its threads for
    the appearance step and the writing (None: the CPU count, at most 16); processes: worker
    processes building the scenes ahead, tube, texture and poses (None or 0: none, the threads do
    it; they are spawned, so a calling script needs an ``if __name__ == "__main__":`` guard). The
    files do not depend on workers or processes. A folder holding another renderer's frames of
    ``m`` is refused unless ``overwrite``. The folder's lock is held while it writes: a second writer is
    refused in one line naming the first (:func:`ensure_dataset` waits for it instead).
    """
    lock = dataset_lock(out).acquire()
    try:
        return _generate(m, Path(out), overwrite=overwrite, progress=progress, counts=counts, renderer=renderer,
                         device=device, workers=workers, processes=processes)
    finally:
        lock.release()


def dataset_lock(out: str | Path) -> FolderLock:
    """The lock of a dataset folder, its file taken away on release (the folder holds the dataset only)."""
    return FolderLock(out, "dataset folder", remove_file=True)


def _generate(m: dict, out: Path, *, overwrite: bool, progress: bool, counts: dict | None, renderer: str, device,
              workers: int | None, processes: int | None) -> Path:
    """:func:`generate` under the folder's lock."""
    kind = resolve_renderer(renderer)
    replaced = _prepare_out_dir(out, m, overwrite, renderer_record(kind, device))
    total, rendered = sum(m["splits"].values()), 0
    lazy = _LazyRenderer(m, kind, device)
    pool = ThreadPoolExecutor(workers or min(16, os.cpu_count() or 1)) if kind == "torch" else None
    ahead, n_ahead = _process_pool(processes) if kind == "torch" else (None, SCENES_AHEAD)
    bar = tqdm(total=total, disable=not progress, desc=f"synth {m['name']}", unit="frame")
    try:
        for split in m["splits"]:
            rendered += _render_split(m, out, split, lazy, bar, pool, ahead, n_ahead)
    finally:
        bar.close()
        for executor in (pool, ahead):
            if executor is not None:
                executor.shutdown(wait=True, cancel_futures=True)
        lazy.close()
    integrity.write_checksums(out, m)
    if counts is not None:
        counts.update(rendered=rendered, kept=total - rendered, replaced=replaced)
    return out


def ensure_dataset(name: str, *, overrides: dict | None = None, root: str | Path | None = None,
                   progress: bool = True, renderer: str | None = None, device=None) -> Path:
    """The dataset of manifest ``data_manifests/<name>.json``, generated if missing or incomplete.

    Goes to ``data_dir()/<name>`` (or ``<name>-<8 hex>`` of the overrides' hash when
    ``overrides``, a dict merged into the manifest and validated like one, is given);
    ``root`` replaces ``data_dir()``. renderer: a complete dataset made by any renderer is
    used when None (else only one made by that renderer); a missing one is made by
    ``renderer`` ("auto" when None) on ``device``. Returns the dataset directory.
    """
    m = mf.load_manifest(name, overrides)
    stem = Path(name).name.removesuffix(".json")
    if overrides:
        stem += "-" + hashlib.sha256(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:8]
    out = Path(root) / stem if root is not None else data_dir() / stem
    wanted = None if renderer in (None, "auto") else renderer
    if integrity.is_complete_by(out, m, wanted):
        return out
    # another process making it (a second notebook, another run): wait for it, then look again
    lock = wait_for_lock(dataset_lock(out), "the process making the dataset")
    try:
        if not integrity.is_complete_by(out, m, wanted):
            _refuse_other_dataset(out, m, name, overrides)
            # a partial dataset of the same manifest is completed
            _generate(m, out, overwrite=False, progress=progress, counts=None, renderer=renderer or "auto",
                      device=device, workers=None, processes=None)
    finally:
        lock.release()
    return out


def _refuse_other_dataset(out: Path, m: dict, name: str, overrides: dict | None) -> None:
    """Refuse to replace a dataset of another manifest found where ``name``'s belongs: name both
    manifests and say how to regenerate, deleting nothing (it may be hours of rendering)."""
    mpath = out / "manifest.json"
    if not mpath.is_file():
        return
    try:
        old = json.loads(mpath.read_text())
    except (OSError, json.JSONDecodeError):
        old = None
    if old == m:
        return
    if isinstance(old, dict):
        frames = sum(old.get("splits", {}).values()) if isinstance(old.get("splits"), dict) else "?"
        found = f"manifest {old.get('name', '?')!r} with {frames} frames"
    else:
        found = "an unreadable manifest.json"
    how = ("delete that folder" if overrides else
           f"run `python -m geodepth_lite synth --manifest {name} --out {out} --overwrite`, or delete that folder")
    raise FileExistsError(f"{out} holds another dataset ({found}) than manifest {m.get('name', name)!r} "
                          f"({sum(m['splits'].values())} frames) asks for; nothing was deleted. "
                          f"To regenerate it: {how}")


def preview(m: dict, organ: str, texture: str, lighting: str, *, n: int = 1, seed: int = 0,
            path: dict | None = None, appearance: dict | None = None, tube=None, renderer=None) -> list[dict]:
    """Render ``n`` frames of one organ x texture x lighting of manifest ``m`` without writing files.

    Uses the manifest's camera, resolution, camera path and appearance (``path`` and
    ``appearance`` update the latter two). ``tube`` and ``renderer`` (an ``render.Renderer``
    of the manifest's size) may be reused. Returns dicts {"rgb", "depth", "K", "T_world_cam",
    "view", "appearance", "tube"} (the same tube for all).
    """
    for field, name, table in (("organs", organ, m["organ_presets"]), ("textures", texture, m["texture_sets"]),
                               ("lightings", lighting, m["lighting_sets"])):
        if name not in table:
            raise UserError(f"{field[:-1]} {name!r} is not in this manifest (has: {', '.join(table)})")
    c = m["camera"]
    K = mf.intrinsics_of(m)
    preset = m["organ_presets"][organ]
    light = m["lighting_sets"][lighting]
    cam_path = dict(m["camera_path"], **(path or {}))
    mf.check_views("camera_path.views", cam_path["views"])
    look_params = dict(m["appearance"], **(appearance or {}))
    ap.check_appearance("appearance", look_params)
    rng = np.random.default_rng(np.random.SeedSequence([m["seed"], seed, 99]))
    tube_seed = int(rng.integers(2**31))  # drawn either way, so a reused tube leaves the rest unchanged
    tube = tube if tube is not None else tb.build_tube(preset, tube_seed, m["resolution"])
    own = renderer is None
    renderer = rd.Renderer(c["width"], c["height"], K, near=c["near"], far=c["far"]) if own else renderer
    try:
        renderer.set_tube(tube, rd.make_texture(m["texture_sets"][texture], rng),
                          {k: light[k] for k in rd.MATERIAL_KEYS})
        frames = [render_frame(rng, tube, float(preset["radius"]), cam_path, light, look_params, K=K,
                               size=(c["width"], c["height"]), renderer=renderer) for _ in range(n)]
    finally:
        if own:
            renderer.close()
    return [{"rgb": f["rgb"], "depth": f["depth"], "K": K, "T_world_cam": f["T_world_cam"], "view": f["pose"]["view"],
             "appearance": f["appearance"], "tube": tube} for f in frames]


# ----------------------------------------------------------------------------- CLI


def add_arguments_synth(parser) -> None:
    parser.add_argument("--manifest", required=True,
                        help="manifest name in data_manifests/ (e.g. scenario_teach) or path to a .json")
    parser.add_argument("--out", default=None, help="output directory (default: <workspace>/data/<manifest name>)")
    parser.add_argument("--overwrite", action="store_true", help="replace a different dataset already in --out")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    parser.add_argument("--renderer", choices=RENDERERS, default="auto",
                        help="vtk (off screen, CPU), torch (any torch device, no VTK) or auto (default: vtk when "
                             "it imports, else torch)")
    parser.add_argument("--device", default=None,
                        help="the torch renderer's device: cpu, cuda, cuda:N (default: cuda when available)")


def run_synth(args) -> int:
    m = mf.load_manifest(args.manifest)
    out = Path(args.out) if args.out else data_dir() / Path(args.manifest).name.removesuffix(".json")
    kind = resolve_renderer(args.renderer)
    if kind == "torch":
        torch_device(args.device)  # a bad --device: one line, before anything is written
    counts: dict = {}
    processes = min(16, os.cpu_count() or 1) if kind == "torch" and torch_device(args.device).type != "cpu" else 0
    generate(m, out, overwrite=args.overwrite, progress=args.progress, counts=counts, renderer=kind,
             device=args.device, processes=processes)
    line = f"synth: rendered {counts['rendered']} frame{'s' * (counts['rendered'] != 1)}"
    if counts["kept"]:
        line += f", kept {counts['kept']} from an earlier run"
    if counts["replaced"]:
        line += f" ({counts['replaced']} changed file{'s' * (counts['replaced'] != 1)} rendered again)"
    if kind != "vtk":
        line += f" with the {kind} renderer on {torch_device(args.device).type}"
    print(f"{line} -> {out}")
    return 0


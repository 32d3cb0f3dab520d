"""The synthetic "Scenario dataset" (paper Section 3.A) on disk: manifests, generation, verification.

A manifest (``data_manifests/*.json``) is the whole recipe: generator version,
seed, camera (size, field of view, principal point, near/far), split sizes,
organ presets, texture and lighting families, camera path, mesh resolution.
The same manifest gives byte-identical files on the same machine.

Layout of a dataset directory ``DIR``::

    DIR/manifest.json                   the resolved recipe (every parameter)
    DIR/<split>/rgb/NNNNNN.png          RGB uint8
    DIR/<split>/depth/NNNNNN.npy        float32 H x W z-depth (scene units; 0 = invalid)
    DIR/<split>/frames.jsonl            one JSON object per frame (paths, K, T_world_cam, ...)
    DIR/checksums.sha256                ``sha256sum -c`` format, written last

Every file is written atomically; an interrupted run is finished by running the
same command again (frames already on disk are kept; in a finished dataset, frames that
no longer match checksums.sha256 are rendered again). ``train`` and ``evaluate`` check a
dataset against its checksums first (``check_dataset``; ``--no-verify`` skips it).

Commands: ``python -m geodepth_lite synth --manifest NAME|PATH --out DIR`` and
``python -m geodepth_lite verify DIR``.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import math
import shutil
from pathlib import Path

import numpy as np

from . import appearance as ap
from . import camera as cam
from . import render as rd
from . import tube as tb
from .utils import (
    FileProblem,
    data_dir,
    make_dir,
    manifests_dir,
    os_reason,
    read_npy,
    remove_stale_temps,
    write_bytes_atomic,
    write_json_atomic,
)

GENERATOR_VERSION = 3  # bump whenever the same manifest would render different files
SPLITS = ("train", "val", "test")
ORGANS = ("colon", "small_intestine", "stomach")
DEFAULT_FOV_X_DEG = cam.fov_x_deg(cam.intrinsics(320), 320)  # fx = 0.5556 W (the authors' set), ~84 degrees

# Top-level manifest sections and their defaults; organ_presets / texture_sets /
# lighting_sets default to the libraries in tube.py and render.py.
DEFAULTS: dict = {
    "name": "custom",                  # dataset name
    "description": "",                 # free text
    "generator_version": GENERATOR_VERSION,
    "seed": 0,                         # master seed: tubes, textures, poses, lights
    "camera": {
        "width": 320,                  # image width (pixels)
        "height": 320,                 # image height (pixels)
        "fov_x_deg": DEFAULT_FOV_X_DEG,  # horizontal field of view (degrees), fx = fy
        "principal_point": None,       # [cx, cy] in pixels, or null = (0.5 W, 0.5 H)
        "near": rd.NEAR,               # smallest valid depth (scene units)
        "far": rd.FAR,                 # largest valid depth (scene units)
    },
    "splits": {"train": 3600, "val": 900, "test": 300},
    "frames_per_scene": 30,            # frames rendered from one tube (one texture x lighting group)
    "organs": list(ORGANS),            # organ presets used, cycled over scenes
    "textures": ["pink", "red", "pale", "orange"],        # texture families used
    "lightings": ["warm_single", "white_dual", "dim_dual"],  # lighting families used
    "resolution": dict(tb.DEFAULT_RESOLUTION),
    "camera_path": {
        "mode": "random",              # "random" (jittered endoscope views) or "axis" (on the centerline)
        "s_range": [0.1, 0.6],         # camera positions along the tube (fractions of its length)
        "jitter_pos": 0.5,             # max offset from the centerline (fraction of the local radius)
        "jitter_angle_deg": 12.0,      # std of the view direction's tilt from the lumen axis
        "views": {"lumen": 0.8, "wall": 0.2},  # share of each view kind (render.VIEW_KINDS), normalized
        "views_by_split": {},          # per-split shares replacing "views", e.g. {"test": {"closeup": 1}}
        "wall_angle_deg": [45.0, 80.0],  # tilt range of wall-facing views
        "oblique_angle_deg": [25.0, 50.0],  # tilt of oblique views, from near one wall across the lumen
        "closeup_distance": [0.2, 1.0],  # closeup/papilla views: camera-to-wall, fraction of the radius
        "closeup_tilt_deg": 30.0,      # closeup/papilla views: max tilt from the wall normal
    },
    "appearance": dict(ap.APPEARANCE_DEFAULTS),  # camera/mucosa effects applied to each frame (appearance.py)
    "organ_presets": {},
    "texture_sets": {},
    "lighting_sets": {},
}
LUMEN_RADII = 4.0  # a pixel deeper than this many lumen radii sees down the lumen (frames.jsonl "lumen_share")


# ----------------------------------------------------------------------------- validation


def _type_name(v) -> str:
    return ({bool: "boolean", int: "integer", float: "number", str: "string", list: "list", dict: "object"}
            .get(type(v), type(v).__name__))


def _check_type(field: str, value, template) -> None:
    """``value`` must have the JSON type of ``template`` (ints accepted for numbers)."""
    if template is None:
        return
    if isinstance(template, bool):
        ok = isinstance(value, bool)
    elif isinstance(template, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif isinstance(template, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(template, list):
        ok = isinstance(value, list)
    else:
        ok = isinstance(value, type(template))
    if not ok:
        raise ValueError(f"manifest field '{field}' must be a {_type_name(template)}, "
                         f"got {_type_name(value)} {value!r}")


_REPLACED = {"splits", "camera_path.views"}  # sections replaced as a whole, not merged key by key


def _merge(field: str, base: dict, update: dict) -> dict:
    """Recursive merge of ``update`` into a copy of ``base``; unknown keys and wrong types are errors."""
    if not isinstance(update, dict):
        raise ValueError(f"manifest field '{field or 'manifest'}' must be an object, got {_type_name(update)}")
    out = copy.deepcopy(base)
    for key, value in update.items():
        name = f"{field}.{key}" if field else key
        if key not in base:
            raise ValueError(f"manifest has an unknown key '{name}' (allowed: {', '.join(base)})")
        if isinstance(base[key], dict) and base[key] and name not in _REPLACED:
            out[key] = _merge(name, base[key], value)
        else:
            _check_type(name, value, base[key])
            out[key] = copy.deepcopy(value)
    return out


def _range(field: str, value, lo=None, hi=None, lo_open=False, hi_open=False) -> None:
    bad = ((lo is not None and (value <= lo if lo_open else value < lo))
           or (hi is not None and (value >= hi if hi_open else value > hi)))
    if bad:
        lo_s = "" if lo is None else f"{'>' if lo_open else '>='} {lo}"
        hi_s = "" if hi is None else f"{'<' if hi_open else '<='} {hi}"
        raise ValueError(f"manifest field '{field}' must be {' and '.join(x for x in (lo_s, hi_s) if x)}, "
                         f"got {value!r}")


def _pair(field: str, value, lo=None, hi=None, lo_open=False, integer=False) -> None:
    if len(value) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise ValueError(f"manifest field '{field}' must be a [min, max] pair of numbers, got {value!r}")
    if integer and not all(isinstance(v, int) for v in value):
        raise ValueError(f"manifest field '{field}' must be a [min, max] pair of integers, got {value!r}")
    for v in value:
        _range(field, v, lo, hi, lo_open=lo_open)
    if value[0] > value[1]:
        raise ValueError(f"manifest field '{field}' must have min <= max, got {value!r}")


def _rgb(field: str, value) -> None:
    if len(value) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0
                                  for v in value):
        raise ValueError(f"manifest field '{field}' must be an [r, g, b] list of numbers in [0, 1], got {value!r}")


def _check_preset(field: str, p: dict) -> None:
    for key in ("radius", "length", "bend_wavelength", "fold_spacing", "fold_width"):
        _range(f"{field}.{key}", p[key], 0.0, lo_open=True)
    for key in ("radius_var", "bend", "fold_depth"):
        _range(f"{field}.{key}", p[key], 0.0)
    _range(f"{field}.radius_var", p["radius_var"], hi=0.5)
    _range(f"{field}.fold_depth", p["fold_depth"], hi=0.6)
    _range(f"{field}.teniae", p["teniae"], 0, 12)
    if p["fold_kind"] not in tb.FOLD_KINDS:
        raise ValueError(f"manifest field '{field}.fold_kind' must be one of {', '.join(tb.FOLD_KINDS)}, "
                         f"got {p['fold_kind']!r}")
    for key in ("polyps", "diverticula", "ridges", "papillae"):
        _pair(f"{field}.{key}", p[key], 0, 50, integer=True)
    for key in ("polyp_size", "diverticulum_size", "ridge_size", "papilla_size"):
        _pair(f"{field}.{key}", p[key], 0.0, 3.0, lo_open=True)


def _check_texture(field: str, t: dict) -> None:
    _rgb(f"{field}.base_color", t["base_color"])
    _rgb(f"{field}.vessel_color", t["vessel_color"])
    for key in ("mottle", "vessel_strength"):
        _range(f"{field}.{key}", t[key], 0.0, 1.0)
    for key in ("mottle_scale", "vessel_density", "vessel_width"):
        _range(f"{field}.{key}", t[key], 0.0, lo_open=True)
    _range(f"{field}.size", t["size"], 16, 4096)


def _check_lighting(field: str, lighting: dict) -> None:
    _range(f"{field}.n_lights", lighting["n_lights"], 1, 2)
    _range(f"{field}.offset", lighting["offset"], 0.0, 1.0)
    _pair(f"{field}.intensity", lighting["intensity"], 0.0)
    _rgb(f"{field}.color", lighting["color"])
    for key in ("color_jitter", "tint_jitter", "ambient", "diffuse", "specular"):
        _range(f"{field}.{key}", lighting[key], 0.0, 1.0)
    _range(f"{field}.specular_power", lighting["specular_power"], 0.0, lo_open=True)


def _check_views(field: str, shares) -> None:
    if not isinstance(shares, dict) or not shares:
        raise ValueError(f"manifest field '{field}' must be an object of view-kind shares, got {shares!r}")
    for kind, share in shares.items():
        if kind not in rd.VIEW_KINDS:
            raise ValueError(f"manifest field '{field}' names an unknown view kind {kind!r} "
                             f"(choose from {', '.join(rd.VIEW_KINDS)})")
        if not isinstance(share, (int, float)) or isinstance(share, bool) or share < 0:
            raise ValueError(f"manifest field '{field}.{kind}' must be a number >= 0, got {share!r}")
    if sum(shares.values()) <= 0:
        raise ValueError(f"manifest field '{field}' must give at least one view kind a share > 0, got {shares!r}")


def split_path(m: dict, split: str) -> dict:
    """The camera path of one split: ``views`` replaced by ``views_by_split[split]`` when given."""
    p = m["camera_path"]
    return dict(p, views=p["views_by_split"].get(split, p["views"]))


def _library_entries(field: str, names: list, given: dict, library: dict, check) -> dict:
    """Resolve the families named in ``names``: library defaults updated by the manifest's own entries."""
    if not isinstance(given, dict):
        raise ValueError(f"manifest field '{field}' must be an object, got {_type_name(given)}")
    out = {}
    template_keys = next(iter(library.values()))
    for name in list(given) + [n for n in names if n not in given]:
        if name in library:
            entry = _merge(f"{field}.{name}", library[name], given.get(name, {}))
        else:
            entry = _merge(f"{field}.{name}", template_keys, given[name]) if name in given else None
            if entry is None:
                raise ValueError(f"manifest names an unknown {field[:-5] if field.endswith('_sets') else field} "
                                 f"'{name}': define it under '{field}' or choose one of {', '.join(library)}")
            missing = [k for k in template_keys if k not in given[name]]
            if missing:
                raise ValueError(f"manifest field '{field}.{name}' is missing {', '.join(missing)}")
        check(f"{field}.{name}", entry)
        out[name] = entry
    return {k: out[k] for k in names} | {k: v for k, v in out.items() if k not in names}


def resolve_manifest(raw: dict, overrides: dict | None = None) -> dict:
    """Validate a manifest dict (plus optional overrides merged on top) and fill every default.

    Raises ValueError with a one-line message naming the offending field.
    """
    if not isinstance(raw, dict):
        raise ValueError(f"a manifest must be a JSON object, got {_type_name(raw)}")
    m = _merge("", DEFAULTS, raw)
    if overrides:
        m = _merge("", m, overrides)
    if m["generator_version"] != GENERATOR_VERSION:
        raise ValueError(f"manifest field 'generator_version' is {m['generator_version']}, "
                         f"this generator is version {GENERATOR_VERSION}")
    c = m["camera"]
    _range("camera.width", c["width"], 8, 8192)
    _range("camera.height", c["height"], 8, 8192)
    _range("camera.fov_x_deg", c["fov_x_deg"], 0.0, 180.0, lo_open=True, hi_open=True)
    if c["principal_point"] is not None:
        pp = c["principal_point"]
        if (not isinstance(pp, list) or len(pp) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pp)):
            raise ValueError(f"manifest field 'camera.principal_point' must be null or [cx, cy] in pixels, got {pp!r}")
    _range("camera.near", c["near"], 0.0, lo_open=True)
    _range("camera.far", c["far"], c["near"], lo_open=True)
    if not m["splits"]:
        raise ValueError("manifest field 'splits' must name at least one split (train, val, test)")
    for split, n in m["splits"].items():
        if split not in SPLITS:
            raise ValueError(f"manifest has an unknown split 'splits.{split}' (allowed: {', '.join(SPLITS)})")
        if not isinstance(n, int) or isinstance(n, bool):
            raise ValueError(f"manifest field 'splits.{split}' must be an integer, got {_type_name(n)} {n!r}")
        _range(f"splits.{split}", n, 1, 10_000_000)
    _range("frames_per_scene", m["frames_per_scene"], 1, 100_000)
    _range("seed", m["seed"], 0, 2**63 - 1)
    for key, allowed in (("organs", tb.PRESETS), ("textures", None), ("lightings", None)):
        if not m[key] or not all(isinstance(v, str) for v in m[key]):
            raise ValueError(f"manifest field '{key}' must be a non-empty list of names, got {m[key]!r}")
        if allowed is not None:
            for v in m[key]:
                if v not in allowed:
                    raise ValueError(f"manifest field '{key}' names an unknown organ preset {v!r} "
                                     f"(choose from {', '.join(allowed)})")
    r = m["resolution"]
    _range("resolution.n_theta", r["n_theta"], 8, 4096)
    _range("resolution.ring_step", r["ring_step"], 0.0, 2.0, lo_open=True)
    p = m["camera_path"]
    if p["mode"] not in ("random", "axis"):
        raise ValueError(f"manifest field 'camera_path.mode' must be 'random' or 'axis', got {p['mode']!r}")
    _pair("camera_path.s_range", p["s_range"], 0.0, 1.0)
    _range("camera_path.jitter_pos", p["jitter_pos"], 0.0, 0.9)
    _range("camera_path.jitter_angle_deg", p["jitter_angle_deg"], 0.0, 60.0)
    _check_views("camera_path.views", p["views"])
    for split, shares in p["views_by_split"].items():
        if split not in SPLITS:
            raise ValueError(f"manifest has an unknown split 'camera_path.views_by_split.{split}' "
                             f"(allowed: {', '.join(SPLITS)})")
        _check_views(f"camera_path.views_by_split.{split}", shares)
    _pair("camera_path.wall_angle_deg", p["wall_angle_deg"], 0.0, 89.0)
    _pair("camera_path.oblique_angle_deg", p["oblique_angle_deg"], 0.0, 89.0)
    _pair("camera_path.closeup_distance", p["closeup_distance"], 0.0, 1.0, lo_open=True)
    _range("camera_path.closeup_tilt_deg", p["closeup_tilt_deg"], 0.0, 80.0)
    ap.check_appearance("appearance", m["appearance"])
    m["organ_presets"] = _library_entries("organ_presets", m["organs"], m["organ_presets"], tb.PRESETS, _check_preset)
    m["texture_sets"] = _library_entries("texture_sets", m["textures"], m["texture_sets"], rd.TEXTURES, _check_texture)
    m["lighting_sets"] = _library_entries("lighting_sets", m["lightings"], m["lighting_sets"], rd.LIGHTINGS,
                                          _check_lighting)
    return m


def manifest_path(name_or_path: str | Path) -> Path:
    """A manifest file: an existing path, or a name in data_manifests/ (with or without .json)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    stem = p.name[:-5] if p.name.endswith(".json") else p.name
    q = manifests_dir() / f"{stem}.json"
    if q.is_file():
        return q
    shipped = ", ".join(sorted(x.stem for x in manifests_dir().glob("*.json")))
    raise FileNotFoundError(f"manifest {str(name_or_path)!r} not found (shipped manifests: {shipped})")


def load_manifest(name_or_path: str | Path, overrides: dict | None = None) -> dict:
    """Read, validate and resolve a manifest file (see ``resolve_manifest``)."""
    path = manifest_path(name_or_path)
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"manifest {path.name} is not valid JSON: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        reason = os_reason(exc) if isinstance(exc, OSError) else "not a text file"
        raise FileProblem(f"cannot read {path}: {reason}", path) from exc
    return resolve_manifest(raw, overrides)


def intrinsics_of(m: dict) -> np.ndarray:
    """3x3 K (pixels) of a resolved manifest."""
    c = m["camera"]
    K = cam.intrinsics_from_fov(c["width"], c["height"], c["fov_x_deg"])
    if c["principal_point"] is not None:
        K[0, 2], K[1, 2] = (float(v) for v in c["principal_point"])
    return K


# ----------------------------------------------------------------------------- generation


def _scene_plan(m: dict, split: str) -> list[dict]:
    """Scenes of a split: organ, texture, tube seed, and per frame (index, lighting family).

    Organs cycle over scenes and textures over each organ's scenes (so every organ meets
    every texture); lighting families cycle over the frames of a scene, so even a small
    split covers many texture x lighting groups.
    """
    n, per = m["splits"][split], m["frames_per_scene"]
    split_id = SPLITS.index(split)
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


def _frame_rng(m: dict, split: str, scene: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([m["seed"], SPLITS.index(split), scene, index, 1]))


def _png_bytes(rgb: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG", compress_level=1)  # fast; still lossless
    return buf.getvalue()


def _npy_bytes(depth: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


def _round(a) -> list:
    return np.round(np.asarray(a, dtype=np.float64), 10).tolist()


def _dataset_files(out: Path, m: dict) -> list[str]:
    files = ["manifest.json"]
    for split, n in m["splits"].items():
        files.append(f"{split}/frames.jsonl")
        files += [f"{split}/rgb/{i:06d}.png" for i in range(n)] + [f"{split}/depth/{i:06d}.npy" for i in range(n)]
    return files


def _frame_files(m: dict) -> set[str]:
    """The rgb and depth files of every frame of manifest ``m`` (paths relative to the dataset directory)."""
    return {f for f in _dataset_files(Path(), m) if f.endswith((".png", ".npy"))}


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
        for split in SPLITS:
            if (out / split).is_dir():
                _remove(out / split)
        for f in ("manifest.json", "checksums.sha256"):
            _remove(out / f)
        return
    try:
        not_empty = out.exists() and any(out.iterdir())
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
    changed = [rel for kind, _, rel in (p.partition(": ") for p in verify(out)) if kind == "changed" and rel in frames]
    for rel in changed:
        _remove(out / rel)
    return len(changed)


def generate(m: dict, out: str | Path, *, overwrite: bool = False, progress: bool = True,
             counts: dict | None = None) -> Path:
    """Render the dataset of resolved manifest ``m`` into ``out`` (resuming any earlier partial run).

    Frames already on disk (both files) are kept; in a finished dataset, frame files that no
    longer match its checksums.sha256 are rendered again. ``counts``, a dict, receives
    "rendered" (frames rendered by this call), "kept" (frames reused from an earlier run) and
    "replaced" (changed frame files rendered again). A file that cannot be read or written
    raises ``utils.FileProblem`` naming it.
    """
    from tqdm.auto import tqdm

    out = Path(out)
    make_dir(out)  # a file in the way, or a folder that cannot be created: a FileProblem naming it
    _check_out_dir(out, m, overwrite)
    replaced = _remove_changed_frames(out, m)
    _remove(out / "checksums.sha256")  # re-written last: its presence marks completion
    try:  # half-written files of a killed run (never under a final name)
        remove_stale_temps(out, recursive=True)
    except OSError as exc:
        raise FileProblem(f"cannot remove temporary files in {out}: {os_reason(exc)}", out) from exc
    write_json_atomic(out / "manifest.json", m)
    n_rendered = n_kept = 0
    c = m["camera"]
    W, H = c["width"], c["height"]
    K = intrinsics_of(m)
    renderer = None
    total = sum(m["splits"].values())
    bar = tqdm(total=total, disable=not progress, desc=f"synth {m['name']}", unit="frame")
    try:
        for split in m["splits"]:
            records = []
            path = split_path(m, split)
            for scene in _scene_plan(m, split):
                preset = m["organ_presets"][scene["organ"]]
                tube = tb.build_tube(preset, scene["tube_seed"], m["resolution"])
                todo = [i for i, _ in scene["frames"]
                        if not ((out / split / "rgb" / f"{i:06d}.png").exists()
                                and (out / split / "depth" / f"{i:06d}.npy").exists())]
                n_rendered += len(todo)
                n_kept += len(scene["frames"]) - len(todo)
                if todo:
                    if renderer is None:
                        renderer = rd.Renderer(W, H, K, near=c["near"], far=c["far"])
                    tex_rng = np.random.default_rng(
                        np.random.SeedSequence([m["seed"], SPLITS.index(split), scene["scene"], 2]))
                    renderer.set_tube(tube, rd.make_texture(m["texture_sets"][scene["texture"]], tex_rng))
                for i, lighting_name in scene["frames"]:
                    lighting = m["lighting_sets"][lighting_name]
                    rng = _frame_rng(m, split, scene["scene"], i)
                    T, info = rd.sample_pose(tube, rng, path)
                    d_ref = rd.exposure_distance(tube, T, K, W, H)
                    lights, tint = rd.sample_lighting(lighting, rng, float(preset["radius"]), d_ref)
                    look = ap.sample_appearance(m["appearance"], rng)
                    if i in todo:
                        renderer.set_material({k: lighting[k] for k in rd.MATERIAL_KEYS})
                        renderer.set_tint(tint)
                        rgb, depth = renderer.render(T, lights)
                        rgb = ap.apply_appearance(rgb, look)
                        write_bytes_atomic(out / split / "depth" / f"{i:06d}.npy", _npy_bytes(depth))
                        write_bytes_atomic(out / split / "rgb" / f"{i:06d}.png", _png_bytes(rgb))
                    else:
                        depth = read_npy(out / split / "depth" / f"{i:06d}.npy")
                    records.append({
                        "index": i, "rgb": f"{split}/rgb/{i:06d}.png", "depth": f"{split}/depth/{i:06d}.npy",
                        "width": W, "height": H, "K": _round(K), "T_world_cam": _round(T),
                        "organ": scene["organ"], "texture": scene["texture"], "lighting": lighting_name,
                        "group": f"{scene['texture']}-{lighting_name}", "scene": scene["scene"],
                        "tube_seed": scene["tube_seed"], "s": round(info["s"], 10), "view": info["view"],
                        "tilt_deg": round(info["tilt_deg"], 10),
                        "view_distance": None if info["distance"] is None else round(info["distance"], 10),
                        "lumen_share": lumen_share(depth, float(preset["radius"])),
                        "tint": _round(tint), "exposure_distance": round(d_ref, 10),
                        "lights": [{"offset_cam": _round(light.offset), "color": _round(light.color),
                                    "intensity": round(light.intensity, 10), "attenuation": [0.0, 0.0, 1.0]}
                                   for light in lights],
                        "appearance": look,
                    })
                    bar.update(1)
            body = "".join(json.dumps(r, sort_keys=True) + "\n" for r in records)
            write_bytes_atomic(out / split / "frames.jsonl", body.encode())
    finally:
        bar.close()
        if renderer is not None:
            renderer.close()
    write_checksums(out, m)
    if counts is not None:
        counts.update(rendered=n_rendered, kept=n_kept, replaced=replaced)
    return out


def lumen_share(depth: np.ndarray, radius: float) -> float:
    """Share of a frame's pixels that see down the lumen: deeper than LUMEN_RADII radii, or beyond far (0)."""
    d = np.asarray(depth)
    return round(float(np.mean((d > LUMEN_RADII * radius) | (d <= 0))), 6)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_checksums(out: Path, m: dict) -> None:
    lines = []
    for rel in _dataset_files(out, m):
        try:
            lines.append(f"{_sha256(out / rel)}  {rel}\n")
        except OSError as exc:
            raise FileProblem(f"cannot read {out / rel}: {os_reason(exc)}", out / rel) from exc
    write_bytes_atomic(out / "checksums.sha256", "".join(lines).encode())


def frame_counts(root: str | Path, m: dict) -> dict[str, tuple[int, int]]:
    """Per split of manifest ``m``: (complete frames in dataset directory ``root``, frames expected).

    A frame is complete when both its files are there (``<split>/rgb/NNNNNN.png`` and
    ``<split>/depth/NNNNNN.npy``; each is written atomically, so a present file is whole).
    """
    root = Path(root)
    out = {}
    for split, n in m["splits"].items():
        names = {}
        for kind in ("rgb", "depth"):
            try:
                names[kind] = set(p.name for p in (root / split / kind).iterdir())
            except OSError:  # not there yet (or unreadable: counted as absent)
                names[kind] = set()
        out[split] = (sum(1 for i in range(n) if f"{i:06d}.png" in names["rgb"] and f"{i:06d}.npy" in names["depth"]),
                      n)
    return out


def _dataset_manifest(root: Path) -> tuple[dict | None, str | None]:
    """(DIR/manifest.json with a usable "splits", None), or (None, the problem line saying what is wrong)."""
    mpath = root / "manifest.json"
    if not mpath.exists():
        return None, ("missing: manifest.json and checksums.sha256 (not a dataset written by synth, or synth "
                      "stopped before it began: run synth again)")
    try:
        m = json.loads(mpath.read_text())
    except OSError as exc:
        reason = os_reason(exc)
    except ValueError as exc:  # json.JSONDecodeError, UnicodeDecodeError
        reason = f"not valid JSON: {exc}"
    else:
        splits = m.get("splits") if isinstance(m, dict) else None
        ok = (isinstance(splits, dict) and splits
              and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in splits.values()))
        if ok:
            return m, None
        reason = "no 'splits' object of frame counts"
    return None, (f"unreadable: manifest.json ({reason}); checksums.sha256 is missing too, so the frames cannot "
                  "be counted: run synth again with --overwrite")


def _incomplete(root: Path) -> list[str]:
    """verify's report on a dataset directory without checksums.sha256: frames present and expected per split."""
    m, problem = _dataset_manifest(root)
    if m is None:
        return [problem]
    counts = frame_counts(root, m)
    parts = [f"{split} {have}/{n}" for split, (have, n) in counts.items()]
    parts[0] += " frames"
    return [f"incomplete: {', '.join(parts)} (checksums.sha256 is written last; run synth again to finish)"]


def verify(root: str | Path) -> list[str]:
    """Problems of a dataset directory against its checksums: 'missing: f', 'changed: f', 'unreadable: f'.

    An empty list means every listed file is present and unchanged. Without checksums.sha256
    (synth has not finished) the one problem is 'incomplete: ...' with the frames present and
    expected per split of manifest.json (or what is wrong with manifest.json).
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"dataset directory {root} does not exist")
    if not root.is_dir():
        raise FileProblem(f"cannot verify {root}: it is a file, not a dataset folder", root)
    sums = root / "checksums.sha256"
    if not sums.is_file():
        return _incomplete(root)
    try:
        text = sums.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        return [f"unreadable: checksums.sha256 ({os_reason(exc) if isinstance(exc, OSError) else 'not a text file'})"]
    problems = []
    for line_no, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        digest, _, rel = line.partition("  ")
        if len(digest) != 64 or not rel:
            problems.append(f"unreadable: checksums.sha256 line {line_no}")
            continue
        path = root / rel
        if not path.exists():
            problems.append(f"missing: {rel}")
            continue
        try:
            actual = _sha256(path)
        except OSError as exc:
            problems.append(f"unreadable: {rel} ({os_reason(exc)})")
            continue
        if actual != digest:
            problems.append(f"changed: {rel}")
    return problems


def _complete_splits(root: Path, splits) -> bool:
    """Without checksums.sha256: whether every frame of ``splits`` (those in manifest.json) and
    their frames.jsonl are on disk."""
    m, _ = _dataset_manifest(root)
    if m is None:
        return False
    counts = frame_counts(root, {"splits": {s: n for s, n in m["splits"].items() if s in splits}})
    return all(have == n and (root / s / "frames.jsonl").is_file() for s, (have, n) in counts.items())


def check_dataset(root: str | Path, splits=None, *, limit: int = 5) -> None:
    """Check a synthetic dataset directory against its checksums.sha256 before it is used
    (``train`` and ``evaluate`` call this unless ``--no-verify``).

    splits: check only the files of these splits (and the top-level ones, manifest.json);
    None: all. Without checksums.sha256 (synth did not finish, or a folder put together by
    hand) there is nothing to compare with: the check passes only when ``splits`` (not None)
    are complete on disk. Raises a one-line ValueError naming the problems (the first
    ``limit``, then "and N more") and how to fix them: synth renders missing or changed frames again.
    """
    root = Path(root)
    problems = verify(root)
    if splits is not None:
        if not (root / "checksums.sha256").is_file():
            problems = [] if _complete_splits(root, set(splits)) else problems
        else:
            def split_of(problem: str) -> str | None:
                rel = problem.partition(": ")[2]
                return rel.split("/", 1)[0] if "/" in rel.split(" ", 1)[0] else None
            problems = [p for p in problems if split_of(p) in (None, *splits)]
    if not problems:
        return
    shown = "; ".join(problems[:limit])
    if len(problems) > limit:
        shown += f"; and {len(problems) - limit} more"
    cmd = f"python -m geodepth_lite synth --manifest {root / 'manifest.json'} --out {root}"
    raise ValueError(f"dataset {root} failed verification against checksums.sha256: {shown}. "
                     f"Regenerate it with `{cmd}` (renders missing and changed frames again), "
                     "or pass --no-verify to use it as it is")


def is_complete(root: Path, m: dict) -> bool:
    """Cheap completeness check: same manifest, checksums written, every file present (no hashing)."""
    try:
        if json.loads((root / "manifest.json").read_text()) != m:
            return False
    except (OSError, json.JSONDecodeError):
        return False
    return (root / "checksums.sha256").is_file() and all((root / f).is_file() for f in _dataset_files(root, m))


def ensure_dataset(name: str, *, overrides: dict | None = None, root: str | Path | None = None,
                   progress: bool = True) -> Path:
    """The dataset of manifest ``data_manifests/<name>.json``, generated if missing or incomplete.

    Goes to ``data_dir()/<name>`` (or ``<name>-<8 hex>`` of the overrides' hash when
    ``overrides``, a dict merged into the manifest and validated like one, is given);
    ``root`` replaces ``data_dir()``. Returns the dataset directory.
    """
    m = load_manifest(name, overrides)
    stem = Path(name).name.removesuffix(".json")
    if overrides:
        stem += "-" + hashlib.sha256(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:8]
    out = Path(root) / stem if root is not None else data_dir() / stem
    if not is_complete(out, m):
        _refuse_other_dataset(out, m, name, overrides)
        generate(m, out, progress=progress)  # a partial dataset of the same manifest is completed
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
            raise ValueError(f"{field[:-1]} {name!r} is not in this manifest (has: {', '.join(table)})")
    c = m["camera"]
    W, H = c["width"], c["height"]
    K = intrinsics_of(m)
    preset = m["organ_presets"][organ]
    light = m["lighting_sets"][lighting]
    cam_path = dict(m["camera_path"], **(path or {}))
    _check_views("camera_path.views", cam_path["views"])
    look_params = dict(m["appearance"], **(appearance or {}))
    ap.check_appearance("appearance", look_params)
    rng = np.random.default_rng(np.random.SeedSequence([m["seed"], seed, 99]))
    tube_seed = int(rng.integers(2**31))  # drawn either way, so a reused tube leaves the rest unchanged
    tube = tube if tube is not None else tb.build_tube(preset, tube_seed, m["resolution"])
    out = []
    own = renderer is None
    renderer = rd.Renderer(W, H, K, near=c["near"], far=c["far"]) if own else renderer
    try:
        renderer.set_tube(tube, rd.make_texture(m["texture_sets"][texture], rng),
                          {k: light[k] for k in ("ambient", "diffuse", "specular", "specular_power")})
        for _ in range(n):
            T, info = rd.sample_pose(tube, rng, cam_path)
            lights, tint = rd.sample_lighting(light, rng, float(preset["radius"]),
                                              rd.exposure_distance(tube, T, K, W, H))
            look = ap.sample_appearance(look_params, rng)
            renderer.set_tint(tint)
            rgb, depth = renderer.render(T, lights)
            out.append({"rgb": ap.apply_appearance(rgb, look), "depth": depth, "K": K, "T_world_cam": T,
                        "view": info["view"], "appearance": look, "tube": tube})
    finally:
        if own:
            renderer.close()
    return out


# ----------------------------------------------------------------------------- CLI


def add_arguments_synth(parser) -> None:
    parser.add_argument("--manifest", required=True,
                        help="manifest name in data_manifests/ (e.g. scenario_teach) or path to a .json")
    parser.add_argument("--out", default=None, help="output directory (default: <workspace>/data/<manifest name>)")
    parser.add_argument("--overwrite", action="store_true", help="replace a different dataset already in --out")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")


def run_synth(args) -> int:
    m = load_manifest(args.manifest)
    out = Path(args.out) if args.out else data_dir() / Path(args.manifest).name.removesuffix(".json")
    counts: dict = {}
    generate(m, out, overwrite=args.overwrite, progress=args.progress, counts=counts)
    line = f"synth: rendered {counts['rendered']} frame{'s' * (counts['rendered'] != 1)}"
    if counts["kept"]:
        line += f", kept {counts['kept']} from an earlier run"
    if counts["replaced"]:
        line += f" ({counts['replaced']} changed file{'s' * (counts['replaced'] != 1)} rendered again)"
    print(f"{line} -> {out}")
    return 0


def add_arguments_verify(parser) -> None:
    parser.add_argument("dir", help="dataset directory (holds manifest.json and checksums.sha256)")


def run_verify(args) -> int:
    problems = verify(args.dir)
    for p in problems:
        print(p)
    if problems:
        print(f"verify: {len(problems)} problem(s) in {args.dir}")
        return 1
    n = sum(1 for line in (Path(args.dir) / "checksums.sha256").read_text().splitlines() if line.strip())
    print(f"verify: ok, {n} files match checksums.sha256")
    return 0

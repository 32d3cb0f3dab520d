"""The manifest of a synthetic dataset (paper Section 3.A): its schema, validation and resolution.

A manifest (``data_manifests/*.json``) is the whole recipe of a dataset: generator version,
seed, camera (size, field of view, principal point, near/far), split sizes, organ presets,
texture and lighting families, camera path, mesh resolution, appearance. ``DEFAULTS`` is the
schema (every section, key and default); ``resolve_manifest`` validates a manifest dict against
it and fills every default, with one-line errors naming the offending field; ``load_manifest``
reads one by name (``data_manifests/<name>.json``) or path. ``synth.py`` renders a resolved
manifest; the same manifest gives byte-identical files on the same machine, per renderer.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np

from geodepth_lite.data import appearance as ap
from geodepth_lite.data import render as rd
from geodepth_lite.data import tube as tb
from geodepth_lite.core import camera as cam
from geodepth_lite.core.errors import UserError
from geodepth_lite.data.bounds import MAX_MANIFEST_BYTES, MAX_PIXELS
from geodepth_lite.utils import FileProblem, manifests_dir, os_reason

GENERATOR_VERSION = 3  # bump whenever the same manifest would render different files (synth.py)
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
        name = _type_name(template)
        raise UserError(f"manifest field '{field}' must be {'an' if name[0] in 'aeiou' else 'a'} {name}, "
                         f"got {_type_name(value)} {value!r}")


_REPLACED = {"splits", "camera_path.views"}  # sections replaced as a whole, not merged key by key


def _merge(field: str, base: dict, update: dict) -> dict:
    """Recursive merge of ``update`` into a copy of ``base``; unknown keys and wrong types are errors."""
    if not isinstance(update, dict):
        raise UserError(f"manifest field '{field or 'manifest'}' must be an object, got {_type_name(update)}")
    out = copy.deepcopy(base)
    for key, value in update.items():
        name = f"{field}.{key}" if field else key
        if key not in base:
            raise UserError(f"manifest has an unknown key '{name}' (allowed: {', '.join(base)})")
        if isinstance(base[key], dict) and base[key] and name not in _REPLACED:
            out[key] = _merge(name, base[key], value)
        else:
            _check_type(name, value, base[key])
            out[key] = copy.deepcopy(value)
    return out


def _check_number(field: str, value) -> None:
    """A UserError naming ``field`` for a float that is not finite (JSON readers accept NaN and Infinity)
    or an integer no float holds (the renderer computes with floats); anything else passes."""
    if isinstance(value, float) and not math.isfinite(value):
        raise UserError(f"manifest field '{field}' must be a finite number, got {value!r}")
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            float(value)
        except OverflowError:  # an integer of hundreds of digits
            raise UserError(f"manifest field '{field}' must be a finite number, got an integer of "
                            f"{len(str(abs(value)))} digits") from None


def _range(field: str, value, lo=None, hi=None, lo_open=False, hi_open=False) -> None:
    _check_number(field, value)
    bad = ((lo is not None and (value <= lo if lo_open else value < lo))
           or (hi is not None and (value >= hi if hi_open else value > hi)))
    if bad:
        lo_s = "" if lo is None else f"{'>' if lo_open else '>='} {lo}"
        hi_s = "" if hi is None else f"{'<' if hi_open else '<='} {hi}"
        raise UserError(f"manifest field '{field}' must be {' and '.join(x for x in (lo_s, hi_s) if x)}, "
                         f"got {value!r}")


def _pair(field: str, value, lo=None, hi=None, lo_open=False, integer=False) -> None:
    if len(value) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise UserError(f"manifest field '{field}' must be a [min, max] pair of numbers, got {value!r}")
    if integer and not all(isinstance(v, int) for v in value):
        raise UserError(f"manifest field '{field}' must be a [min, max] pair of integers, got {value!r}")
    for v in value:
        _range(field, v, lo, hi, lo_open=lo_open)
    if value[0] > value[1]:
        raise UserError(f"manifest field '{field}' must have min <= max, got {value!r}")


def _rgb(field: str, value) -> None:
    if len(value) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0
                                  for v in value):
        raise UserError(f"manifest field '{field}' must be an [r, g, b] list of numbers in [0, 1], got {value!r}")


def _check_preset(field: str, p: dict) -> None:
    for key in ("radius", "length", "bend_wavelength", "fold_spacing", "fold_width"):
        _range(f"{field}.{key}", p[key], 0.0, lo_open=True)
    for key in ("radius_var", "bend", "fold_depth"):
        _range(f"{field}.{key}", p[key], 0.0)
    _range(f"{field}.radius_var", p["radius_var"], hi=0.5)
    _range(f"{field}.fold_depth", p["fold_depth"], hi=0.6)
    _range(f"{field}.teniae", p["teniae"], 0, 12)
    if p["fold_kind"] not in tb.FOLD_KINDS:
        raise UserError(f"manifest field '{field}.fold_kind' must be one of {', '.join(tb.FOLD_KINDS)}, "
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


def check_views(field: str, shares) -> None:
    """``shares`` ({view kind: share}) must name known view kinds (render.VIEW_KINDS) with shares >= 0, one > 0."""
    if not isinstance(shares, dict) or not shares:
        raise UserError(f"manifest field '{field}' must be an object of view-kind shares, got {shares!r}")
    for kind, share in shares.items():
        if kind not in rd.VIEW_KINDS:
            raise UserError(f"manifest field '{field}' names an unknown view kind {kind!r} "
                             f"(choose from {', '.join(rd.VIEW_KINDS)})")
        if not isinstance(share, (int, float)) or isinstance(share, bool) or share < 0:
            raise UserError(f"manifest field '{field}.{kind}' must be a number >= 0, got {share!r}")
    if sum(shares.values()) <= 0:
        raise UserError(f"manifest field '{field}' must give at least one view kind a share > 0, got {shares!r}")


def split_path(m: dict, split: str) -> dict:
    """The camera path of one split: ``views`` replaced by ``views_by_split[split]`` when given."""
    p = m["camera_path"]
    return dict(p, views=p["views_by_split"].get(split, p["views"]))


def _library_entries(field: str, names: list, given: dict, library: dict, check) -> dict:
    """Resolve the families named in ``names``: library defaults updated by the manifest's own entries."""
    if not isinstance(given, dict):
        raise UserError(f"manifest field '{field}' must be an object, got {_type_name(given)}")
    out = {}
    template_keys = next(iter(library.values()))
    for name in list(given) + [n for n in names if n not in given]:
        if name in library:
            entry = _merge(f"{field}.{name}", library[name], given.get(name, {}))
        else:
            entry = _merge(f"{field}.{name}", template_keys, given[name]) if name in given else None
            if entry is None:
                raise UserError(f"manifest names an unknown {field[:-5] if field.endswith('_sets') else field} "
                                 f"'{name}': define it under '{field}' or choose one of {', '.join(library)}")
            missing = [k for k in template_keys if k not in given[name]]
            if missing:
                raise UserError(f"manifest field '{field}.{name}' is missing {', '.join(missing)}")
        check(f"{field}.{name}", entry)
        out[name] = entry
    return {k: out[k] for k in names} | {k: v for k, v in out.items() if k not in names}


# ----------------------------------------------------------------------------- resolution


def _check_camera(c: dict) -> None:
    _range("camera.width", c["width"], 8, 8192)
    _range("camera.height", c["height"], 8, 8192)
    _range("camera.fov_x_deg", c["fov_x_deg"], 0.0, 180.0, lo_open=True, hi_open=True)
    if c["principal_point"] is not None:
        pp = c["principal_point"]
        if (not isinstance(pp, list) or len(pp) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pp)):
            raise UserError(f"manifest field 'camera.principal_point' must be null or [cx, cy] in pixels, got {pp!r}")
    _range("camera.near", c["near"], 0.0, lo_open=True)
    _range("camera.far", c["far"], c["near"], lo_open=True)


def _check_splits(m: dict) -> None:
    if not m["splits"]:
        raise UserError("manifest field 'splits' must name at least one split (train, val, test)")
    for split, n in m["splits"].items():
        if split not in SPLITS:
            raise UserError(f"manifest has an unknown split 'splits.{split}' (allowed: {', '.join(SPLITS)})")
        if not isinstance(n, int) or isinstance(n, bool):
            raise UserError(f"manifest field 'splits.{split}' must be an integer, got {_type_name(n)} {n!r}")
        _range(f"splits.{split}", n, 1, 10_000_000)
    _range("frames_per_scene", m["frames_per_scene"], 1, 100_000)
    _range("seed", m["seed"], 0, 2**63 - 1)


def _check_family_lists(m: dict) -> None:
    """The names in ``organs``, ``textures`` and ``lightings`` (organs must be presets of tube.py)."""
    for key, allowed in (("organs", tb.PRESETS), ("textures", None), ("lightings", None)):
        if not m[key] or not all(isinstance(v, str) for v in m[key]):
            raise UserError(f"manifest field '{key}' must be a non-empty list of names, got {m[key]!r}")
        if allowed is not None:
            for v in m[key]:
                if v not in allowed:
                    raise UserError(f"manifest field '{key}' names an unknown organ preset {v!r} "
                                     f"(choose from {', '.join(allowed)})")


def _check_camera_path(p: dict) -> None:
    if p["mode"] not in ("random", "axis"):
        raise UserError(f"manifest field 'camera_path.mode' must be 'random' or 'axis', got {p['mode']!r}")
    _pair("camera_path.s_range", p["s_range"], 0.0, 1.0)
    _range("camera_path.jitter_pos", p["jitter_pos"], 0.0, 0.9)
    _range("camera_path.jitter_angle_deg", p["jitter_angle_deg"], 0.0, 60.0)
    check_views("camera_path.views", p["views"])
    for split, shares in p["views_by_split"].items():
        if split not in SPLITS:
            raise UserError(f"manifest has an unknown split 'camera_path.views_by_split.{split}' "
                             f"(allowed: {', '.join(SPLITS)})")
        check_views(f"camera_path.views_by_split.{split}", shares)
    _pair("camera_path.wall_angle_deg", p["wall_angle_deg"], 0.0, 89.0)
    _pair("camera_path.oblique_angle_deg", p["oblique_angle_deg"], 0.0, 89.0)
    _pair("camera_path.closeup_distance", p["closeup_distance"], 0.0, 1.0, lo_open=True)
    _range("camera_path.closeup_tilt_deg", p["closeup_tilt_deg"], 0.0, 80.0)


def resolve_manifest(raw: dict, overrides: dict | None = None) -> dict:
    """Validate a manifest dict (plus optional overrides merged on top) and fill every default.

    Raises ValueError with a one-line message naming the offending field.
    """
    if not isinstance(raw, dict):
        raise UserError(f"a manifest must be a JSON object, got {_type_name(raw)}")
    m = _merge("", DEFAULTS, raw)
    if overrides:
        m = _merge("", m, overrides)
    if m["generator_version"] != GENERATOR_VERSION:
        raise UserError(f"manifest field 'generator_version' is {m['generator_version']}, "
                         f"this generator is version {GENERATOR_VERSION}")
    _check_camera(m["camera"])
    _check_splits(m)
    _check_family_lists(m)
    _range("resolution.n_theta", m["resolution"]["n_theta"], 8, 4096)
    _range("resolution.ring_step", m["resolution"]["ring_step"], 0.0, 2.0, lo_open=True)
    _check_camera_path(m["camera_path"])
    ap.check_appearance("appearance", m["appearance"])
    m["organ_presets"] = _library_entries("organ_presets", m["organs"], m["organ_presets"], tb.PRESETS, _check_preset)
    m["texture_sets"] = _library_entries("texture_sets", m["textures"], m["texture_sets"], rd.TEXTURES, _check_texture)
    m["lighting_sets"] = _library_entries("lighting_sets", m["lightings"], m["lighting_sets"], rd.LIGHTINGS,
                                          _check_lighting)
    _check_finite("", m)
    check_memory(m)
    return m


def _check_finite(field: str, value, depth: int = 0) -> None:
    """Every number anywhere in the manifest finite (JSON readers accept NaN and Infinity), and every
    integer within a float's range (the renderer computes with floats)."""
    _check_number(field, value)
    if depth > MAX_JSON_DEPTH:
        raise UserError(f"manifest field '{field}' is nested over {MAX_JSON_DEPTH} deep")
    if isinstance(value, dict):
        for k, v in value.items():
            _check_finite(f"{field}.{k}" if field else str(k), v, depth + 1)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _check_finite(f"{field}[{i}]", v, depth + 1)


# What one render may take: a tube mesh of at most MAX_MESH_VERTICES points (about
# MESH_BYTES_PER_VERTEX each while it is built and traced), frames of at most bounds.MAX_PIXELS.
MAX_MESH_VERTICES = 4_000_000  # the shipped manifests' tubes have 20 000 to 60 000
MESH_BYTES_PER_VERTEX = 400
MAX_JSON_DEPTH = 64  # nesting of a manifest or a frames.jsonl record (the schema needs 4)


def mesh_vertices(m: dict, organ: str) -> int:
    """Points of the tube mesh ``tube.make_tube`` builds for ``organ`` under manifest ``m``."""
    p, res = m["organ_presets"][organ], m["resolution"]
    rings = max(math.ceil(float(p["length"]) / (float(res["ring_step"]) * float(p["radius"]))) + 1, 2)
    return rings * (int(res["n_theta"]) + 1)


def check_memory(m: dict) -> None:
    """A ValueError naming the field when rendering ``m`` would need more than the bounds above."""
    c = m["camera"]
    if c["width"] * c["height"] > MAX_PIXELS:
        raise UserError(f"manifest fields 'camera.width' x 'camera.height' give {c['width']} x {c['height']} "
                         f"pixels, over the limit of {MAX_PIXELS} pixels a frame")
    for organ in m["organs"]:
        n = mesh_vertices(m, organ)
        if n > MAX_MESH_VERTICES:
            raise UserError(f"manifest field 'resolution.ring_step' ({m['resolution']['ring_step']!r}) with "
                             f"'organ_presets.{organ}.length' / 'radius' asks for a tube mesh of {n} points "
                             f"(about {n * MESH_BYTES_PER_VERTEX / 2**30:.3g} GiB), over the limit of "
                             f"{MAX_MESH_VERTICES} points: use a larger ring_step or a shorter tube")


# ----------------------------------------------------------------------------- loading


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
        if path.stat().st_size > MAX_MANIFEST_BYTES:
            raise FileProblem(f"cannot read manifest {path}: {path.stat().st_size} bytes, over the limit of "
                              f"{MAX_MANIFEST_BYTES} bytes for a manifest", path)
        raw = json.loads(path.read_text())
    except FileProblem:
        raise
    except json.JSONDecodeError as exc:
        raise UserError(f"manifest {path.name} is not valid JSON: {exc}") from None
    except RecursionError:
        raise UserError(f"manifest {path} is not a usable manifest: its JSON is nested too deep "
                         f"(a manifest nests at most {MAX_JSON_DEPTH} levels)") from None
    except (OSError, UnicodeDecodeError) as exc:
        reason = os_reason(exc) if isinstance(exc, OSError) else "not a text file"
        raise FileProblem(f"cannot read {path}: {reason}", path) from exc
    try:
        return resolve_manifest(raw, overrides)
    except RecursionError:
        raise UserError(f"manifest {path}: nested too deep (a manifest nests at most {MAX_JSON_DEPTH} levels)"
                         ) from None
    except ValueError as exc:
        raise UserError(f"manifest {path}: {exc}") from None


def intrinsics_of(m: dict) -> np.ndarray:
    """3x3 K (pixels) of a resolved manifest."""
    c = m["camera"]
    K = cam.intrinsics_from_fov(c["width"], c["height"], c["fov_x_deg"])
    if c["principal_point"] is not None:
        K[0, 2], K[1, 2] = (float(v) for v in c["principal_point"])
    return K

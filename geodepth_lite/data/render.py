"""Headless rendering of an endoscope's view: RGB uint8 and z-depth float32, pixel-aligned.

Stands in for the paper's Blender set-up (Section 3.A): "a virtual camera with
additional point lights ... follow[s] the desired path", with texture, colour and
intensity varied per sample. Here VTK (off-screen, EGL/OSMesa, CPU) draws the
procedural tube of ``tube.py``:

- camera: pinhole ``K`` honoured exactly under ``core/camera.py``'s convention (pixel
  centres at integer coordinates) through an explicit OpenGL projection matrix;
- depth: the z-buffer linearized with the near/far planes, i.e. z-depth along the
  optical axis in scene units; pixels outside [near, far] are 0 (invalid);
- lights: one or two positional point lights rigidly beside the camera (the
  endoscope's light guides), inverse-square falloff (VTK attenuation (0, 0, 1));
- appearance: procedural mucosa texture with vessels (``make_texture``), wet
  specular highlights (Phong), per-sample tint, light colour and intensity.

One ``Renderer`` keeps one scene (one tube) and moves camera and lights per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geodepth_lite.core import camera as cam

NEAR, FAR = cam.DEPTH_RANGE  # valid rendered depth range (scene units): core/camera.py's, the paper's set
MATERIAL_KEYS = ("ambient", "diffuse", "specular", "specular_power")  # Phong material, part of a lighting family

# ----------------------------------------------------------------------------- fixed coefficients
# What the texture and lighting families (below) and the camera_path settings leave fixed.

# texture (``make_texture``): a second, finer vessel network imitating the capillaries
CAPILLARY_DENSITY_FACTOR = 2.5  # capillary density, x the family's vessel_density
CAPILLARY_WIDTH_FACTOR = 0.8  # capillary width, x the family's vessel_width
CAPILLARY_WEIGHT = 0.45  # capillary opacity relative to the large vessels
VESSEL_PROFILE_SCALE = 2.0  # a vessel is exp(-(n / (scale x width))^2) of band-limited noise n (unit std)

# lighting (``sample_lighting``, ``exposure_distance``): mucosa tint and auto-exposure
MUCOSA_TINT = 0.9  # mean per-sample tint of the mucosa (all channels), jittered by the family's tint_jitter
EXPOSURE_GRID_SPAN = (0.1, 0.9)  # auto-exposure rays: a grid over this span of the image (fractions of W, H)
EXPOSURE_GRID_SIZE = 5  # ... of this many rays per side
EXPOSURE_PERCENTILE = 20.0  # reference distance: this percentile of the wall distances along those rays
# untextured scenes (``Renderer.set_tube`` without texture/material): the warm_single family's material
DEFAULT_MATERIAL = {"ambient": 0.04, "diffuse": 0.9, "specular": 0.45, "specular_power": 35.0}
DEFAULT_MUCOSA_COLOR = (0.85, 0.45, 0.4)  # plain pink mucosa (RGB 0..1)

# camera poses (``sample_pose``): distances are fractions of the local lumen radius unless noted
OFF_AXIS_RANGE = (0.3, 0.6)  # wall and oblique views: camera offset from the centerline, x local minimum radius
CLOSEUP_WALL_MARGIN = 0.05  # closeups: the camera keeps at least this x R (preset radius) from the wall ...
CLOSEUP_BACKOFF, CLOSEUP_BACKOFF_STEPS = 0.7, 8  # ... moved closer by this factor, up to this many times
WALL_FACING_STANDOFF = 0.3  # ``wall_facing_pose``: camera beyond the centre, x the wall-to-centre distance


# ----------------------------------------------------------------------------- appearance

# Texture families: base mucosa colour, mottling, vessel colour/density/width (all 0..1 RGB).
TEXTURES: dict[str, dict] = {
    "pink":   {"base_color": [0.86, 0.45, 0.40], "mottle": 0.18, "mottle_scale": 0.08,
               "vessel_color": [0.55, 0.08, 0.10], "vessel_density": 6.0, "vessel_width": 0.05, "vessel_strength": 0.7,
               "size": 512},
    "red":    {"base_color": [0.80, 0.30, 0.25], "mottle": 0.22, "mottle_scale": 0.05,
               "vessel_color": [0.45, 0.05, 0.08], "vessel_density": 9.0, "vessel_width": 0.04, "vessel_strength": 0.6,
               "size": 512},
    "pale":   {"base_color": [0.90, 0.62, 0.55], "mottle": 0.12, "mottle_scale": 0.12,
               "vessel_color": [0.65, 0.20, 0.22], "vessel_density": 4.0, "vessel_width": 0.06, "vessel_strength": 0.8,
               "size": 512},
    "orange": {"base_color": [0.88, 0.52, 0.33], "mottle": 0.20, "mottle_scale": 0.06,
               "vessel_color": [0.60, 0.15, 0.10], "vessel_density": 7.0, "vessel_width": 0.035, "vessel_strength": 0.5,
               "size": 512},
    # held-out families (never in the training recipes), cf. ColonDepth's T1-T3 x L1-L3
    "T1":     {"base_color": [0.93, 0.70, 0.52], "mottle": 0.10, "mottle_scale": 0.15,
               "vessel_color": [0.70, 0.25, 0.20], "vessel_density": 3.0, "vessel_width": 0.07, "vessel_strength": 0.6,
               "size": 512},
    "T2":     {"base_color": [0.70, 0.22, 0.22], "mottle": 0.30, "mottle_scale": 0.04,
               "vessel_color": [0.35, 0.03, 0.06], "vessel_density": 12.0, "vessel_width": 0.03, "vessel_strength": 0.7,
               "size": 512},
    "T3":     {"base_color": [0.82, 0.50, 0.55], "mottle": 0.25, "mottle_scale": 0.10,
               "vessel_color": [0.40, 0.10, 0.30], "vessel_density": 5.0, "vessel_width": 0.05, "vessel_strength": 0.9,
               "size": 512},
    # held-out close-up family: yellowish duodenal mucosa with fine villous mottling, few vessels
    "T4":     {"base_color": [0.92, 0.72, 0.48], "mottle": 0.28, "mottle_scale": 0.03,
               "vessel_color": [0.72, 0.35, 0.22], "vessel_density": 4.0, "vessel_width": 0.04, "vessel_strength": 0.35,
               "size": 512},
}
# Lighting families: light guides (offset: fraction of the lumen radius), exposure range (intensity
# = exposure x d_ref^2, see ``exposure_distance``), light colour and jitter, mucosa tint jitter, material.
LIGHTINGS: dict[str, dict] = {
    "warm_single": {"n_lights": 1, "offset": 0.08, "intensity": [1.1, 1.9], "color": [1.0, 0.93, 0.82],
                    "color_jitter": 0.05, "tint_jitter": 0.08, "ambient": 0.04, "diffuse": 0.9, "specular": 0.45,
                    "specular_power": 35.0},
    "white_dual":  {"n_lights": 2, "offset": 0.10, "intensity": [1.0, 1.6], "color": [1.0, 1.0, 1.0],
                    "color_jitter": 0.04, "tint_jitter": 0.08, "ambient": 0.03, "diffuse": 0.85, "specular": 0.6,
                    "specular_power": 50.0},
    "dim_dual":    {"n_lights": 2, "offset": 0.06, "intensity": [0.6, 1.0], "color": [1.0, 0.96, 0.9],
                    "color_jitter": 0.06, "tint_jitter": 0.1, "ambient": 0.05, "diffuse": 0.9, "specular": 0.35,
                    "specular_power": 25.0},
    # held-out families
    "L1": {"n_lights": 1, "offset": 0.12, "intensity": [1.4, 2.2], "color": [1.0, 0.88, 0.70], "color_jitter": 0.05,
           "tint_jitter": 0.06, "ambient": 0.02, "diffuse": 0.95, "specular": 0.7, "specular_power": 60.0},
    "L2": {"n_lights": 2, "offset": 0.15, "intensity": [0.8, 1.3], "color": [0.85, 0.92, 1.0], "color_jitter": 0.05,
           "tint_jitter": 0.1, "ambient": 0.06, "diffuse": 0.8, "specular": 0.25, "specular_power": 15.0},
    "L3": {"n_lights": 1, "offset": 0.05, "intensity": [0.7, 1.1], "color": [1.0, 0.80, 0.60], "color_jitter": 0.08,
           "tint_jitter": 0.12, "ambient": 0.08, "diffuse": 0.85, "specular": 0.5, "specular_power": 40.0},
    "L4": {"n_lights": 2, "offset": 0.2, "intensity": [1.6, 2.6], "color": [1.0, 0.92, 0.72], "color_jitter": 0.04,
           "tint_jitter": 0.06, "ambient": 0.05, "diffuse": 0.9, "specular": 0.8, "specular_power": 80.0},
}


def _periodic_noise(rng: np.random.Generator, size: int, scale: float) -> np.ndarray:
    """Smooth periodic noise (size x size, zero mean, unit std): white noise low-passed in Fourier space.

    scale: correlation length as a fraction of the tile. Periodic in both axes, so the
    texture wraps seamlessly around the tube (theta) and along it (s).
    """
    fx = np.fft.fftfreq(size)[:, None]
    fy = np.fft.rfftfreq(size)[None, :]
    gain = np.exp(-(fx**2 + fy**2) * (np.pi * scale * size) ** 2 / 4)  # Gaussian low-pass, sigma ~ scale
    out = np.fft.irfft2(np.fft.rfft2(rng.standard_normal((size, size))) * gain, s=(size, size))
    out -= out.mean()
    return out / (out.std() + 1e-12)


def make_texture(params: dict, rng: np.random.Generator) -> np.ndarray:
    """Procedural mucosa texture (size x size x 3 uint8): mottled base colour and vessel network.

    Vessels are the zero level sets of band-limited noise (thin, branching, curvy lines),
    at two scales (large vessels and capillaries).
    """
    size = int(params["size"])
    base = np.asarray(params["base_color"], dtype=np.float64)
    mottle = _periodic_noise(rng, size, float(params["mottle_scale"]))
    img = base[None, None, :] * (1.0 + float(params["mottle"]) * mottle[..., None])
    density, width = float(params["vessel_density"]), float(params["vessel_width"])
    vessels = np.zeros((size, size))
    scales = ((density, width, 1.0),
              (CAPILLARY_DENSITY_FACTOR * density, CAPILLARY_WIDTH_FACTOR * width, CAPILLARY_WEIGHT))
    for level, (dens, wid, weight) in enumerate(scales):
        n = _periodic_noise(rng, size, 1.0 / dens)
        vessels = np.maximum(vessels, weight * np.exp(-((n / (wid * VESSEL_PROFILE_SCALE)) ** 2)))
    vessels *= float(params["vessel_strength"])
    img = img * (1.0 - vessels[..., None]) + np.asarray(params["vessel_color"])[None, None, :] * vessels[..., None]
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class Light:
    """A point light rigidly attached to the camera: position in camera coordinates (OpenCV frame)."""

    offset: tuple[float, float, float]
    color: tuple[float, float, float]
    intensity: float


def exposure_distance(tube, T_world_cam, K, width: int, height: int,
                      percentile: float = EXPOSURE_PERCENTILE, cast_rays=None) -> float:
    """Auto-exposure reference distance: a low percentile of the wall distances along a 5 x 5 grid of rays.

    An endoscope's processor adjusts gain to the scene; here the light intensity is
    scaled by this distance squared, so near-wall views are not blown out and views
    down the lumen are not black, while inverse-square falloff within a frame stays.
    cast_rays: ``(origin, unit directions) -> distances`` (default ``tube.cast_rays``, VTK's).
    """
    origin, directions = exposure_rays(T_world_cam, K, width, height)
    dist = (tube.cast_rays if cast_rays is None else cast_rays)(origin, directions)
    return exposure_from_distances(tube, dist, percentile)


def exposure_rays(T_world_cam, K, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The auto-exposure rays of a pose: (origin (3,), unit directions (25 x 3)), world frame."""
    K = np.asarray(K, dtype=np.float64)
    u = np.linspace(*EXPOSURE_GRID_SPAN, EXPOSURE_GRID_SIZE) * (width - 1)
    v = np.linspace(*EXPOSURE_GRID_SPAN, EXPOSURE_GRID_SIZE) * (height - 1)
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    T = np.asarray(T_world_cam, dtype=np.float64)
    return T[:3, 3], rays @ T[:3, :3].T


def exposure_from_distances(tube, dist: np.ndarray, percentile: float = EXPOSURE_PERCENTILE) -> float:
    """``exposure_distance`` from the wall distances along its rays (inf: none met; no finite one: the radius)."""
    dist = dist[np.isfinite(dist)]
    return float(np.percentile(dist, percentile)) if len(dist) else float(tube.preset["radius"])


def sample_lighting(params: dict, rng: np.random.Generator, radius: float,
                    distance: float | None = None) -> tuple[list[Light], tuple[float, float, float]]:
    """Per-sample lights (1 or 2 beside the lens) and a per-sample mucosa tint from a lighting family.

    radius: lumen radius (scales the light-guide offset); distance: auto-exposure reference
    (``exposure_distance``; default: the radius). Total intensity = exposure x distance^2.
    """
    n = int(params["n_lights"])
    off = float(params["offset"]) * radius
    lo, hi = params["intensity"]
    distance = radius if distance is None else distance
    intensity = float(rng.uniform(lo, hi)) * distance**2  # inverse-square falloff: expose for the reference distance
    base = np.asarray(params["color"], dtype=np.float64)
    lights = []
    angle = rng.uniform(0, 2 * np.pi)
    for k in range(n):
        a = angle + np.pi * k
        color = np.clip(base * (1.0 + float(params["color_jitter"]) * rng.uniform(-1, 1, 3)), 0.0, 1.0)
        lights.append(Light((off * math.cos(a), off * math.sin(a), 0.0), tuple(float(c) for c in color), intensity / n))
    tint = np.clip(MUCOSA_TINT * (1.0 + float(params["tint_jitter"]) * rng.uniform(-1, 1, 3)), 0.0, 1.0)
    return lights, tuple(float(t) for t in tint)


# ----------------------------------------------------------------------------- camera path


def look_pose(position, forward, up_hint) -> np.ndarray:
    """T_world_cam (4x4) for a camera at ``position`` looking along ``forward`` (OpenCV: y down)."""
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(-np.asarray(up_hint, dtype=np.float64), z)  # y down = -up
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, position
    return T


def _min_radius(tube, s: float, half_window: float) -> float:
    ss = np.linspace(max(s - half_window, 0.0), min(s + half_window, tube.length), 9)
    th = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    return float(tube.radius(ss[:, None], th[None, :]).min())


VIEW_KINDS = ("lumen", "wall", "oblique", "closeup", "papilla")  # camera_path.views: share of each kind


def choose_view(shares: dict, u: float) -> str:
    """The view kind whose cumulative share (normalized, in VIEW_KINDS order) first exceeds ``u`` in [0, 1)."""
    total = sum(float(shares.get(k, 0.0)) for k in VIEW_KINDS)
    acc = 0.0
    for kind in VIEW_KINDS:
        acc += float(shares.get(kind, 0.0)) / total
        if u < acc:
            return kind
    return [k for k in VIEW_KINDS if shares.get(k, 0.0) > 0][-1]


def inside_tube(tube, point, margin: float = 0.0) -> bool:
    """Whether ``point`` lies in the lumen at least ``margin`` from the wall (nearest centerline ring)."""
    point = np.asarray(point, dtype=np.float64)
    s0 = float(tube.s_grid[np.argmin(np.linalg.norm(tube.points - point, axis=1))])
    t, n, b = tube.frame(s0)
    v = point - tube.centerline(s0)
    v = v - (v @ t) * t
    theta = math.atan2(float(v @ b), float(v @ n)) % (2 * np.pi)
    return float(np.linalg.norm(v)) < float(tube.radius(s0, theta)) - margin


def wall_normal(tube, s: float, theta: float, h: float = 1e-3) -> np.ndarray:
    """Unit surface normal of the wall at (s, theta), pointing into the lumen (central differences)."""
    d_s = tube.wall_point(s + h, theta) - tube.wall_point(s - h, theta)
    d_t = tube.wall_point(s, theta + h) - tube.wall_point(s, theta - h)
    m = np.cross(d_s, d_t)
    m /= np.linalg.norm(m)
    return m if m @ (tube.centerline(s) - tube.wall_point(s, theta)) > 0 else -m


def _facing_pose(tube, rng, path: dict, s: float, theta: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Close-up facing the wall point (s, theta): position, forward, tilt from the normal (deg), distance.

    The camera sits at ``closeup_distance`` x local radius from the point, along the wall's
    inward normal tilted by up to ``closeup_tilt_deg``; moved closer (x CLOSEUP_BACKOFF, up to
    CLOSEUP_BACKOFF_STEPS times) if that position would be outside the lumen (behind a fold).
    """
    target = tube.wall_point(s, theta)
    m = wall_normal(tube, s, theta)
    e1 = np.cross(m, tube.frame(s)[0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    tilt = math.radians(rng.uniform(0.0, float(path["closeup_tilt_deg"])))
    az = rng.uniform(0, 2 * np.pi)
    v = math.cos(tilt) * m + math.sin(tilt) * (math.cos(az) * e1 + math.sin(az) * e2)
    dist = float(rng.uniform(*path["closeup_distance"])) * float(tube.radius(s, theta))
    margin = CLOSEUP_WALL_MARGIN * float(tube.preset["radius"])
    for _ in range(CLOSEUP_BACKOFF_STEPS):
        if inside_tube(tube, target + dist * v, margin):
            break
        dist *= CLOSEUP_BACKOFF
    return target + dist * v, -v, math.degrees(tilt), dist


def sample_pose(tube, rng: np.random.Generator, path: dict) -> tuple[np.ndarray, dict]:
    """One endoscope pose of a view kind drawn from ``path["views"]`` (shares of VIEW_KINDS).

    path: {"mode": "random" | "axis", "s_range": [lo, hi] (fractions of the length),
    "views": {kind: share}, "jitter_pos", "jitter_angle_deg" (lumen views: offset from the
    centerline as a fraction of the local minimum radius, std of the tilt), "wall_angle_deg"
    (wall views: tilt range from the axis, camera 0.3-0.6 radius off the centre towards that
    wall), "oblique_angle_deg" (oblique views: from near one wall across the lumen at that
    tilt, so folds are seen side-on), "closeup_distance" (closeup and papilla views: fraction of
    the local radius between camera and the wall point faced), "closeup_tilt_deg" (their max
    tilt from the wall normal)}. A papilla view faces one of the tube's papillae (a closeup
    when it has none). Returns (T_world_cam, info) with s, the view kind, tilt and distance.
    """
    L, R = tube.length, float(tube.preset["radius"])
    lo, hi = path["s_range"]
    s = float(rng.uniform(lo, hi) * L)
    t, n, b = tube.frame(s)
    c = tube.centerline(s)
    if path["mode"] == "axis":
        return _axis_pose(c, t, n, b), {"s": s, "view": "axis", "tilt_deg": 0.0, "distance": None}
    r_min = _min_radius(tube, s, R)
    roll = rng.uniform(0, 2 * np.pi)
    view = choose_view(path["views"], rng.uniform())
    phi = rng.uniform(0, 2 * np.pi)
    radial = math.cos(phi) * n + math.sin(phi) * b
    distance = None
    if view == "wall":
        rho = rng.uniform(*OFF_AXIS_RANGE) * r_min
        tilt = math.radians(rng.uniform(*path["wall_angle_deg"]))
        forward = math.cos(tilt) * t + math.sin(tilt) * radial
        position = c + rho * radial
    elif view == "oblique":
        rho = rng.uniform(*OFF_AXIS_RANGE) * r_min
        tilt = math.radians(rng.uniform(*path["oblique_angle_deg"]))
        forward = math.cos(tilt) * t + math.sin(tilt) * radial  # across the lumen to the far wall
        position = c - rho * radial
    elif view in ("closeup", "papilla"):
        papillae = tube.features.papillae
        if view == "papilla" and papillae:
            s, phi, _size = papillae[int(rng.integers(len(papillae)))]
        position, forward, tilt_deg, distance = _facing_pose(tube, rng, path, s, phi)
        tilt = math.radians(tilt_deg)
        t = tube.frame(s)[0]
        side = np.cross(forward, t)
        side /= np.linalg.norm(side)
        up = math.cos(roll) * t + math.sin(roll) * side
        return look_pose(position, forward, up), {"s": float(s), "view": view, "tilt_deg": math.degrees(tilt),
                                                  "distance": distance}
    else:
        rho = math.sqrt(rng.uniform()) * float(path["jitter_pos"]) * r_min
        position = c + rho * radial
        tilt = abs(rng.normal(0.0, math.radians(float(path["jitter_angle_deg"]))))
        az = rng.uniform(0, 2 * np.pi)
        forward = math.cos(tilt) * t + math.sin(tilt) * (math.cos(az) * n + math.sin(az) * b)
    up = math.cos(roll) * n + math.sin(roll) * b
    up = up - (up @ forward) * forward
    return look_pose(position, forward, up), {"s": s, "view": view, "tilt_deg": math.degrees(tilt),
                                              "distance": distance}


def _axis_pose(c, t, n, b) -> np.ndarray:
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = n, b, t, c
    return T


def wall_facing_pose(tube, s: float, theta: float, standoff: float = WALL_FACING_STANDOFF) -> np.ndarray:
    """T_world_cam looking straight at the wall point (s, theta) from across the lumen.

    The camera sits on the line from that wall point through the centerline, ``standoff``
    x (wall-to-centre distance) beyond the centre; the image's up is the tube's direction.
    """
    target = tube.wall_point(s, theta)
    centre = tube.centerline(s)
    position = centre - standoff * (target - centre)
    return look_pose(position, target - position, tube.frame(s)[0])


def sequence_poses(tube, n_frames: int, s_start: float, step: float, offset=(0.0, 0.0)) -> list[np.ndarray]:
    """Consecutive poses down the lumen: s = s_start + k * step, on a line parallel to the centerline.

    offset: (along N, along B) in scene units. Frames follow the parallel-transport frame
    (x = N, y = B, z = T), so there is no roll between frames; for visual odometry tests.
    """
    poses = []
    for k in range(int(n_frames)):
        s = s_start + k * step
        t, nn, bb = tube.frame(s)
        poses.append(_axis_pose(tube.centerline(s) + offset[0] * nn + offset[1] * bb, t, nn, bb))
    return poses


# ----------------------------------------------------------------------------- the renderer


def projection_matrix(K, width: int, height: int, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """OpenGL projection for pinhole K with pixel centres at integer (u, v) (core/camera.py's convention).

    Eye coordinates are VTK's (x right, y up, looking down -z). Column u of the image
    covers NDC x in [2u/W - 1, 2(u+1)/W - 1]; OpenGL rows count from the bottom, so
    image row v is OpenGL row H - 1 - v (``Renderer`` flips the read-back).
    """
    fx, fy, cx, cy = float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2])
    W, H = float(width), float(height)
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / W
    P[0, 2] = -(2.0 * cx + 1.0 - W) / W
    P[1, 1] = 2.0 * fy / H
    P[1, 2] = -(H - 2.0 * cy - 1.0) / H
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = -1.0
    return P


class Renderer:
    """Off-screen VTK renderer for one tube at a time; ``render(T_world_cam, lights)`` per frame.

    width, height: image size; K: 3x3 intrinsics in pixels (any principal point);
    fxaa: anti-alias the RGB image (a post-process: the depth buffer is untouched).
    """

    def __init__(self, width: int, height: int, K=None, near: float = NEAR, far: float = FAR, fxaa: bool = False):
        import pyvista as pv  # VTK: heavy, needed only to build or render meshes
        import vtk  # VTK: heavy, needed only to render

        vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
        self.width, self.height = int(width), int(height)
        self.K = np.asarray(cam.intrinsics(self.width, self.height) if K is None else K, dtype=np.float64)
        self.near, self.far = float(near), float(far)
        self.plotter = pv.Plotter(off_screen=True, window_size=(self.width, self.height), lighting="none")
        self.ren_win = self.plotter.ren_win
        self.ren_win.SetMultiSamples(0)
        self.renderer = self.plotter.renderer
        self.renderer.SetBackground(0.0, 0.0, 0.0)
        if fxaa:
            self.renderer.UseFXAAOn()
        self.camera = self.renderer.GetActiveCamera()
        m = vtk.vtkMatrix4x4()
        P = projection_matrix(self.K, self.width, self.height, self.near, self.far)
        for i in range(4):
            for j in range(4):
                m.SetElement(i, j, P[i, j])
        self.camera.SetExplicitProjectionTransformMatrix(m)
        self.camera.UseExplicitProjectionTransformMatrixOn()
        self.camera.SetClippingRange(self.near, self.far)
        self._lights: list = []
        self.actor = None
        self._rgb = vtk.vtkUnsignedCharArray()
        self._z = vtk.vtkFloatArray()
        self.tube = None

    # scene -------------------------------------------------------------------
    def set_tube(self, tube, texture: np.ndarray | None = None, material: dict | None = None) -> None:
        """Show ``tube`` (a tube.TubeMesh) with an RGB texture (h x w x 3 uint8, periodic) and Phong material."""
        import pyvista as pv  # VTK: heavy, needed only to build or render meshes

        if self.actor is not None:
            self.plotter.remove_actor(self.actor, render=False)
        mat = dict(DEFAULT_MATERIAL)
        mat.update(material or {})
        kwargs = dict(smooth_shading=True, ambient=mat["ambient"], diffuse=mat["diffuse"], specular=mat["specular"],
                      specular_power=mat["specular_power"], scalars=None, render=False, reset_camera=False)
        if texture is not None:
            tex = pv.Texture(np.ascontiguousarray(texture))
            tex.repeat = True
            tex.interpolate = True
            kwargs["texture"] = tex
        else:
            kwargs["color"] = DEFAULT_MUCOSA_COLOR
        self.actor = self.plotter.add_mesh(tube.mesh, **kwargs)
        self.actor.GetProperty().SetSpecularColor(1.0, 1.0, 1.0)
        self.tube = tube

    def set_material(self, material: dict) -> None:
        """Phong coefficients {ambient, diffuse, specular, specular_power} of the mucosa (per frame)."""
        prop = self.actor.GetProperty()
        prop.SetAmbient(float(material["ambient"]))
        prop.SetDiffuse(float(material["diffuse"]))
        prop.SetSpecular(float(material["specular"]))
        prop.SetSpecularPower(float(material["specular_power"]))

    def set_tint(self, tint) -> None:
        """Per-sample colour/intensity variation of the mucosa (multiplies the texture)."""
        self.actor.GetProperty().SetColor(*[float(min(max(t, 0.0), 1.0)) for t in tint])

    def _set_lights(self, T_world_cam: np.ndarray, lights: list[Light]) -> None:
        import vtk  # VTK: heavy, needed only to render

        while len(self._lights) < len(lights):
            light = vtk.vtkLight()
            light.SetLightTypeToSceneLight()
            light.SetPositional(True)
            light.SetConeAngle(180.0)  # >= 90 degrees: a point light, not a spot
            light.SetAttenuationValues(0.0, 0.0, 1.0)  # inverse-square falloff
            self.renderer.AddLight(light)
            self._lights.append(light)
        forward = T_world_cam[:3, 2]
        for k, light in enumerate(self._lights):
            if k >= len(lights):
                light.SwitchOff()
                continue
            spec = lights[k]
            pos = T_world_cam[:3, :3] @ np.asarray(spec.offset, dtype=np.float64) + T_world_cam[:3, 3]
            light.SwitchOn()
            light.SetPosition(*pos)
            light.SetFocalPoint(*(pos + forward))
            light.SetColor(*spec.color)
            light.SetIntensity(float(spec.intensity))

    def _set_camera(self, T_world_cam: np.ndarray) -> None:
        T = np.asarray(T_world_cam, dtype=np.float64)
        pos, z, y = T[:3, 3], T[:3, 2], T[:3, 1]
        self.camera.SetPosition(*pos)
        self.camera.SetFocalPoint(*(pos + z))
        self.camera.SetViewUp(*(-y))
        self.camera.SetClippingRange(self.near, self.far)

    # frame -------------------------------------------------------------------
    def render(self, T_world_cam: np.ndarray, lights: list[Light] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render one frame: (rgb H x W x 3 uint8, depth H x W float32 z-depth; 0 = no surface in [near, far])."""
        from vtkmodules.util.numpy_support import vtk_to_numpy  # VTK: heavy, needed only to render

        T = np.asarray(T_world_cam, dtype=np.float64)
        if lights is None:
            lights = [Light((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1.0)]
        self._set_camera(T)
        self._set_lights(T, lights)
        self.ren_win.Render()
        W, H = self.width, self.height
        self.ren_win.GetPixelData(0, 0, W - 1, H - 1, 0, self._rgb, 0)
        rgb = vtk_to_numpy(self._rgb).reshape(H, W, -1)[::-1, :, :3].copy()
        self.ren_win.GetZbufferData(0, 0, W - 1, H - 1, self._z)
        zb = vtk_to_numpy(self._z).reshape(H, W)[::-1].astype(np.float64)
        return rgb, self.depth_from_zbuffer(zb)

    def depth_from_zbuffer(self, zb: np.ndarray) -> np.ndarray:
        """Linearize window-space depth (0..1) to z-depth: z = 2 n f / ((f + n) - (2 zb - 1)(f - n))."""
        n, f = self.near, self.far
        z = 2.0 * n * f / ((f + n) - (2.0 * zb - 1.0) * (f - n))
        valid = (zb < 1.0) & (z >= n) & (z <= f)
        return np.where(valid, z, 0.0).astype(np.float32)

    def close(self) -> None:
        self.plotter.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

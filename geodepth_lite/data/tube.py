"""Procedural digestive-tract tube: centerline, radius field, local structures, mesh.

The paper (Section 3.A) renders its "Scenario dataset" from CT meshes of the
digestive tract, which were never released. This module stands in for them: a
tube swept along a smooth 3D centerline with rotation-minimizing
(parallel-transport) frames, whose wall radius ``r(s, theta)`` carries the
organ's folds (colon: semilunar haustral folds between three teniae; small
intestine: dense circular folds; stomach: longitudinal rugae) and the local
structures of the paper's shape-index discussion (Section 3.C, Fig. 5): polyps
(caps), diverticula (cups) and ridges, plus papilla-like mounds (a cap with a
small central pit, as the duodenal papilla seen close up).

Coordinates: ``s`` is arc length along the centerline (scene units), ``theta``
the angle around it measured from the frame's normal ``N`` towards ``B``. A wall
point is ``c(s) + r(s, theta) (cos(theta) N(s) + sin(theta) B(s))``.

Public API: ``build_tube(preset, seed, resolution) -> TubeMesh`` with ``.arrays`` (the mesh as
numpy arrays) and ``.mesh`` (the same as a pyvista PolyData, inward normals, texture coordinates), ``.centerline(s)``,
``.frame(s)``, ``.radius(s, theta)`` and ``.wall_point(s, theta)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Organ presets (scene units). Every key is a manifest parameter (manifest.py validates them).
# fold_kind: "haustral" (colon), "circular" (small intestine), "longitudinal" (stomach), "none".
PRESETS: dict[str, dict] = {
    "colon": {
        "radius": 2.0,             # mean lumen radius
        "length": 40.0,            # centerline length
        "radius_var": 0.12,        # slow relative variation of the radius along s
        "bend": 3.0,               # amplitude of the centerline's sideways bends
        "bend_wavelength": 30.0,   # wavelength of those bends
        "fold_kind": "haustral",   # semilunar folds between three teniae
        "fold_spacing": 2.2,       # distance between folds along s
        "fold_depth": 0.28,        # fold height, fraction of the radius
        "fold_width": 0.22,        # fold half-width along s, fraction of the radius
        "teniae": 3,               # longitudinal muscle bands (colon)
        "polyps": [0, 3],          # [min, max] count of polyps (caps)
        "polyp_size": [0.25, 0.6], # [min, max] polyp radius, fraction of the lumen radius
        "diverticula": [0, 2],     # [min, max] count of diverticula (cups)
        "diverticulum_size": [0.25, 0.5],
        "ridges": [0, 3],          # [min, max] count of extra ridge-shaped folds
        "ridge_size": [0.8, 2.0],  # [min, max] ridge length, fraction of the lumen radius
        "papillae": [0, 0],         # [min, max] count of papilla-like mounds (a cap with a central pit)
        "papilla_size": [0.3, 0.5], # [min, max] mound radius, fraction of the lumen radius
    },
    "small_intestine": {
        "radius": 1.0,
        "length": 30.0,
        "radius_var": 0.08,
        "bend": 2.5,
        "bend_wavelength": 15.0,
        "fold_kind": "circular",
        "fold_spacing": 0.55,
        "fold_depth": 0.22,
        "fold_width": 0.12,
        "teniae": 0,
        "polyps": [0, 2],
        "polyp_size": [0.2, 0.4],
        "diverticula": [0, 1],
        "diverticulum_size": [0.2, 0.4],
        "ridges": [0, 2],
        "ridge_size": [0.6, 1.5],
        "papillae": [0, 1],
        "papilla_size": [0.3, 0.5],
    },
    "stomach": {
        "radius": 4.0,
        "length": 40.0,
        "radius_var": 0.2,
        "bend": 6.0,
        "bend_wavelength": 50.0,
        "fold_kind": "longitudinal",
        "fold_spacing": 0.55,      # for rugae: angular spacing as arc length / radius
        "fold_depth": 0.08,
        "fold_width": 0.06,
        "teniae": 0,
        "polyps": [0, 3],
        "polyp_size": [0.1, 0.25],
        "diverticula": [0, 1],
        "diverticulum_size": [0.1, 0.2],
        "ridges": [1, 4],
        "ridge_size": [0.5, 1.5],
        "papillae": [0, 0],
        "papilla_size": [0.1, 0.2],
    },
    "cylinder": {  # the analytic check: straight, constant radius, nothing on the wall
        "radius": 1.0,
        "length": 60.0,
        "radius_var": 0.0,
        "bend": 0.0,
        "bend_wavelength": 30.0,
        "fold_kind": "none",
        "fold_spacing": 1.0,
        "fold_depth": 0.0,
        "fold_width": 0.1,
        "teniae": 0,
        "polyps": [0, 0],
        "polyp_size": [0.2, 0.3],
        "diverticula": [0, 0],
        "diverticulum_size": [0.2, 0.3],
        "ridges": [0, 0],
        "ridge_size": [0.5, 1.0],
        "papillae": [0, 0],
        "papilla_size": [0.2, 0.3],
    },
}
FOLD_KINDS = ("haustral", "circular", "longitudinal", "none")

# ----------------------------------------------------------------------------- shape coefficients
# The fixed coefficients of every tube (PRESETS holds what differs between organs). Lengths are
# fractions of the lumen radius R, of the tube length L or of a preset value, as noted; angles in
# radians; a (lo, hi) pair bounds a uniform draw from the tube's random stream.

TUBE_RNG_TAG = 0x7B  # second word of the tube's SeedSequence([seed, tag]): its own random stream

# centerline: per side axis, sinusoidal bends (frequency x 1 / bend_wavelength, amplitude x bend)
CENTERLINE_HARMONICS = ((1.0, 1.0), (1.7, 0.35))  # (frequency, weight): a main bend and a smaller, faster one
CENTERLINE_AMPLITUDE_RANGE = (0.5, 1.0)  # random scale of each bend's amplitude
CENTERLINE_OVERSHOOT = 1.3  # the curve is sampled over 1.3 L of its parameter so its arc length covers L

# base radius: slow variation along s (relative amplitude radius_var), two sines; and its floor
RADIUS_WAVE_AMPLITUDE = (0.6, 0.4)  # weights of the two sines
RADIUS_WAVE_PERIOD = (0.45, 0.17)  # their periods, x L
MIN_RADIUS_FRACTION = 0.3  # the wall radius is clamped to at least this x R: the lumen never pinches shut

# colon: semilunar haustral folds in the sectors between the teniae coli, haustra bulging between folds
HAUSTRAL_FOLD_STRENGTH_RANGE = (0.7, 1.15)  # height of each fold, x fold_depth
HAUSTRAL_SPACING_JITTER = (0.8, 1.2)  # distance to the next fold, x fold_spacing
FOLD_CRESCENT_EXPONENT = 0.7  # fold height across a sector ~ sin(pi u)^p: highest mid-sector, 0 at the teniae
HAUSTRUM_BULGE = 0.35  # outward bulge of the haustra between folds, x fold depth
TENIA_WIDTH = 0.08  # angular width of a tenia band (radians, Gaussian)
TENIA_DEPTH = 0.08  # inward offset of the teniae (flat bands slightly inside), x fold depth

# small intestine: circular folds (plicae circulares), often not full circles
CIRCULAR_FOLD_STRENGTH_RANGE = (0.6, 1.2)  # height of each fold, x fold_depth
CIRCULAR_SPACING_JITTER = (0.75, 1.25)  # distance to the next fold, x fold_spacing
CIRCULAR_FOLD_AROUND = (0.55, 0.45)  # (a, b): height around the lumen ~ a + b cos(theta - fold's theta)

# stomach: longitudinal rugae, wandering sideways and varying in height along s
MIN_RUGAE = 3  # fewest rugae around the lumen
RUGA_ANGLE_JITTER = (-0.25, 0.25)  # offset of each ruga from even spacing, x the angular spacing
RUGA_WANDER_RANGE = (0.1, 0.35)  # sideways wander amplitude (radians)
RUGA_STRENGTH_RANGE = (0.6, 1.3)  # height of each ruga, x fold_depth
RUGA_WANDER_PERIOD = 0.3  # period of the wander along s, x L
RUGA_HEIGHT_MODULATION = (0.6, 0.4)  # (a, b): height along s ~ a + b sin(...)
RUGA_HEIGHT_PERIOD = 0.21  # period of that height modulation, x L
RUGA_PHASE_RATIO = 1.3  # phase of the height modulation, x the wander's phase

# local structures of the shape-index discussion (Sec. 3.C, Fig. 5): caps, cups, ridges, papillae.
# Polyps, diverticula and papillae are domes of height h x size: h * size * max(1 - d^2, 0)^p.
FEATURE_MARGIN = 0.05  # local structures keep this x L away from both ends of the tube
DOME_PROFILE_EXPONENT = 1.5  # p above: a smooth dome
POLYP_HEIGHT = 0.8  # polyps (caps): inward dome height, x polyp radius
DIVERTICULUM_DEPTH = 0.9  # diverticula (cups): outward pocket depth, x diverticulum radius
RIDGE_HEIGHT_RANGE = (0.1, 0.2)  # ridges (short folds at any orientation): height, x R
RIDGE_WIDTH = 0.12  # across-ridge width of the sech^2 profile, x R
# papilla shape (fractions of the mound radius): dome height, pit depth and pit radius
PAPILLA_HEIGHT, PAPILLA_PIT_DEPTH, PAPILLA_PIT_RADIUS = 0.6, 0.2, 0.3

# Mesh resolution: rings along s per unit radius, and points around each ring.
DEFAULT_RESOLUTION = {"n_theta": 96, "ring_step": 0.07}  # ring_step: ring spacing, fraction of radius


# ----------------------------------------------------------------------------- centerline


def parallel_transport_frames(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-minimizing frames (T, N, B) along a polyline (n x 3), double-reflection method.

    Wang et al. (2008), "Computation of rotation minimizing frames": N is carried
    from point to point by two reflections, so the frame never spins about the
    tangent (no twist). Returns three n x 3 arrays of unit vectors.
    """
    tangents = np.gradient(points, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    t0 = tangents[0]
    helper = np.array([1.0, 0.0, 0.0]) if abs(t0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = np.cross(t0, helper)
    n /= np.linalg.norm(n)
    normals = np.empty_like(points)
    normals[0] = n
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        r_l = n - (2.0 / c1) * (v1 @ n) * v1
        t_l = tangents[i] - (2.0 / c1) * (v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - t_l
        c2 = v2 @ v2
        n = r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-30 else r_l
        n -= (n @ tangents[i + 1]) * tangents[i + 1]
        n /= np.linalg.norm(n)
        normals[i + 1] = n
    binormals = np.cross(tangents, normals)
    return tangents, normals, binormals


def _centerline_points(t: np.ndarray, preset: dict, rng: np.random.Generator) -> np.ndarray:
    """A smooth 3D curve: the z axis plus two bending sinusoids per side axis (t in scene units)."""
    pts = np.zeros((len(t), 3))
    pts[:, 2] = t
    bend, lam = float(preset["bend"]), float(preset["bend_wavelength"])
    for axis in (0, 1):
        for harmonic, weight in CENTERLINE_HARMONICS:
            phase = rng.uniform(0, 2 * np.pi)
            amp = bend * weight * rng.uniform(*CENTERLINE_AMPLITUDE_RANGE)
            pts[:, axis] += amp * (np.sin(2 * np.pi * harmonic * t / lam + phase) - np.sin(phase))
    return pts


# ----------------------------------------------------------------------------- radius field


def _sech2(x):
    return 1.0 / np.cosh(np.clip(x, -30, 30)) ** 2


def _wrap(a):
    """Angle difference wrapped to (-pi, pi]."""
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass
class WallFeatures:
    """Everything random about one tube's wall, drawn once from the seed (all in scene units / radians)."""

    base_phases: np.ndarray
    folds: list = field(default_factory=list)        # haustral/circular: (s, theta_centre, sector, strength)
    rugae: list = field(default_factory=list)        # longitudinal: (theta0, wander_amp, wander_phase, strength)
    tenia_offset: float = 0.0
    polyps: list = field(default_factory=list)       # (s, theta, size)
    diverticula: list = field(default_factory=list)  # (s, theta, size)
    ridges: list = field(default_factory=list)       # (s, theta, length, angle, height)
    papillae: list = field(default_factory=list)     # (s, theta, size): duodenal papilla-like mounds


def _draw_features(preset: dict, rng: np.random.Generator) -> WallFeatures:
    R, L = float(preset["radius"]), float(preset["length"])
    feats = WallFeatures(base_phases=rng.uniform(0, 2 * np.pi, size=3))
    kind, spacing = preset["fold_kind"], float(preset["fold_spacing"])
    feats.tenia_offset = float(rng.uniform(0, 2 * np.pi))
    if kind == "haustral":
        n_sectors = max(int(preset["teniae"]), 1)
        for sector in range(n_sectors):
            s = rng.uniform(0, spacing)  # folds of neighbouring sectors are staggered
            while s < L:
                feats.folds.append((s, 0.0, sector, rng.uniform(*HAUSTRAL_FOLD_STRENGTH_RANGE)))
                s += spacing * rng.uniform(*HAUSTRAL_SPACING_JITTER)
    elif kind == "circular":
        s = rng.uniform(0, spacing)
        while s < L:
            feats.folds.append((s, rng.uniform(0, 2 * np.pi), -1, rng.uniform(*CIRCULAR_FOLD_STRENGTH_RANGE)))
            s += spacing * rng.uniform(*CIRCULAR_SPACING_JITTER)
    elif kind == "longitudinal":
        n_rugae = max(MIN_RUGAE, int(round(2 * np.pi / spacing)))
        for j in range(n_rugae):
            theta0 = 2 * np.pi * (j + rng.uniform(*RUGA_ANGLE_JITTER)) / n_rugae
            feats.rugae.append((theta0, rng.uniform(*RUGA_WANDER_RANGE), rng.uniform(0, 2 * np.pi),
                                rng.uniform(*RUGA_STRENGTH_RANGE)))
    margin = FEATURE_MARGIN * L

    def place(count_range, size_range):
        lo, hi = (int(v) for v in count_range)
        out = []
        for _ in range(int(rng.integers(lo, hi + 1))):
            out.append((rng.uniform(margin, L - margin), rng.uniform(0, 2 * np.pi), R * rng.uniform(*size_range)))
        return out

    feats.polyps = place(preset["polyps"], preset["polyp_size"])
    feats.diverticula = place(preset["diverticula"], preset["diverticulum_size"])
    for s, theta, length in place(preset["ridges"], preset["ridge_size"]):
        feats.ridges.append((s, theta, length, rng.uniform(0, np.pi), rng.uniform(*RIDGE_HEIGHT_RANGE) * R))
    feats.papillae = place(preset["papillae"], preset["papilla_size"])  # drawn last: older draws unchanged
    return feats


def radius_field(s: np.ndarray, theta: np.ndarray, preset: dict, feats: WallFeatures) -> np.ndarray:
    """Wall radius r(s, theta) (broadcasting arrays, scene units): base, organ folds, local structures.

    Folds and ridges are ridge-shaped (sech^2 profiles, pointing into the lumen);
    polyps are caps (inward bumps, positive shape index seen from the lumen);
    diverticula are cups (outward pockets). Clamped to at least MIN_RADIUS_FRACTION x radius.
    """
    s, theta = np.broadcast_arrays(np.asarray(s, dtype=np.float64), np.asarray(theta, dtype=np.float64))
    R, L = float(preset["radius"]), float(preset["length"])
    p = feats.base_phases
    var = float(preset["radius_var"])
    r = R * (1.0 + var * (RADIUS_WAVE_AMPLITUDE[0] * np.sin(2 * np.pi * s / (RADIUS_WAVE_PERIOD[0] * L) + p[0])
                          + RADIUS_WAVE_AMPLITUDE[1] * np.sin(2 * np.pi * s / (RADIUS_WAVE_PERIOD[1] * L) + p[1])))
    depth, width = float(preset["fold_depth"]) * R, float(preset["fold_width"]) * R
    kind = preset["fold_kind"]
    if kind == "haustral" and depth > 0:
        r = _haustral_folds(r, s, theta, int(preset["teniae"]), feats, depth, width)
    elif kind == "circular" and depth > 0:
        r = _circular_folds(r, s, theta, feats, depth, width)
    elif kind == "longitudinal" and depth > 0:
        r = _longitudinal_folds(r, s, theta, R, L, feats, depth, width)
    r = _local_structures(r, s, theta, R, feats)
    return np.maximum(r, MIN_RADIUS_FRACTION * R)


def _haustral_folds(r, s, theta, teniae: int, feats: WallFeatures, depth: float, width: float) -> np.ndarray:
    """The colon's semilunar folds between the teniae, the haustra bulging between folds, the teniae."""
    n_sec = max(teniae, 1)
    sector_w = 2 * np.pi / n_sec
    local = (theta - feats.tenia_offset) % (2 * np.pi)
    sector = np.minimum((local // sector_w).astype(int), n_sec - 1)
    u = (local - sector * sector_w) / sector_w  # 0..1 across the sector between two teniae
    crescent = np.sin(np.pi * u) ** FOLD_CRESCENT_EXPONENT  # semilunar: highest mid-sector, vanishing at the teniae
    fold = np.zeros_like(r)
    for k in range(n_sec):  # per sector only the two nearest folds matter (spacing >> width)
        fk = sorted((fs, st) for fs, _, fsec, st in feats.folds if fsec == k)
        if not fk:
            continue
        pos, strength = np.array([f[0] for f in fk]), np.array([f[1] for f in fk])
        j = np.clip(np.searchsorted(pos, s), 1, len(pos)) - 1
        near = np.maximum(strength[j] * _sech2((s - pos[j]) / width),
                          strength[np.minimum(j + 1, len(pos) - 1)]
                          * _sech2((s - pos[np.minimum(j + 1, len(pos) - 1)]) / width))
        fold = np.where(sector == k, near, fold)
    # haustra bulge outwards between folds; teniae are flat bands slightly inside
    r = r - depth * crescent * fold + HAUSTRUM_BULGE * depth * crescent * (1.0 - fold)
    tenia = (np.exp(-((u * sector_w) ** 2) / (TENIA_WIDTH**2))
             + np.exp(-(((1 - u) * sector_w) ** 2) / (TENIA_WIDTH**2)))
    return r - TENIA_DEPTH * depth * tenia


def _circular_folds(r, s, theta, feats: WallFeatures, depth: float, width: float) -> np.ndarray:
    """The small intestine's plicae: ring-shaped folds, often not full circles."""
    fold = np.zeros_like(r)
    for fs, ftheta, _, strength in feats.folds:
        around = CIRCULAR_FOLD_AROUND[0] + CIRCULAR_FOLD_AROUND[1] * np.cos(theta - ftheta)
        fold = np.maximum(fold, strength * around * _sech2((s - fs) / width))
    return r - depth * fold


def _longitudinal_folds(r, s, theta, R: float, L: float, feats: WallFeatures, depth: float,
                        width: float) -> np.ndarray:
    """The stomach's rugae: folds along the axis that wander around it and vary in height."""
    fold = np.zeros_like(r)
    for theta0, wander, phase, strength in feats.rugae:
        centre = theta0 + wander * np.sin(2 * np.pi * s / (RUGA_WANDER_PERIOD * L) + phase)
        along = RUGA_HEIGHT_MODULATION[0] + RUGA_HEIGHT_MODULATION[1] * np.sin(
            2 * np.pi * s / (RUGA_HEIGHT_PERIOD * L) + phase * RUGA_PHASE_RATIO)
        fold = np.maximum(fold, strength * along * _sech2(R * _wrap(theta - centre) / width))
    return r - depth * fold


def _local_structures(r, s, theta, R: float, feats: WallFeatures) -> np.ndarray:
    """Polyps (inward domes), diverticula (outward cups), papillae (a dome with a pit), ridges."""
    for ps, pth, size in feats.polyps:  # caps: inward, smooth dome
        d2 = ((s - ps) ** 2 + (R * _wrap(theta - pth)) ** 2) / size**2
        r = r - POLYP_HEIGHT * size * np.clip(1.0 - d2, 0.0, None) ** DOME_PROFILE_EXPONENT
    for ds_, dth, size in feats.diverticula:  # cups: outward pockets
        d2 = ((s - ds_) ** 2 + (R * _wrap(theta - dth)) ** 2) / size**2
        r = r + DIVERTICULUM_DEPTH * size * np.clip(1.0 - d2, 0.0, None) ** DOME_PROFILE_EXPONENT
    for ps, pth, size in feats.papillae:  # papilla: a low dome with a small pit at its top (the orifice)
        d2 = ((s - ps) ** 2 + (R * _wrap(theta - pth)) ** 2) / size**2
        r = r - PAPILLA_HEIGHT * size * np.clip(1.0 - d2, 0.0, None) ** DOME_PROFILE_EXPONENT
        r = r + PAPILLA_PIT_DEPTH * size * np.exp(-d2 / PAPILLA_PIT_RADIUS**2)
    for rs, rth, length, angle, height in feats.ridges:  # ridges: a short fold at any orientation
        ds_, dt = s - rs, R * _wrap(theta - rth)
        along = ds_ * np.cos(angle) + dt * np.sin(angle)
        across = -ds_ * np.sin(angle) + dt * np.cos(angle)
        envelope = np.clip(1.0 - (along / (0.5 * length)) ** 2, 0.0, None)
        r = r - height * envelope * _sech2(across / (RIDGE_WIDTH * R))
    return r


# ----------------------------------------------------------------------------- the mesh


@dataclass
class TubeMesh:
    """A procedural tube: mesh plus the geometry it came from.

    arrays: the triangle mesh as numpy arrays (``tube_arrays``): ``points`` (n x 3 float64),
    ``triangles`` (m x 3 int64), point ``normals`` pointing into the lumen, texture coordinates
    ``tcoords`` ``(s / tile, theta / 2 pi)``, and per point ``s`` and ``theta`` (float32).
    mesh: the same as a pyvista PolyData of triangles (built from ``arrays`` on first use, so a
    renderer without VTK never imports it), closed (both ends capped), point normals, texture
    coordinates (``Texture Coordinates``) and point arrays ``s`` and ``theta``.
    The seam theta = 0 = 2 pi has duplicated points (same coordinates) so the
    texture does not wrap backwards; ``mesh.clean()`` merges them.
    """

    preset: dict
    seed: int
    arrays: dict
    s_grid: np.ndarray
    points: np.ndarray
    T: np.ndarray
    N: np.ndarray
    B: np.ndarray
    features: WallFeatures
    texture_tile: float
    _mesh: object = field(default=None, repr=False, compare=False)

    @property
    def mesh(self):
        """The pyvista PolyData of ``arrays`` (VTK: imported here, on first use)."""
        if self._mesh is None:
            self._mesh = _polydata(self.arrays)
        return self._mesh

    @property
    def length(self) -> float:
        return float(self.s_grid[-1])

    def _interp(self, arr, s):
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        return np.stack([np.interp(s, self.s_grid, arr[:, k]) for k in range(3)], axis=-1)

    def centerline(self, s) -> np.ndarray:
        """Centerline point(s) at arc length s (scalar -> 3, array (n,) -> n x 3)."""
        return self._interp(self.points, s)

    def frame(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Parallel-transport frame (T, N, B) at arc length s, re-orthonormalized after interpolation."""
        t = self._interp(self.T, s)
        t /= np.linalg.norm(t, axis=-1, keepdims=True)
        n = self._interp(self.N, s)
        n -= np.sum(n * t, axis=-1, keepdims=True) * t
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return t, n, np.cross(t, n)

    def radius(self, s, theta) -> np.ndarray:
        """Wall radius r(s, theta) (scene units)."""
        return radius_field(s, theta, self.preset, self.features)

    def cast_rays(self, origin, directions) -> np.ndarray:
        """Distance from ``origin`` (3,) along each unit direction (n x 3) to the first wall hit (inf: none)."""
        import vtk  # VTK: heavy, needed only when rays are cast at the wall

        if getattr(self, "_locator", None) is None:
            self._locator = vtk.vtkStaticCellLocator()
            self._locator.SetDataSet(self.mesh)
            self._locator.BuildLocator()
        origin = np.asarray(origin, dtype=np.float64)
        reach = 4.0 * (self.length + float(self.preset["radius"]))
        out = np.full(len(directions), np.inf)
        t, x, pc, sub = vtk.reference(0.0), [0.0] * 3, [0.0] * 3, vtk.reference(0)
        for k, d in enumerate(np.asarray(directions, dtype=np.float64)):
            if self._locator.IntersectWithLine(origin, origin + reach * d, 1e-9, t, x, pc, sub):
                out[k] = float(t) * reach * float(np.linalg.norm(d))
        return out

    def wall_point(self, s, theta) -> np.ndarray:
        """World point of the wall at (s, theta) (... x 3)."""
        s = np.asarray(s, dtype=np.float64)
        theta = np.asarray(theta, dtype=np.float64)
        _, n, b = self.frame(s)
        r = self.radius(s, theta)[..., None]
        return self.centerline(s) + r * (np.cos(theta)[..., None] * n + np.sin(theta)[..., None] * b)


def build_tube(preset: dict | str, seed: int, resolution: dict | None = None) -> TubeMesh:
    """Build the tube of an organ preset (a name in PRESETS or a dict with the same keys).

    resolution: {"n_theta": points per ring, "ring_step": ring spacing as a fraction of the
    radius}. Deterministic in (preset, seed, resolution).
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown organ preset {preset!r}: choose one of {', '.join(PRESETS)}")
        preset = PRESETS[preset]
    preset = dict(preset)
    res = dict(DEFAULT_RESOLUTION, **(resolution or {}))
    n_theta = int(res["n_theta"])
    R, L = float(preset["radius"]), float(preset["length"])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), TUBE_RNG_TAG]))
    s_grid, pts = _sample_centerline(preset, rng, max(int(math.ceil(L / (float(res["ring_step"]) * R))) + 1, 2))
    T, N, B = parallel_transport_frames(pts)
    feats = _draw_features(preset, rng)
    S, TH, wall, normals = _wall_grid(s_grid, pts, N, B, n_theta, preset, feats)
    tile = 2 * np.pi * R
    arrays = tube_arrays(S, TH, wall, normals, s_grid, pts, T, tile)
    return TubeMesh(preset=preset, seed=int(seed), arrays=arrays, s_grid=s_grid, points=pts, T=T, N=N, B=B,
                    features=feats, texture_tile=tile)


def _sample_centerline(preset: dict, rng: np.random.Generator, n_rings: int) -> tuple[np.ndarray, np.ndarray]:
    """(arc lengths, points) of ``n_rings`` rings along the centerline: sampled densely, then
    re-parametrized by arc length."""
    L = float(preset["length"])
    t_dense = np.linspace(0.0, L * CENTERLINE_OVERSHOOT, 4000)
    dense = _centerline_points(t_dense, preset, rng)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    s_grid = np.linspace(0.0, L, n_rings)
    return s_grid, np.stack([np.interp(s_grid, arc, dense[:, k]) for k in range(3)], axis=1)


def _wall_grid(s_grid, pts, N, B, n_theta: int, preset: dict, feats: WallFeatures):
    """(S, TH, wall points, unit normals) on the rings x (n_theta + 1) grid; the last column
    duplicates the first (the texture seam). Normals dP/ds x dP/dtheta point into the lumen."""
    theta = np.linspace(0.0, 2 * np.pi, n_theta + 1)  # last column = seam duplicate of the first
    S, TH = np.meshgrid(s_grid, theta, indexing="ij")  # n_rings x (n_theta+1)
    r = radius_field(S, TH, preset, feats)
    r[:, -1] = r[:, 0]
    cos_t, sin_t = np.cos(TH), np.sin(TH)
    cos_t[:, -1], sin_t[:, -1] = 1.0, 0.0
    wall = pts[:, None, :] + r[..., None] * (cos_t[..., None] * N[:, None, :] + sin_t[..., None] * B[:, None, :])
    # analytic-grid normals (periodic in theta)
    core = wall[:, :-1]
    d_s = np.gradient(core, s_grid, axis=0)
    d_t = (np.roll(core, -1, axis=1) - np.roll(core, 1, axis=1))
    normals = np.cross(d_s, d_t)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return S, TH, wall, np.concatenate([normals, normals[:, :1]], axis=1)


def tube_arrays(S, TH, wall, normals, s_grid, pts, T, tile: float) -> dict:
    """The wall grid as triangles, closed by a fan at each end, with normals, texture coordinates,
    and the arc length ``s`` and angle ``theta`` of every point (numpy arrays: see ``TubeMesh``)."""
    n_rings, n_cols = wall.shape[:2]
    idx = np.arange(n_rings * n_cols).reshape(n_rings, n_cols)
    a, b_, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    # winding chosen so right-hand-rule face normals point into the lumen
    tris = np.concatenate([np.stack([a, c, b_], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    verts, nrm = [wall.reshape(-1, 3)], [normals.reshape(-1, 3)]
    tex = [np.stack([S.ravel() / tile, TH.ravel() / (2 * np.pi)], axis=1)]
    s_arr, th_arr = [S.ravel()], [TH.ravel()]
    base = n_rings * n_cols
    for k, (ring, sign) in enumerate(((0, 1.0), (n_rings - 1, -1.0))):  # end caps: a fan to each end's centre
        centre = base + k
        verts.append(pts[ring][None])
        nrm.append((sign * T[ring])[None])
        tex.append(np.array([[s_grid[ring] / tile, 0.5]]))
        s_arr.append([s_grid[ring]])
        th_arr.append([0.0])
        j0, j1 = idx[ring][:-1], idx[ring][1:]
        fan = (np.stack([np.full_like(j0, centre), j0, j1], -1) if ring == 0
               else np.stack([np.full_like(j0, centre), j1, j0], -1))
        tris = np.concatenate([tris, fan])
    return {"points": np.concatenate(verts).astype(np.float64), "triangles": tris.astype(np.int64),
            "normals": np.concatenate(nrm).astype(np.float32), "tcoords": np.concatenate(tex).astype(np.float32),
            "s": np.concatenate(s_arr).astype(np.float32), "theta": np.concatenate(th_arr).astype(np.float32)}


def _polydata(arrays: dict):
    """``tube_arrays``' mesh as a pyvista PolyData with point normals, texture coordinates, ``s`` and ``theta``."""
    import pyvista as pv  # VTK: imported where a mesh is built

    tris = arrays["triangles"]
    faces = np.hstack([np.full((len(tris), 1), 3), tris]).astype(np.int64).ravel()
    mesh = pv.PolyData(arrays["points"], faces)
    mesh.point_data["Normals"] = arrays["normals"]
    mesh.point_data.active_normals_name = "Normals"
    mesh.active_texture_coordinates = arrays["tcoords"]
    mesh.point_data["s"] = arrays["s"]
    mesh.point_data["theta"] = arrays["theta"]
    return mesh

"""Image-space appearance of real endoscopy frames, applied to each rendered RGB frame (depth untouched).

The renderer (``render.py``) draws clean frames: one exposure family, a linear response,
no sensor, no optics defects, no fluids. Real clinical frames, on which the paper's stage II
applies the synthetic-trained network zero-shot (Section 4.2.3, Kvasir and clinical videos),
also show: under- to over-exposure with saturated highlights, specular flecks and small
bubbles, mucus sheen, colour casts from pink to yellow, vignetting, a camera response curve,
sensor noise, motion or defocus blur and JPEG artefacts. This module adds them as a cheap,
deterministic post-process so that the training frames cover that range:

- ``APPEARANCE_DEFAULTS``: the manifest section ``appearance`` (every default is the identity);
- ``check_appearance``: validation of a merged section (one-line ``ValueError`` naming the field);
- ``sample_appearance``: one frame's draw, a JSON record (always the same number of draws);
- ``apply_appearance``: uint8 H x W x 3 -> uint8 H x W x 3, a pure function of the record.

Order of operations follows a camera: colour cast and exposure gain, surface effects
(mucus sheen, specular flecks), bubbles, vignetting, sensor clipping, response curve (gamma),
blur, noise, 8-bit quantization, JPEG. Sizes in pixels are given at a reference width of
128 and scale with the image width, so a manifest looks the same at every resolution.
"""

from __future__ import annotations

import io
import math

import numpy as np
from PIL import Image

from geodepth_lite.core.errors import UserError

APPEARANCE_DEFAULTS: dict = {
    "exposure_stops": [0.0, 0.0],   # gain 2**stops, then sensor clipping at 1 (over-exposure saturates)
    "gamma": [1.0, 1.0],            # camera response out = in ** (1 / gamma)
    "color_cast": [0.0, 0.0],       # -1 pinkish-magenta, 0 none, +1 yellowish (see CAST_PINK, CAST_YELLOW)
    "vignetting": [0.0, 0.0],       # multiply by 1 - v * (r / r_corner)**2
    "specular_flecks": [0, 0],      # count per frame: saturated white dots on well-lit pixels, 1-3 px at width 128
    "bubbles": [0, 0],              # count per frame: thin bright rings plus a small saturated highlight
    "bubble_radius": [0.01, 0.04],  # bubble radius, fraction of the image width
    "mucus": [0.0, 0.0],            # strength of smooth whitish sheen patches
    "noise": [0.0, 0.0],            # sensor noise std (image units 0..1, after the response curve)
    "p_blur": 0.0,                  # chance of blur per frame, motion or defocus 50/50
    "blur_px": [1.0, 3.0],          # motion streak length / defocus diameter in pixels at width 128
    "p_jpeg": 0.0,                  # chance of JPEG re-encoding per frame
    "jpeg_quality": [30, 90],       # JPEG quality range (integers)
}

REFERENCE_WIDTH = 128  # pixel sizes in the manifest are given at this width
# Channel gains of the extreme casts; a cast c scales channels by 1 + |c| (end - 1). Gains <= 1, so a cast
# never brightens (exposure does that): yellow lowers blue (old scopes, bile); pink lowers green most.
CAST_YELLOW = (1.0, 0.96, 0.70)
CAST_PINK = (1.0, 0.78, 0.92)
FLECK_CANDIDATES = 16      # a fleck lands on the brightest of this many random pixels
FLECK_VALUE = 2.0          # specular flecks are far brighter than the mucosa: over range, saturate after clipping
RING_ALPHA, RING_VALUE = 0.8, 1.0  # bubble rims: thin, bright, nearly white
MUCUS_ALPHA = 0.55         # blend towards white at full strength, full patch, full light
MUCUS_GRID = 8             # mucus patches: nodes of a 9 x 9 random grid, smoothly interpolated
IRWIN_HALL_STD = math.sqrt(4 * (256**2 - 1) / 12)  # std of a sum of four uniform bytes
# The uniform draws of ``sample_appearance``, by name, in the order they are taken from the frame's
# generator (one seed follows). The order is part of every dataset: reordering or adding a draw changes
# the frames (bump manifest.GENERATOR_VERSION).
DRAWS = ("exposure_stops", "gamma", "color_cast", "vignetting", "specular_flecks", "bubbles", "mucus", "noise",
         "blur", "blur_kind", "blur_px", "blur_angle", "jpeg", "jpeg_quality")
N_DRAWS = len(DRAWS)       # 14 uniform draws per frame

_PAIRS = {  # key: (lo, hi, lo_open, integer)
    "exposure_stops": (-5.0, 5.0, False, False),
    "gamma": (0.0, 5.0, True, False),
    "color_cast": (-1.0, 1.0, False, False),
    "vignetting": (0.0, 1.0, False, False),
    "specular_flecks": (0, 200, False, True),
    "bubbles": (0, 200, False, True),
    "bubble_radius": (0.0, 0.5, True, False),
    "mucus": (0.0, 1.0, False, False),
    "noise": (0.0, 0.2, False, False),
    "blur_px": (0.0, 32.0, False, False),
    "jpeg_quality": (1, 100, False, True),
}
_PROBS = ("p_blur", "p_jpeg")


# ----------------------------------------------------------------------------- manifest


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_appearance(field: str, a: dict) -> None:
    """Validate a fully merged ``appearance`` section; raises ValueError naming ``f"{field}.{key}"``."""
    if not isinstance(a, dict):
        raise UserError(f"manifest field '{field}' must be an object, got {type(a).__name__}")
    unknown = [k for k in a if k not in APPEARANCE_DEFAULTS]
    if unknown:
        raise UserError(f"manifest has an unknown key '{field}.{unknown[0]}' "
                         f"(allowed: {', '.join(APPEARANCE_DEFAULTS)})")
    missing = [k for k in APPEARANCE_DEFAULTS if k not in a]
    if missing:
        raise UserError(f"manifest field '{field}' is missing {', '.join(missing)}")
    for key, (lo, hi, lo_open, integer) in _PAIRS.items():
        name, v = f"{field}.{key}", a[key]
        if not isinstance(v, (list, tuple)) or len(v) != 2 or not all(_is_number(x) for x in v):
            raise UserError(f"manifest field '{name}' must be a [min, max] pair of numbers, got {v!r}")
        if integer and not all(isinstance(x, int) for x in v):
            raise UserError(f"manifest field '{name}' must be a [min, max] pair of integers, got {v!r}")
        if any((x <= lo if lo_open else x < lo) or x > hi for x in v):
            raise UserError(f"manifest field '{name}' must lie in {'(' if lo_open else '['}{lo}, {hi}], got {v!r}")
        if v[0] > v[1]:
            raise UserError(f"manifest field '{name}' must have min <= max, got {v!r}")
    for key in _PROBS:
        v = a[key]
        if not _is_number(v) or not 0.0 <= v <= 1.0:
            raise UserError(f"manifest field '{field}.{key}' must be a probability in [0, 1], got {v!r}")


def sample_appearance(a: dict, rng: np.random.Generator) -> dict:
    """One frame's appearance: a JSON-serializable record for ``apply_appearance``.

    Always draws the ``N_DRAWS`` uniforms named in ``DRAWS`` (in that order) and one seed,
    whatever the settings, so that changing one parameter does not shift the other draws (or
    those that follow in ``rng``).
    ``bubble_radius`` (the range) is carried along: bubbles' radii are drawn per pixel seed.
    """
    u = dict(zip(DRAWS, rng.random(N_DRAWS)))
    seed = int(rng.integers(0, 2**31 - 1))

    def uniform(key):  # a[key] = [lo, hi]: a number in that range, from the draw of that name
        lo, hi = a[key]
        return round(float(lo + (hi - lo) * u[key]), 10)

    def integer(key):  # a[key] = [lo, hi]: an integer in lo..hi, from the draw of that name
        lo, hi = (int(v) for v in a[key])
        return lo + min(int(u[key] * (hi - lo + 1)), hi - lo)

    blur = None
    if u["blur"] < a["p_blur"]:
        blur = {"kind": "motion" if u["blur_kind"] < 0.5 else "defocus", "px": uniform("blur_px"),
                "angle_deg": round(float(180.0 * u["blur_angle"]), 10)}
    return {
        "exposure_stops": uniform("exposure_stops"),
        "gamma": uniform("gamma"),
        "color_cast": uniform("color_cast"),
        "vignetting": uniform("vignetting"),
        "specular_flecks": integer("specular_flecks"),
        "bubbles": integer("bubbles"),
        "bubble_radius": [round(float(v), 10) for v in a["bubble_radius"]],
        "mucus": uniform("mucus"),
        "noise": uniform("noise"),
        "blur": blur,
        "jpeg_quality": integer("jpeg_quality") if u["jpeg"] < a["p_jpeg"] else None,
        "seed": seed,
    }


# ----------------------------------------------------------------------------- effects


def _channel_gains(cast: float, stops: float) -> np.ndarray:
    end = np.asarray(CAST_YELLOW if cast >= 0 else CAST_PINK)
    return (1.0 + abs(cast) * (end - 1.0)) * 2.0**stops


def _interp_weights(n: int, g: int, repeat: int = 1) -> np.ndarray:
    """n x (g+1) weights interpolating g+1 grid nodes at n pixels (smoothstep: no visible grid lines),
    each row repeated ``repeat`` times (3: one row per channel of an H x W x 3 image's row)."""
    t = np.linspace(0.0, g, n)
    i = np.minimum(t.astype(int), g - 1)
    f = t - i
    f = f * f * (3 - 2 * f)
    w = np.zeros((n, g + 1), np.float32)
    w[np.arange(n), i] = 1 - f
    w[np.arange(n), i + 1] = f
    return np.repeat(w, repeat, axis=0) if repeat > 1 else w


def _mucus(x: np.ndarray, strength: float, rng: np.random.Generator, t: np.ndarray) -> None:
    """Mucus sheen: a whitish layer screened over the image, x = 1 - (1 - x)(1 - a), a <= MUCUS_ALPHA x strength.

    Patches: the nodes of a random (g+1)^2 grid above a threshold (about a third of them), smoothly
    interpolated. A wet film reflects the light guides, so each node is also weighted by the local
    brightness (the dim distal lumen shows little sheen; illumination is smooth, 9 samples per node do).
    Interpolating the nodes gives the per-pixel, per-channel 1 - a in one matrix product (the weights
    sum to 1), written into the scratch ``t`` (H x 3W): 4 full-frame passes in all.
    """
    H, W = x.shape[:2]
    g = MUCUS_GRID
    off = np.array([-1.0, 0.0, 1.0]) / (4 * g)  # 3 x 3 samples around each node, a quarter cell apart
    ys = np.clip(np.rint(np.linspace(0, H - 1, g + 1)[:, None] + off * H), 0, H - 1).astype(int)  # (g+1, 3)
    xs = np.clip(np.rint(np.linspace(0, W - 1, g + 1)[:, None] + off * W), 0, W - 1).astype(int)
    light = np.clip(x[ys[:, None, :, None], xs[None, :, None, :]].mean(axis=(2, 3, 4)), 0.0, 1.0)  # (g+1, g+1)
    patch = np.clip(rng.standard_normal((g + 1, g + 1)) - 0.5, 0.0, 1.0)
    keep = 1.0 - patch * (0.15 + 0.85 * light) * (strength * MUCUS_ALPHA)
    x2 = x.reshape(H, 3 * W)
    np.matmul(_interp_weights(H, g), keep.astype(np.float32) @ _interp_weights(W, g, 3).T, out=t)
    np.subtract(np.float32(1.0), x2, out=x2)
    x2 *= t
    np.subtract(np.float32(1.0), x2, out=x2)


def _disc_alpha(dist: np.ndarray, radius) -> np.ndarray:
    """Anti-aliased disc coverage (1 inside, 0 beyond radius + 0.5 px)."""
    return np.clip(radius + 0.5 - dist, 0.0, 1.0)


def _splat(acc: np.ndarray, H: int, W: int, ys: np.ndarray, xs: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """acc (H*W flat) = max(acc, alpha) at integer pixels (ys, xs); out-of-frame and zero entries dropped.

    Returns the flat indices touched (with repeats).
    """
    ok = (alpha > 0) & (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
    idx = ys[ok] * W + xs[ok]
    np.maximum.at(acc, idx, alpha[ok].astype(np.float32))
    return idx


def _flecks(x: np.ndarray, n: int, rng: np.random.Generator, spec: np.ndarray) -> np.ndarray:
    """Specular flecks: 1-3 px discs (at width 128) on the brightest of FLECK_CANDIDATES random pixels each.

    Specular reflections need surface facing camera and light, i.e. near, well-lit mucosa:
    the best-of-k rule puts nearly all of them on bright pixels without a full-frame sort.
    """
    H, W = x.shape[:2]
    cy = rng.integers(0, H, (n, FLECK_CANDIDATES))
    cx = rng.integers(0, W, (n, FLECK_CANDIDATES))
    best = np.argmax(x[cy, cx].sum(axis=-1), axis=1)
    cy, cx = cy[np.arange(n), best], cx[np.arange(n), best]
    diam = rng.uniform(1.0, 3.0, n) * (W / REFERENCE_WIDTH)
    r = int(math.ceil(diam.max() / 2 + 0.5))
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1].reshape(2, -1)
    alpha = _disc_alpha(np.hypot(oy, ox)[None, :], diam[:, None] / 2)
    return _splat(spec, H, W, cy[:, None] + oy, cx[:, None] + ox, alpha)


def _bubbles(H: int, W: int, n: int, radius_range, rng: np.random.Generator, ring: np.ndarray,
             spec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bubbles: thin bright rims (refraction and Fresnel at grazing angles) and a small saturated highlight.

    Centres anywhere in the frame (partly outside is fine), radii from ``radius_range`` x width,
    highlight 0.4 radius off centre towards a random side (the light guides' side).
    """
    cy = rng.uniform(0, H - 1, n)
    cx = rng.uniform(0, W - 1, n)
    rad = rng.uniform(radius_range[0], radius_range[1], n) * W
    ang = rng.uniform(0, 2 * np.pi, n)
    half = 0.5 + 0.5 * W / REFERENCE_WIDTH  # rim half width (px): ~1 px at width 128
    r = int(math.ceil(rad.max() + half + 1))
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1].reshape(2, -1)
    ys, xs = np.rint(cy)[:, None].astype(int) + oy, np.rint(cx)[:, None].astype(int) + ox
    d = np.hypot(ys - cy[:, None], xs - cx[:, None])
    touched_ring = _splat(ring, H, W, ys, xs, RING_ALPHA * np.clip(1.0 - np.abs(d - rad[:, None]) / half, 0.0, 1.0))
    hy, hx = cy + 0.4 * rad * np.sin(ang), cx + 0.4 * rad * np.cos(ang)
    dh = np.hypot(ys - hy[:, None], xs - hx[:, None])
    return touched_ring, _splat(spec, H, W, ys, xs, _disc_alpha(dh, np.maximum(0.5, 0.12 * rad)[:, None]))


def _blend_sparse(x: np.ndarray, alpha: np.ndarray, touched: list, value: float) -> None:
    """x = x + alpha (value - x) at the ``touched`` flat indices (alpha: flat H*W): no full-frame pass."""
    idx = np.unique(np.concatenate(touched)) if touched else np.zeros(0, int)
    if idx.size:
        xf = x.reshape(-1, 3)
        a = alpha[idx, None]
        xf[idx] += a * (value - xf[idx])


def _tent_cdf(u: float) -> float:
    """CDF of the unit tent (linear interpolation kernel) on [-1, 1]."""
    u = min(max(u, -1.0), 1.0)
    return 0.5 * (u + 1) ** 2 if u < 0 else 1.0 - 0.5 * (1 - u) ** 2


def _line_taps(length: float, angle_deg: float) -> list[tuple[int, int, float]]:
    """A streak ``length`` px long along a direction, as (dy, dx, weight) taps one pixel apart on the major axis.

    Weights: a continuous box of that length on the linearly interpolated image, w_j = integral of the
    tent over [j - h, j + h] (h: half length on the major axis), so that sub-pixel streaks still blur
    a little and lengths vary smoothly; taps under 5% of the centre's are dropped. Minor-axis offsets are
    rounded (Bresenham). Symmetric (w_j = w_-j): no shift of RGB against depth.
    """
    t = math.radians(angle_deg)
    c, s = math.cos(t), math.sin(t)
    x_major = abs(c) >= abs(s)
    slope = s / c if x_major else c / s
    h = 0.5 * length * max(abs(c), abs(s))
    w0 = _tent_cdf(h) - _tent_cdf(-h)
    taps = []
    for j in range(-math.ceil(h + 1), math.ceil(h + 1) + 1):
        w = _tent_cdf(j + h) - _tent_cdf(j - h)
        if w >= 0.05 * w0:
            minor = int(round(j * slope))
            taps.append((minor, j, w / w0) if x_major else (j, minor, w / w0))
    return taps


def _apply_taps(P: np.ndarray, taps: list, ry: int, rx: int, out: np.ndarray | None = None) -> np.ndarray:
    """Valid-mode weighted sum of shifted views of P (margins ry, rx consumed), weights normalized, into ``out``.

    ``taps``: symmetric pairs around a centre tap (``_line_taps``), summed Horner-style from the lightest
    pair inwards: acc = (((v_a + v_-a) r + v_b + v_-b) r' + ...), no temporary arrays.
    """
    H, W = P.shape[0] - 2 * ry, P.shape[1] - 2 * rx
    view = lambda dy, dx: P[ry + dy:ry + dy + H, rx + dx:rx + dx + W]  # noqa: E731
    acc = np.empty((H, W) + P.shape[2:], P.dtype) if out is None else out
    centre = next(w for dy, dx, w in taps if (dy, dx) == (0, 0))
    pairs = sorted(((w, dy, dx) for dy, dx, w in taps if (dy, dx) > (0, 0)), key=lambda p: (p[0], p[1], p[2]))
    total = centre + 2 * sum(w for w, _, _ in pairs)
    w_prev = pairs[0][0]
    np.add(view(pairs[0][1], pairs[0][2]), view(-pairs[0][1], -pairs[0][2]), out=acc)
    for w, dy, dx in pairs[1:]:
        if w != w_prev:
            acc *= np.float32(w_prev / w)
            w_prev = w
        acc += view(dy, dx)
        acc += view(-dy, -dx)
    acc *= np.float32(w_prev / centre)
    acc += view(0, 0)
    acc *= np.float32(centre / total)
    return acc


def _blur(x: np.ndarray, blur: dict) -> None:
    """Blur x (H x W x 3) in place. Motion: a box streak of ``px`` along ``angle_deg``. Defocus: three
    streaks of px/2 at 0/60/120 deg (plus angle), whose convolution is a hexagonal aperture ``px`` across,
    smooth towards its centre (a 6-blade iris). Shifted-view sums on one reflect-padded copy: no FFT and
    no 2D kernel, a handful of array passes per streak.
    """
    px = float(blur["px"]) * x.shape[1] / REFERENCE_WIDTH
    a = float(blur["angle_deg"])
    passes = [_line_taps(px, a)] if blur["kind"] == "motion" else [_line_taps(px / 2, a + d) for d in (0, 60, 120)]
    passes = [p for p in passes if len(p) > 1]  # a single tap (streak under one pixel) changes nothing
    if not passes:
        return
    reach = [(max(abs(t[0]) for t in p), max(abs(t[1]) for t in p)) for p in passes]
    my, mx = sum(r[0] for r in reach), sum(r[1] for r in reach)
    P = np.pad(x, ((my, my), (mx, mx), (0, 0)), mode="reflect" if min(x.shape[:2]) > max(my, mx) else "edge")
    spare = None  # ping-pong: a pass writes into the memory of the array read two passes before
    for i, (taps, (ry, rx)) in enumerate(zip(passes, reach)):
        shape = (P.shape[0] - 2 * ry, P.shape[1] - 2 * rx, 3)  # each pass eats its own margin
        out = x if i == len(passes) - 1 else None if spare is None else spare.ravel()[:math.prod(shape)].reshape(shape)
        P, spare = _apply_taps(P, taps, ry, rx, out=out), P


def _add_noise_and_scale(x2: np.ndarray, sigma: float, rng: np.random.Generator, t: np.ndarray) -> None:
    """x2 = 255 (x2 + sigma z), in place: sensor noise, independent per pixel and channel, std ``sigma``.

    Additive in the output (gamma-encoded) domain: photon noise, std ~ sqrt(signal), comes out nearly
    constant after a response of about 1/2.2 (and read noise is lifted in the darks), so one sigma for
    all levels is a fair and cheap model. z nearly Gaussian: the sum of four uniform random bytes
    (Irwin-Hall, |z| < 3.5 std), about 4x cheaper than ``standard_normal``.
    """
    n = x2.size
    b = rng.bit_generator.random_raw((n + 1) // 2).astype("<u8", copy=False).view(np.uint8).reshape(4, -1)[:, :n]
    s = np.add(b[0], b[1], dtype=np.uint16)
    s += b[2]
    s += b[3]  # 0..1020, mean 510
    np.subtract(s.reshape(x2.shape), np.float32(510.0), out=t, dtype=np.float32)
    t *= np.float32(255.0 * sigma / IRWIN_HALL_STD)
    x2 *= np.float32(255.0)
    x2 += t


def _jpeg(rgb: np.ndarray, quality: int) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB")).copy()


def is_identity(rec: dict) -> bool:
    """True when ``rec`` changes nothing (``apply_appearance`` then returns a copy of its input)."""
    return (rec["exposure_stops"] == 0 and rec["gamma"] == 1 and rec["color_cast"] == 0 and rec["vignetting"] == 0
            and rec["specular_flecks"] == 0 and rec["bubbles"] == 0 and rec["mucus"] == 0 and rec["noise"] == 0
            and rec["blur"] is None and rec["jpeg_quality"] is None)


def _highlights(x: np.ndarray, rec: dict, rng) -> None:
    """Saturating highlights in place: specular flecks, and bubbles (a ring and a glint each);
    ``rng(i)`` is effect i's generator (0 flecks, 1 bubbles)."""
    H, W = x.shape[:2]
    spec, touched = np.zeros(H * W, np.float32), []
    if rec["specular_flecks"] > 0:
        touched.append(_flecks(x, int(rec["specular_flecks"]), rng(0), spec))
    if rec["bubbles"] > 0:
        ring = np.zeros(H * W, np.float32)
        touched_ring, touched_spec = _bubbles(H, W, int(rec["bubbles"]), rec["bubble_radius"], rng(1), ring, spec)
        _blend_sparse(x, ring, [touched_ring], RING_VALUE)
        touched.append(touched_spec)
    _blend_sparse(x, spec, touched, FLECK_VALUE)


def _vignetting(x2: np.ndarray, strength: float, H: int, W: int, t: np.ndarray) -> None:
    """Darken ``x2`` (H x 3W) towards the corners in place: 1 - strength * (r / r_corner)^2."""
    dy2 = (np.arange(H) - (H - 1) / 2) ** 2
    dx2 = (np.arange(W) - (W - 1) / 2) ** 2
    k = strength / max(dy2[0] + dx2[0], 1e-12)  # r_corner: the corner pixel's centre
    np.subtract((1.0 - k * dy2).astype(np.float32)[:, None], np.repeat(k * dx2, 3).astype(np.float32), out=t)
    x2 *= t


def apply_appearance(rgb: np.ndarray, rec: dict) -> np.ndarray:
    """uint8 H x W x 3 -> uint8 H x W x 3 with the effects of ``rec`` (from ``sample_appearance``).

    Deterministic: pixel-level randomness (fleck and bubble positions, mucus patches, noise) comes from
    the children of ``numpy.random.default_rng(rec["seed"])``, one per effect, so that switching one
    effect on does not move another. An identity record returns an untouched copy.
    """
    if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3):
        raise ValueError(f"apply_appearance expects a uint8 H x W x 3 array, got {getattr(rgb, 'dtype', type(rgb))} "
                         f"{getattr(rgb, 'shape', '')}")
    if is_identity(rec):
        return rgb.copy()
    H, W = rgb.shape[:2]
    # the children of default_rng(seed) (its SeedSequence spawned), built only for the effects in use
    kids = np.random.SeedSequence(rec["seed"]).spawn(4)
    rng = lambda i: np.random.default_rng(kids[i])  # noqa: E731  0 flecks, 1 bubbles, 2 mucus, 3 noise
    blur = rec["blur"] if rec["blur"] is not None and float(rec["blur"]["px"]) > 0 else None
    floating = (rec["exposure_stops"] != 0 or rec["gamma"] != 1 or rec["color_cast"] != 0 or rec["vignetting"] != 0
                or rec["specular_flecks"] > 0 or rec["bubbles"] > 0 or rec["mucus"] > 0 or rec["noise"] > 0
                or blur is not None)
    out = rgb
    if floating:
        # Work on x (H x W x 3 float32) through its (H, 3W) view x2: numpy is slow at broadcasting over a
        # trailing axis of 3, so per-channel and per-pixel factors are laid out as rows of length 3W.
        # One scratch array t serves every stage: each fresh frame-sized array also costs page faults.
        x = rgb.astype(np.float32)
        x2 = x.reshape(H, 3 * W)
        t = np.empty_like(x2)
        # colour cast and exposure: one per-channel gain, applied with the conversion to [0, 1]
        x2 *= np.tile((_channel_gains(rec["color_cast"], rec["exposure_stops"]) / 255.0).astype(np.float32), W)
        if rec["mucus"] > 0:
            _mucus(x, float(rec["mucus"]), rng(2), t)
        if rec["specular_flecks"] > 0 or rec["bubbles"] > 0:
            _highlights(x, rec, rng)
        if rec["vignetting"] > 0:
            _vignetting(x2, float(rec["vignetting"]), H, W, t)
        np.clip(x2, 0.0, 1.0, out=x2)  # the sensor saturates
        if rec["gamma"] != 1:
            np.power(x2, np.float32(1.0 / rec["gamma"]), out=x2)
        if blur is not None:
            _blur(x, blur)
        if rec["noise"] > 0:
            _add_noise_and_scale(x2, float(rec["noise"]), rng(3), t)
        else:
            x2 *= np.float32(255.0)
        np.clip(x2, 0.0, 255.0, out=x2)
        out = np.rint(x2, out=x2).astype(np.uint8).reshape(H, W, 3)
    if rec["jpeg_quality"] is not None:
        out = _jpeg(np.ascontiguousarray(out), rec["jpeg_quality"])
    return out.copy() if out is rgb else out

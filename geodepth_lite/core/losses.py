"""The five losses of Section 3.C and their weighted sum (Eq. for L_total).

Shapes and units (all losses):
- ``pred``, ``gt``: z-depth maps ``B x 1 x H x W`` (float tensors, scene units);
- ``image``: ``B x 3 x H x W`` in [0, 1];
- ``K``: ``3 x 3`` or ``B x 3 x 3`` intrinsics in pixels (see :mod:`geodepth_lite.core.camera`);
- ``mask``: optional ``B x 1 x H x W`` bool, True where the ground truth may be used.

Ground truth that is NaN, infinite, zero or negative is always treated as invalid (in
addition to ``mask``), and each loss returns a finite scalar tensor even when no pixel is
valid (then 0, still connected to ``pred`` for autograd).

Image gradients are forward differences in depth units per pixel:
``grad_x D(v, u) = D(v, u+1) - D(v, u)`` and ``grad_y D(v, u) = D(v+1, u) - D(v, u)``;
a difference is valid when both of its pixels are valid.

The SDF term (:func:`sdf_loss`) is built on :mod:`geodepth_lite.core.sdf`: the exact nearest-point
search, the signed fields with their sign rule (the paper's view rule by default), where the
samples lie (the paper's bounding-box grid by default) and the cache of ground-truth fields, all
chosen by one :class:`geodepth_lite.core.sdf.SDFOptions`.

The settings of L_total beside the batch (the weights, the depth term, its border weight and the
SDF options) are one :class:`LossSpec`; ``LossSpec()`` is the paper's recipe.
"""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass
from typing import Callable

import torch

from geodepth_lite.core.errors import UserError

from .sdf import (  # the SDF machinery; valid_mask and check_depths are shared with it
    SDFOptions,
    check_depths,
    sdf_fields,
    sdf_fields_batched,
    valid_mask,
)


# ----------------------------------------------------------------------------- helpers
def _prepare(pred, gt, mask):
    """Check shapes; return (gt with invalid pixels replaced by 1, validity mask)."""
    check_depths(pred, gt)
    valid = valid_mask(gt, mask)
    gt_safe = torch.where(valid, gt, torch.ones_like(gt))  # no NaN/inf can reach autograd
    return gt_safe, valid


def masked_mean(x: torch.Tensor, valid: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of ``x`` over ``valid`` entries (weighted by ``weight``, broadcast to ``x``, when given);
    0 (connected to ``x``) when none is valid."""
    x = torch.where(valid, x, torch.zeros_like(x))
    if weight is None:
        return x.sum() / valid.sum().clamp(min=1).to(x.dtype)
    w = weight.to(x.dtype) * valid.to(x.dtype)
    return (w * x).sum() / w.sum().clamp(min=1e-12)


BORDER_RAMP_START = 0.7  # border_weight_map: the weight rises from here (0 = centre, 1 = edge) to the edge


def border_weight_map(height: int, width: int, beta: float, like: torch.Tensor | None = None) -> torch.Tensor:
    """1 x 1 x H x W pixel weights for the depth term: 1 in the middle, rising linearly to 1 + ``beta``
    at the image edge over the outer 15% of each side.

    A pixel's place is its Chebyshev distance from the centre in normalised coordinates (pixel
    centres, 0 at the centre, 1 at the edge); the ramp starts at ``BORDER_RAMP_START``. Why: a
    network sees less context at the border and its error there is larger (notebook 06's border
    map; docs/teach_recipe.md); weighting those pixels more spends more of its effort there.
    Notebook 04 ("What the network minimises") writes the weight out as an equation.

    Explained with its equation in notebook 04, "What the network minimises" (the border weight w_p).
    """
    if not beta >= 0:
        raise UserError(f"border weight must be a non-negative number, got {beta!r}")
    dtype = like.dtype if like is not None and like.is_floating_point() else torch.float32
    device = like.device if like is not None else None
    ys = (torch.arange(height, device=device, dtype=dtype) + 0.5) / height * 2 - 1
    xs = (torch.arange(width, device=device, dtype=dtype) + 0.5) / width * 2 - 1
    place = torch.maximum(ys.abs()[:, None], xs.abs()[None, :])
    ramp = ((place - BORDER_RAMP_START) / (1 - BORDER_RAMP_START)).clamp(0, 1)
    return (1 + beta * ramp)[None, None]


def grad_x(d: torch.Tensor) -> torch.Tensor:
    """Forward difference along the columns: ... x H x (W-1)."""
    return d[..., :, 1:] - d[..., :, :-1]


def grad_y(d: torch.Tensor) -> torch.Tensor:
    """Forward difference along the rows: ... x (H-1) x W."""
    return d[..., 1:, :] - d[..., :-1, :]


# ----------------------------------------------------------------------------- pixel losses
def depth_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None,
               weight: torch.Tensor | None = None) -> torch.Tensor:
    """L_depth = || D_pred - D_gt ||_1, as the mean absolute difference over valid pixels (Sec. 3.C, Eq. 1).

    ``weight``: optional per-pixel weights (e.g. :func:`border_weight_map`); the mean becomes weighted.

    Explained with its equation in notebook 03, section 1 (Eq. 1).
    """
    gt_safe, valid = _prepare(pred, gt, mask)
    return masked_mean((pred - gt_safe).abs(), valid, weight)


def log_depth_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None,
                   weight: torch.Tensor | None = None) -> torch.Tensor:
    """|ln D_pred - ln D_gt|, mean over valid pixels: the depth term in relative units.

    Not the paper's term (its Eq. 1 is the absolute L1 above). A far lumen pixel at 30 units
    weighs no more here than a wall pixel at 1 unit, as in the median-scaled metrics
    (Abs Rel, RMSE log). Measured against L1 and silog on docs/teach_recipe.md.
    """
    gt_safe, valid = _prepare(pred, gt, mask)
    return masked_mean((torch.log(pred.clamp(min=1e-6)) - torch.log(gt_safe)).abs(), valid, weight)


SILOG_VARIANCE_FOCUS = 0.85  # lambda of the scale-invariant log loss (Eigen et al. 2014; BTS)


def silog_depth_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None,
                     weight: torch.Tensor | None = None) -> torch.Tensor:
    """Scale-invariant log loss, per frame sqrt(mean(d^2) - lambda mean(d)^2), d = ln D_pred - ln D_gt.

    Not the paper's term. One image does not say how far away the scene is (the endoscope's
    auto-exposure removes the brightness cue for absolute scale), and the metrics median-scale
    every frame. With lambda = 0.85 the loss mostly ignores a frame's global scale error
    (the mean of d) and spends the network's effort on relative depth; the remaining 15%
    keeps the scale anchored. Mean over the frames that have valid pixels. ``weight``: optional
    per-pixel weights (e.g. :func:`border_weight_map`): the per-frame means become weighted means.
    Notebook 04 ("What the network minimises") writes it out as an equation.

    Explained with its equation in notebook 04, "What the network minimises" (L_silog).
    """
    gt_safe, valid = _prepare(pred, gt, mask)
    d = torch.where(valid, torch.log(pred.clamp(min=1e-6)) - torch.log(gt_safe), torch.zeros_like(pred))
    w = valid.to(d.dtype) if weight is None else weight.to(d.dtype) * valid.to(d.dtype)
    w = w.expand_as(d)
    has = valid.flatten(1).any(1)
    n = w.flatten(1).sum(1).clamp(min=1e-12)  # (weighted) valid pixels per frame
    mean = (w * d).flatten(1).sum(1) / n
    msq = (w * d * d).flatten(1).sum(1) / n
    per_frame = torch.sqrt((msq - SILOG_VARIANCE_FOCUS * mean * mean).clamp(min=1e-12))
    return torch.where(has, per_frame, torch.zeros_like(per_frame)).sum() / has.sum().clamp(min=1).to(d.dtype)


DEPTH_TERMS = {"l1": depth_loss, "log_l1": log_depth_loss, "silog": silog_depth_loss}  # the depth term's variants


def smoothness_loss(pred: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """L_smooth = (e^{-|grad I|} . grad D)^2, edge-aware (Sec. 3.C, Eq. 2; Godard et al. 2017).

    |grad I| is the channel mean of the absolute image differences; the loss is the mean over
    pixels of the squared, edge-weighted x differences plus that of the y differences.

    Explained with its equation in notebook 03, section 2.
    """
    if image.dim() != 4 or image.shape[0] != pred.shape[0] or image.shape[-2:] != pred.shape[-2:]:
        raise ValueError(f"image must be B x 3 x H x W matching pred {tuple(pred.shape)}, got {tuple(image.shape)}")
    sx, sy = smoothness_maps(pred, image)
    return sx.mean() + sy.mean()


def smoothness_maps(pred: torch.Tensor, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel terms of :func:`smoothness_loss`: (e^{-|grad_x I|} grad_x D)^2, B x 1 x H x (W-1),
    and the same along y, B x 1 x (H-1) x W."""
    wx = torch.exp(-grad_x(image).abs().mean(dim=1, keepdim=True))  # (B, 1, H, W-1)
    wy = torch.exp(-grad_y(image).abs().mean(dim=1, keepdim=True))  # (B, 1, H-1, W)
    return (wx * grad_x(pred)).pow(2), (wy * grad_y(pred)).pow(2)


def gradient_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_grad = ||grad_x D_pred - grad_x D_gt||_1 + ||grad_y D_pred - grad_y D_gt||_1 (Sec. 3.C, Eq. 3).

    Each term is a mean over the valid differences (depth units per pixel).

    Explained with its equation in notebook 03, section 3.
    """
    (ex, vx), (ey, vy) = gradient_maps(pred, gt, mask)
    return masked_mean(ex, vx) + masked_mean(ey, vy)


def gradient_maps(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None):
    """Per-pixel terms of :func:`gradient_loss` with their validity:
    ((|grad_x D_pred - grad_x D_gt|, valid), B x 1 x H x (W-1); (the same along y, valid), B x 1 x (H-1) x W)."""
    gt_safe, valid = _prepare(pred, gt, mask)
    vx = valid[..., :, 1:] & valid[..., :, :-1]
    vy = valid[..., 1:, :] & valid[..., :-1, :]
    return ((grad_x(pred) - grad_x(gt_safe)).abs(), vx), ((grad_y(pred) - grad_y(gt_safe)).abs(), vy)


def surface_normals(d: torch.Tensor) -> torch.Tensor:
    """n = [-grad_x D, -grad_y D, 1] at pixel (v, u), u < W-1, v < H-1: B x 3 x (H-1) x (W-1) (Sec. 3.C)."""
    gx = grad_x(d)[..., :-1, :]
    gy = grad_y(d)[..., :, :-1]
    return torch.cat((-gx, -gy, torch.ones_like(gx)), dim=1)


def normal_map(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None):
    """Per-pixel 1 - cos(n_pred, n_gt), B x 1 x (H-1) x (W-1), and its validity mask."""
    gt_safe, valid = _prepare(pred, gt, mask)
    v = valid[..., :-1, :-1] & valid[..., :-1, 1:] & valid[..., 1:, :-1]
    n_p, n_g = surface_normals(pred), surface_normals(gt_safe)
    cos = (n_p * n_g).sum(1, keepdim=True) / (n_p.norm(dim=1, keepdim=True) * n_g.norm(dim=1, keepdim=True))
    return 1.0 - cos, v  # norms are >= 1 (third component is 1): no division by zero


def normal_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_normal = 1 - <n_gt, n_pred> / (|n_gt| |n_pred|), mean over valid pixels (Sec. 3.C, Eq. 4).

    Explained with its equation in notebook 03, section 4.
    """
    per_pixel, v = normal_map(pred, gt, mask)
    return masked_mean(per_pixel, v)


# ----------------------------------------------------------------------------- SDF loss
def sdf_loss(pred, gt, K, options: SDFOptions = SDFOptions(), mask=None, frame_ids=None) -> torch.Tensor:
    """L_sdf: mean over the r_x r_y r_z grid of |phi(X_ijk, S_pred) - phi(X_ijk, S_gt)| (Sec. 3.C, Eq. 10).

    The fields come from :mod:`geodepth_lite.core.sdf`, built as ``options`` says
    (:class:`geodepth_lite.core.sdf.SDFOptions`, whose fields are named below; ``SDFOptions()`` is the
    paper's term). Both depth maps are back-projected with K
    (valid pixels only); the grid spans the ground truth's 3D bounding box [X_lb, X_ub]
    (:func:`geodepth_lite.core.sdf.grid_points`); phi is the exact nearest distance, signed by the
    paper's view rule (``sign_rule="view"``): grid point q projected with K to its nearest
    pixel, +1 where q_z is less than that map's own depth there (the prediction's field uses
    ``pred``, the ground truth's ``gt``), -1 where greater, 0 on it; for q_z <= 0, q projecting
    outside the image or onto an invalid pixel, the fallback sign((X_n - q) . X_n) with X_n the
    nearest surface point (:func:`geodepth_lite.core.sdf.sdf_fields`,
    :func:`geodepth_lite.core.sdf.signed_distance`). ``sign_rule="nearest"`` uses that nearest-point
    sign everywhere (the former rule, for comparison). The loss is the mean over images with at
    least one valid pixel (0 if none). ``method``: exact nearest-neighbour search, "auto" =
    cKDTree on the CPU, the batched torch search (:mod:`geodepth_lite.core.nnsearch`) on CUDA.
    ``signed=False`` gives the unsigned variant (for comparison). ``cache``: ground-truth fields
    are reused for frames seen before (:class:`geodepth_lite.core.sdf.GTFieldCache`; None to always search),
    keyed by ``frame_ids`` (one hashable id per image) where given, by the frames' content otherwise.
    The fields are built for the whole batch at once (:func:`geodepth_lite.core.sdf.sdf_fields_batched`),
    and the loss equals, bit for bit, its former image-by-image form (``sdf_loss_reference``).

    Two options, not the paper's (docs/network_and_losses.md, "Where the SDF samples lie"):
    ``sign_rule="masked"`` leaves out the points where the view rule does not apply in either
    field (q_z <= 0, outside the image, on an invalid pixel): each image's loss is the mean of
    |phi_pred - phi_gt| over the remaining points, the batch's the mean over images that have
    some (0 if none). ``sampling="frustum"`` samples r_x x r_y pixels times r_z log-spaced depths
    between the ground truth's nearest and farthest valid depth instead of the bounding box
    (:func:`geodepth_lite.core.sdf.frustum_points`).

    Explained with its equation in notebook 03, section 5 (the grid, the sign rule, L_SDF).
    """
    f = sdf_fields_batched(pred, gt, K, options, mask, frame_ids)
    return sdf_loss_from_fields(f, pred)


def _front_mean(x: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Per row of x (B x M), the mean of the entries where ``keep`` (B x M bool), 0 for a row without any;
    the kept entries are moved, in order, to the front of the row and the rest zeroed, so the sum adds the
    same numbers in the same places as a sum over the kept entries alone (the per-image loss's)."""
    order = torch.argsort((~keep).to(torch.uint8), dim=1, stable=True)  # kept entries first, in order
    k = torch.gather(keep, 1, order)
    front = torch.where(k, torch.gather(x, 1, order), torch.zeros((), dtype=x.dtype, device=x.device))
    n = keep.sum(1)
    return front.sum(1) / n.clamp_min(1).to(x.dtype), n > 0


def sdf_loss_from_fields(f: dict, pred: torch.Tensor) -> torch.Tensor:
    """L_sdf of the batched fields of :func:`geodepth_lite.core.sdf.sdf_fields_batched` (``pred``: only for a
    zero connected to it): the mean over the images with a valid pixel ("masked": over the images with a
    known sample, each the mean over its known samples), with no host sync."""
    err = (f["pred"] - f["gt"]).abs()  # (B, M)
    has = f["has"]
    if "known" in f:
        per_image, some = _front_mean(err, f["known"] & has[:, None])  # (B,) each
        return _front_mean(per_image[None], some[None])[0][0]
    # the mean over every sample of the images with a valid pixel: those rows first, the others zeroed
    rows = torch.argsort((~has).to(torch.uint8), stable=True)  # (B,)
    h = has.index_select(0, rows)
    front = torch.where(h[:, None], err.index_select(0, rows), torch.zeros((), dtype=err.dtype, device=err.device))
    return front.sum() / (h.sum() * err.shape[1]).clamp_min(1).to(err.dtype)


def sdf_loss_reference(pred, gt, K, options: SDFOptions, mask=None) -> torch.Tensor:
    """:func:`sdf_loss` image by image from :func:`geodepth_lite.core.sdf.sdf_fields` (the former code, kept as the
    reference the batched loss must equal bit for bit, and as the benchmark's baseline); ground-truth fields
    are keyed by content in ``options.cache``."""
    fields = [f for f in sdf_fields(pred, gt, K, options, mask) if f is not None]
    if options.sign_rule == "masked":
        per_image = [(f["pred"] - f["gt"]).abs()[f["known"]].mean() for f in fields if bool(f["known"].any())]
        return torch.stack(per_image).mean() if per_image else pred.sum() * 0.0
    if not fields:
        return pred.sum() * 0.0
    return (torch.stack([f["pred"] for f in fields]) - torch.stack([f["gt"] for f in fields])).abs().mean()


# ----------------------------------------------------------------------------- the loss table
def _depth_term(p: torch.Tensor, x: LossInputs) -> torch.Tensor:
    spec = x.spec
    weight = border_weight_map(*p.shape[-2:], spec.border_weight, p) if spec.border_weight else None
    return DEPTH_TERMS[spec.depth_term](p, x.gt, x.mask, weight=weight)


@dataclass(frozen=True)
class LossTerm:
    """One term of L_total: its function of (pred, LossInputs) and the weight group that scales it."""

    fn: Callable[[torch.Tensor, LossInputs], torch.Tensor]
    group: str       # "lambda1" | "lambda2" | "lambda3" (Eq. 11) or a new group
    equation: str    # where the paper defines it


# Every term of L_total, named once, in the order of Eq. 11 (Sec. 3.C):
# L_total = lambda1 (L_depth + L_smooth) + lambda2 (L_grad + L_normal) + lambda3 L_sdf.
# A new term is one entry here (plus its function); the training log, the widgets and the
# notebooks read this table. A term in a new group needs that group's weight in ``lambdas``.
LOSS_TERMS: dict[str, LossTerm] = {
    "depth": LossTerm(_depth_term, "lambda1", "Eq. 1"),
    "smooth": LossTerm(lambda p, x: smoothness_loss(p, x.image), "lambda1", "Eq. 2"),
    "grad": LossTerm(lambda p, x: gradient_loss(p, x.gt, x.mask), "lambda2", "Eq. 3"),
    "normal": LossTerm(lambda p, x: normal_loss(p, x.gt, x.mask), "lambda2", "Eq. 4"),
    "sdf": LossTerm(lambda p, x: sdf_loss(p, x.gt, x.K, x.spec.sdf, x.mask, x.frame_ids), "lambda3", "Eq. 10"),
}


def term_names() -> tuple[str, ...]:
    """The loss terms' names in table order (``LOSS_TERMS``)."""
    return tuple(LOSS_TERMS)


def group_names() -> tuple[str, ...]:
    """The weight groups in order of first appearance in ``LOSS_TERMS``: lambda1, lambda2, lambda3."""
    return tuple(dict.fromkeys(t.group for t in LOSS_TERMS.values()))


def group_weights(lambdas) -> dict[str, float]:
    """{group: weight} from weights given by group name ({"lambda1": 1, ...}; a missing group is 0)
    or in ``group_names()`` order ([lambda1, lambda2, lambda3], the paper's notation)."""
    groups = group_names()
    if isinstance(lambdas, dict):
        unknown = sorted(set(lambdas) - set(groups))
        if unknown:
            raise UserError(f"unknown loss weight group {', '.join(map(repr, unknown))}: "
                             f"choose from {', '.join(groups)}")
        weights = {g: float(lambdas.get(g, 0.0)) for g in groups}
    else:
        if len(lambdas) != len(groups):
            raise UserError(f"lambdas must be {len(groups)} non-negative weights ({', '.join(groups)}), "
                             f"got {lambdas!r}")
        weights = {g: float(w) for g, w in zip(groups, lambdas)}
    if any(not w >= 0 for w in weights.values()):
        raise UserError(f"loss weights must be non-negative, got {weights!r}")
    return weights


@dataclass(frozen=True)
class LossSpec:
    """The settings of L_total beside the batch: the weight of each group, the depth term's variant, its
    border weight and the SDF term's options. ``LossSpec()`` is the paper's recipe (Sec. 3.C, Eq. 11).

    ``lambdas``: the groups' weights by name or in ``group_names()`` order (:func:`group_weights`; the
    paper's (1, 1, 1) by default; a list is kept as a tuple). ``depth_term``: "l1" (the paper's Eq. 1),
    "log_l1" (:func:`log_depth_loss`) or "silog" (:func:`silog_depth_loss`). ``border_weight``: beta of
    :func:`border_weight_map` in the depth term (0: every pixel alike, the paper). ``sdf``: the SDF term's
    :class:`geodepth_lite.core.sdf.SDFOptions` (the paper's grid, sampling and sign rule by default).
    A value out of range raises the UserError that names it, here.
    """

    lambdas: tuple | dict = (1.0, 1.0, 1.0)
    depth_term: str = "l1"
    border_weight: float = 0.0
    sdf: SDFOptions = SDFOptions()

    def __post_init__(self):
        if self.depth_term not in DEPTH_TERMS:
            raise UserError(f"depth_term must be one of {', '.join(DEPTH_TERMS)}, got {self.depth_term!r}")
        if not self.border_weight >= 0:
            raise UserError(f"border weight must be a non-negative number, got {self.border_weight!r}")
        if not isinstance(self.sdf, SDFOptions):
            raise TypeError(f"sdf must be an SDFOptions (e.g. SDFOptions(grid=8)), got {self.sdf!r}")
        if not isinstance(self.lambdas, dict):
            object.__setattr__(self, "lambdas", tuple(self.lambdas))
        group_weights(self.lambdas)


@dataclass(frozen=True, kw_only=True)
class LossInputs:
    """What a loss term may read besides the prediction: one batch and the loss settings, given by keyword
    (``LossInputs(gt=gt, image=image, K=K, spec=LossSpec())``)."""

    gt: torch.Tensor                      # (B, 1, H, W) ground-truth depth
    image: torch.Tensor                   # (B, 3, H, W) in [0, 1]
    K: torch.Tensor                       # (B, 3, 3) or (3, 3) pixels
    mask: torch.Tensor | None = None      # (B, 1, H, W) bool or None
    frame_ids: tuple | None = None        # one hashable id per frame keying cached ground-truth fields (None: content)
    spec: LossSpec = LossSpec()           # the weights, the depth term, its border weight, the SDF options

    def __post_init__(self):
        if self.frame_ids is not None:
            object.__setattr__(self, "frame_ids", tuple(self.frame_ids))


def _spec(spec) -> LossSpec:
    """``spec`` itself, or a TypeError saying what the loss functions take instead."""
    if not isinstance(spec, LossSpec):
        raise TypeError(f"the loss settings must be a LossSpec (e.g. LossSpec(lambdas=(1, 0, 0))), got {spec!r}")
    return spec


def total_loss(pred, gt, image, K, spec: LossSpec = LossSpec(), mask=None, frame_ids=None):
    """L_total: each group's weight times the sum of its terms (``LOSS_TERMS``; Sec. 3.C, Eq. 11).

    Returns (loss, terms): ``loss`` a scalar tensor for backward; ``terms`` a dict of floats with
    one key per term (unweighted) and "total" (weighted). A zero weight skips computing its
    group's terms, which are then reported as 0.0. ``spec``: the weights, the depth term, its border
    weight and the SDF term's options (:class:`LossSpec`; the paper's recipe by default). The ablation
    cases of Sec. 4.2.1 are weight settings (``config.ABLATION_CASES``). ``frame_ids``: one hashable id
    per frame, whose ground truth is the same whenever the id is (no augmentation), to key the SDF term's
    cached ground-truth fields without reading the frames (:func:`sdf_loss`); None keys them by content.

    Explained with its equation in notebook 04, "What the network minimises" (Eq. 11).
    """
    weights = group_weights(_spec(spec).lambdas)
    inputs = LossInputs(gt=gt, image=image, K=K, mask=mask, frame_ids=frame_ids, spec=spec)
    zero = pred.sum() * 0.0
    t = {name: (term.fn(pred, inputs) if weights[term.group] else zero) for name, term in LOSS_TERMS.items()}
    loss = None
    for group, w in weights.items():
        members = [t[name] for name, term in LOSS_TERMS.items() if term.group == group]
        part = w * functools.reduce(operator.add, members)
        loss = part if loss is None else loss + part
    terms = {k: float(v.detach()) for k, v in t.items()}
    terms["total"] = float(loss.detach())
    return loss, terms


def term_gradient_norms(pred, gt, image, K, spec: LossSpec = LossSpec(), mask=None,
                        frame_ids=None) -> dict[str, float]:
    """||dL_term / dD_pred||_2 of each unweighted term at the network's output (a loss-balancing diagnostic).

    The network sees the losses only through this gradient on its output depth map, so the
    ratio of two norms says how strongly each term pulls on the prediction at a given lambda:
    a term whose gradient is 10x the depth term's dominates the update at lambda = 1.
    ``pred`` is detached here (nothing reaches the network); returns {term: norm} for the terms that
    :func:`total_loss` evaluates under ``spec``, those whose group's weight is not zero (with the paper's
    weights, every term of ``LOSS_TERMS``). The other arguments as in :func:`total_loss`.
    """
    weights = group_weights(_spec(spec).lambdas)
    p = pred.detach().float().clone().requires_grad_(True)
    inputs = LossInputs(gt=gt, image=image, K=K, mask=mask, frame_ids=frame_ids, spec=spec)
    out = {}
    for name, term in LOSS_TERMS.items():
        if weights[term.group]:
            (g,) = torch.autograd.grad(term.fn(p, inputs), p, allow_unused=True)
            out[name] = 0.0 if g is None else float(g.norm())
    return out

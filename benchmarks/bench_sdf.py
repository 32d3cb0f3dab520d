"""Benchmark of the SDF loss (Sec. 3.C) at the paper's scale: ``python benchmarks/bench_sdf.py``.

In one run, on the same depth maps (rendered frames of the synthetic dataset) and medians
of repeats, it times:

1. the SDF loss forward + backward with the exact spatial-index search used in training
   (cKDTree on the CPU, chunked on-device search on CUDA), batch 20, 320x320, 32^3 grid;
2. the same loss with a chunked brute-force nearest-neighbour search over all pairs (torch.cdist
   in its fastest, matrix-product form), measured on fewer images and scaled linearly to the
   batch (the output says so);
3. one training step of DepthNet at the same batch (forward, all five losses, backward,
   Adam step);
   (1 and 3 each without and with the cache of ground-truth fields, i.e. first and later epochs);
4. inference frames/s of DepthNet at 320x320;
5. the nearest-point search alone (``--search``), on the same tensors' device: the batched exact
   search of the device path (:mod:`geodepth_lite.core.nnsearch`), scipy's cKDTree (one worker unless
   ``--threads``) and the matrix-product brute force, side by side, with the device search's
   agreement with cKDTree on every query. Its points are depth maps back-projected, its queries
   each map's 32^3 bounding-box grid, as in the SDF loss.

6. ``--compare``: the whole SDF loss (forward and backward) of a batch, today's batched form
   (:func:`geodepth_lite.core.losses.sdf_loss`, fields as B x M tensors, ground-truth fields keyed by frame
   id) beside the former image-by-image one (``losses.sdf_loss_reference``, content keys), on the same
   tensors: without the cache, with it warm, and with the nearest points given (all but the search),
   medians of interleaved repeats and their ratio.

``--data analytic`` takes analytic lumen, wall and close-up views (:mod:`geodepth_lite.data.analytic`,
no rendering, so no VTK) instead of rendered frames of the synthetic dataset.

The predictions are the ground truth times a smooth random factor (about +-10 %), so both
surfaces are realistic endoscopic depth maps.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from geodepth_lite import utils
from geodepth_lite.core import losses, sdf
from geodepth_lite.core.model import DepthNet


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def _timed(fn, device) -> float:
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


def analytic_batch(batch: int, size: int, device) -> dict:
    """``batch`` analytic frames (image, depth, K): lumen, wall and close-up views in turn (no VTK)."""
    from geodepth_lite.data import analytic

    K = torch.from_numpy(analytic.intrinsics(size)).float()
    depth, image = [], []
    for i in range(batch):
        d = analytic.depth_map(analytic.KINDS[i % len(analytic.KINDS)], size, seed=i)
        depth.append(torch.from_numpy(d)[None])
        image.append(torch.from_numpy(analytic.shaded_image(d, K.double().numpy(), seed=i)).permute(2, 0, 1) / 255.0)
    return {"image": torch.stack(image).to(device), "depth": torch.stack(depth).to(device),
            "K": K.expand(batch, 3, 3).contiguous().to(device)}


def search_inputs(depth: torch.Tensor, K: torch.Tensor, grid: int) -> list:
    """Per image (points N x 3, queries grid^3 x 3): the depth map back-projected and its bounding-box grid."""
    from geodepth_lite.core import camera

    pts = camera.backproject(depth, K)  # (B, H*W, 3)
    return [(p, sdf.grid_points(p.min(0).values, p.max(0).values, grid)) for p in pts]


def run_search(pairs: list, repeats: int, bf_images: int, device) -> dict:
    """Medians of the nearest-point search of ``pairs`` by three methods, and the agreement on every query."""
    import numpy as np

    dev_idx = sdf.nearest_indices_many(pairs, "device")
    kd_idx = [sdf.nearest_indices_kdtree(p, q) for p, q in pairs]
    agree = sum(int((a.cpu() == b.cpu()).sum()) for a, b in zip(dev_idx, kd_idx))
    queries = sum(len(q) for _, q in pairs)
    t = {"device": [], "kdtree": [], "bf": []}
    for _ in range(repeats):
        t["device"].append(_timed(lambda: sdf.nearest_indices_many(pairs, "device"), device))
        t["kdtree"].append(_timed(lambda: [sdf.nearest_indices_kdtree(p, q) for p, q in pairs], device))
        t["bf"].append(_timed(lambda: [sdf.nearest_indices(p, q, "brute_mm") for p, q in pairs[:bf_images]], device))
    med = {k: statistics.median(v) for k, v in t.items()}
    n = len(pairs)
    return {"search_images": n, "search_queries": queries, "search_points": int(np.mean([len(p) for p, _ in pairs])),
            "search_agree": agree, "search_device_s": med["device"], "search_kdtree_s": med["kdtree"],
            "search_brute_mm_s": med["bf"] * n / bf_images, "search_brute_mm_measured_images": bf_images,
            "search_device_per_field_ms": 1e3 * med["device"] / n,
            "search_kdtree_per_field_ms": 1e3 * med["kdtree"] / n,
            "search_device_vs_kdtree": med["device"] / med["kdtree"],
            "search_repeats": repeats}


def load_batch(batch: int, size: int, device, data: str = "synthetic") -> dict:
    """``batch`` rendered frames (image, depth, K) at size x size from a small synthetic dataset
    (``data="analytic"``: :func:`analytic_batch`)."""
    if data == "analytic":
        return analytic_batch(batch, size, device)
    from geodepth_lite.data.datasets import SyntheticDepthDataset
    from geodepth_lite.data.synth import ensure_dataset

    overrides = {"camera": {"width": size, "height": size}, "splits": {"train": batch, "val": 1, "test": 1}}
    root = ensure_dataset("scenario_smoke", overrides=overrides, progress=False)
    ds = SyntheticDepthDataset(root, "train")
    items = [ds[i] for i in range(batch)]
    return {k: torch.stack([it[k] for it in items]).to(device) for k in ("image", "depth", "K")}


def fake_prediction(gt: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """gt times a smooth random factor in about [0.9, 1.1] (a plausible network error)."""
    g = torch.Generator().manual_seed(seed)
    B, _, H, W = gt.shape
    coarse = torch.rand(B, 1, 5, 5, generator=g) * 0.2 - 0.1
    factor = 1.0 + torch.nn.functional.interpolate(coarse, size=(H, W), mode="bicubic", align_corners=True)
    return (gt * factor.to(gt.device)).contiguous()


def sdf_step(pred0, gt, K, grid, method, cache=None):
    pred = pred0.clone().requires_grad_()
    losses.sdf_loss(pred, gt, K, sdf.SDFOptions(grid=grid, method=method, cache=cache)).backward()


class _GivenNearest:
    """Replays the nearest points a first search found (for timing everything but the search): patches
    ``sdf.nearest_indices_many`` (the per-image loss's search) and passes ``nearest`` to the batched one."""

    def __init__(self):
        self.found = None

    def __call__(self, pairs, method="auto"):
        if self.found is None:
            self.found = _SEARCH_MANY(pairs, method)
        return self.found


_SEARCH_MANY = sdf.nearest_indices_many


def run_compare(gt, K, pred0, grid, repeats, dev, method) -> dict:
    """Medians of the whole SDF loss, forward and backward, batched and per image, side by side."""
    g3 = (grid,) * 3
    ids = [("bench", i) for i in range(gt.shape[0])]
    c_ref, c_new = sdf.GTFieldCache(), sdf.GTFieldCache()
    f0 = sdf.sdf_fields_batched(pred0, gt, K, sdf.SDFOptions(grid=g3, method=method, cache=c_new),
                                frame_ids=ids)  # fills c_new
    nearest = sdf.nearest_indices_grid(sdf.camera.backproject(pred0, K), (gt > 0).reshape(gt.shape[0], -1),
                                       f0["grid"], method)
    given = _GivenNearest()

    def step(fn, cache, **kw):
        p = pred0.clone().requires_grad_()
        fn(p, gt, K, sdf.SDFOptions(grid=g3, method=method, cache=cache), **kw).backward()

    def ref_given():
        sdf.nearest_indices_many = given
        try:
            step(losses.sdf_loss_reference, c_ref)
        finally:
            sdf.nearest_indices_many = _SEARCH_MANY

    def new_given():
        p = pred0.clone().requires_grad_()
        f = sdf.sdf_fields_batched(p, gt, K, sdf.SDFOptions(grid=g3, method=method, cache=c_new), frame_ids=ids,
                                   nearest=nearest)
        losses.sdf_loss_from_fields(f, p).backward()

    runs = {"ref": lambda: step(losses.sdf_loss_reference, None),
            "new": lambda: step(losses.sdf_loss, None),
            "ref_cached": lambda: step(losses.sdf_loss_reference, c_ref),
            "new_cached": lambda: step(losses.sdf_loss, c_new, frame_ids=ids),
            "ref_given": ref_given, "new_given": new_given}
    runs["ref_cached"]()  # fills c_ref
    ref_given()  # records the per-image search's answers
    t = {k: [] for k in runs}
    for _ in range(repeats):  # interleaved, so machine load affects all alike
        for k, fn in runs.items():
            t[k].append(_timed(fn, dev))
    med = {k: statistics.median(v) for k, v in t.items()}
    out = {f"compare_{k}_s": v for k, v in med.items()}
    for k in ("", "_cached", "_given"):
        out[f"compare_ratio{k}"] = med[f"ref{k}"] / med[f"new{k}"]
    out["compare_times"] = t
    return out


def report_compare(res: dict) -> str:
    b, s, g = res["batch"], res["size"], res["grid"]
    lines = [f"Whole SDF loss (forward + backward) on {res['device']} ({res['torch_threads']} torch threads, "
             f"cKDTree workers {sdf.KDTREE_WORKERS}, search {res['index_method']}), {res['data']} frames, batch {b}, "
             f"{s}x{s}, {g}^3 grid, medians of {res['repeats']} interleaved repeats",
             f"  {'':44s} {'per image (former)':>18s} {'batched':>10s} {'ratio':>8s}"]
    for k, name in (("", "no ground-truth cache"), ("_cached", "ground-truth fields cached"),
                    ("_given", "cached, nearest points given (no search)")):
        lines.append(f"  {name:44s} {res[f'compare_ref{k}_s']:16.3f} s {res[f'compare_new{k}_s']:8.3f} s "
                     f"{res[f'compare_ratio{k}']:7.2f} x")
    return "\n".join(lines)


def run(batch=20, size=320, grid=32, repeats=3, bf_images=1, device="auto", train_step=True, seed=0,
        data="synthetic", search_only=False, compare=False) -> dict:
    """Run the benchmark; returns a dict of median seconds and the derived ratios.

    The SDF loss and the training step are timed twice: without the ground-truth field cache
    (every field searched: the first epoch) and with it warm (later epochs: only the
    prediction's field is searched; :class:`geodepth_lite.core.sdf.GTFieldCache`).
    """
    dev = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device)
    utils.seed_everything(seed)
    frames = load_batch(batch, size, dev, data)
    gt, K, image = frames["depth"], frames["K"], frames["image"]
    if search_only or compare:
        return run_apart(gt, K, grid, repeats, bf_images, dev, data, seed, compare)
    pred = fake_prediction(gt, seed)
    g3 = (grid, grid, grid)
    index = sdf.resolve_method("auto", dev)
    res = {"device": str(dev), "batch": batch, "size": size, "grid": grid, "repeats": repeats,
           "index_method": index, "bf_images": bf_images, "torch_threads": torch.get_num_threads()}
    cache = sdf.GTFieldCache()
    # total_loss reads sdf.GT_FIELD_CACHE (the default SDFOptions' cache, bound when sdf is imported):
    # rebinding the name would not reach it, so the uncached step switches that object off instead
    gt_cache = sdf.GT_FIELD_CACHE
    model = opt = None
    if train_step:
        model = DepthNet().to(dev)
        opt = torch.optim.Adam(model.parameters(), lr=1e-4, betas=(0.9, 0.999), weight_decay=0.01)

    def train_once(use_cache):
        saved_max_bytes = gt_cache.max_bytes
        gt_cache.max_bytes = saved_max_bytes if use_cache else 0
        try:
            model.train()
            p = model(image)
            loss, _ = losses.total_loss(p, gt, image, K, losses.LossSpec(sdf=sdf.SDFOptions(grid=g3)))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        finally:
            gt_cache.max_bytes = saved_max_bytes

    t = {k: [] for k in ("sdf", "sdf_cached", "bf", "step", "step_cached")}
    sdf_step(pred, gt, K, g3, index, cache)  # warm-ups (this also fills the cache)
    if train_step:
        train_once(False)
        train_once(True)  # fills the ground-truth field cache for the cached steps
    for _ in range(repeats):  # interleaved, so machine load affects all alike
        t["sdf"].append(_timed(lambda: sdf_step(pred, gt, K, g3, index, None), dev))
        t["sdf_cached"].append(_timed(lambda: sdf_step(pred, gt, K, g3, index, cache), dev))
        t["bf"].append(_timed(lambda: sdf_step(pred[:bf_images], gt[:bf_images], K[:bf_images], g3, "brute_mm"), dev))
        if train_step:
            t["step"].append(_timed(lambda: train_once(False), dev))
            t["step_cached"].append(_timed(lambda: train_once(True), dev))
    med = {k: statistics.median(v) for k, v in t.items() if v}
    res.update(sdf_s=med["sdf"], sdf_cached_s=med["sdf_cached"], brute_force_measured_s=med["bf"],
               brute_force_s=med["bf"] * batch / bf_images, speedup_vs_brute_force=med["bf"] * batch / bf_images
               / med["sdf"])
    if train_step:
        res.update(step_figures(res, med, model, image, repeats, dev))
    return res


def step_figures(res: dict, med: dict, model, image, repeats: int, dev) -> dict:
    """The training step's medians, the SDF share of a step, and inference frames/s."""
    out = {"train_step_s": med["step"], "train_step_cached_s": med["step_cached"],
           "sdf_fraction_of_step": res["sdf_s"] / med["step"],
           "sdf_cached_fraction_of_step": res["sdf_cached_s"] / med["step_cached"]}
    model.eval()
    with torch.no_grad():
        inf_t = [_timed(lambda: model(image), dev) for _ in range(repeats)]
    out["inference_fps"] = image.shape[0] / statistics.median(inf_t)
    return out


def run_apart(gt, K, grid: int, repeats: int, bf_images: int, dev, data: str, seed: int, compare: bool) -> dict:
    """``--search`` (the nearest-point search alone) or ``--compare`` (the whole SDF loss, batched and per
    image) on the batch ``gt``, ``K``."""
    res = {"device": str(dev), "batch": gt.shape[0], "size": gt.shape[-1], "grid": grid, "data": data,
           "torch_threads": torch.get_num_threads()}
    if not compare:
        res["kdtree_workers"] = sdf.KDTREE_WORKERS
        res.update(run_search(search_inputs(gt, K, grid), repeats, bf_images, dev))
        return res
    index = sdf.resolve_method("auto", dev)
    res.update(repeats=repeats, index_method=index)
    res.update(run_compare(gt, K, fake_prediction(gt, seed), grid, repeats, dev, index))
    return res


def report_search(res: dict) -> str:
    n, s, g = res["search_images"], res["size"], res["grid"]
    return "\n".join([
        f"Nearest-point search on {res['device']} ({res['torch_threads']} torch threads, cKDTree workers "
        f"{res['kdtree_workers']}), {res['data']} depth maps, {n} images {s}x{s} ({res['search_points']} points "
        f"each), {g}^3 bounding-box grid ({res['search_queries'] // n} queries each), "
        f"medians of {res['search_repeats']}",
        f"  device search (batched, torch ops):   {res['search_device_s']:8.3f} s  "
        f"({res['search_device_per_field_ms']:.1f} ms per field)",
        f"  cKDTree:                              {res['search_kdtree_s']:8.3f} s  "
        f"({res['search_kdtree_per_field_ms']:.1f} ms per field)",
        f"  matrix-product brute force:           {res['search_brute_mm_s']:8.3f} s  "
        f"(measured on {res['search_brute_mm_measured_images']} image(s), scaled linearly to {n})",
        f"  device search / cKDTree:              {res['search_device_vs_kdtree']:8.2f} x",
        f"  agreement with cKDTree:               {res['search_agree']} of {res['search_queries']} queries",
    ])


def report(res: dict) -> str:
    if "compare_ratio" in res:
        return report_compare(res)
    if "sdf_s" not in res:
        return report_search(res)
    b, s, g = res["batch"], res["size"], res["grid"]
    lines = [
        f"SDF loss benchmark on {res['device']} ({res['torch_threads']} torch threads, cKDTree workers "
        f"{sdf.KDTREE_WORKERS}), batch {b}, {s}x{s}, "
        f"{g}^3 grid, medians of {res['repeats']} repeats",
        f"  SDF loss fwd+bwd, exact spatial index ({res['index_method']}):        {res['sdf_s']:8.2f} s",
        f"  SDF loss fwd+bwd, ground-truth fields cached (epoch >= 2): {res['sdf_cached_s']:8.2f} s",
        f"  SDF loss fwd+bwd, chunked brute force (cdist):         {res['brute_force_s']:8.2f} s "
        f"(measured {res['brute_force_measured_s']:.2f} s on {res['bf_images']} image(s), scaled linearly to {b})",
        f"  speed-up over brute force (no cache):                  {res['speedup_vs_brute_force']:8.1f} x   "
        "(goal >= 50 x)",
    ]
    if "train_step_s" in res:
        lines += [
            f"  DepthNet training step (fwd, all losses, bwd, Adam):   {res['train_step_s']:8.2f} s "
            f"(ground-truth fields cached: {res['train_step_cached_s']:.2f} s)",
            f"  SDF share of a training step, first epoch:             {100 * res['sdf_fraction_of_step']:8.1f} %   "
            "(goal <= 15 %)",
            f"  SDF share of a training step, later epochs (cached):   "
            f"{100 * res['sdf_cached_fraction_of_step']:8.1f} %",
            f"  DepthNet inference at {s}x{s}:                        {res['inference_fps']:8.1f} frames/s (batch {b})",
        ]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/bench_sdf.py", description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=20, help="images per batch (paper: 20)")
    ap.add_argument("--size", type=int, default=320, help="image height = width (paper: 320)")
    ap.add_argument("--grid", type=int, default=32, help="SDF samples per axis (paper: 32)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats; medians are reported")
    ap.add_argument("--bf-images", type=int, default=1, help="images timed with brute force (scaled to --batch)")
    ap.add_argument("--device", default="auto", help="auto | cpu | cuda")
    ap.add_argument("--no-train-step", action="store_true", help="skip the training-step and inference timing")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads and cKDTree workers "
                         "(0: torch's default; 1 gives stable figures on a busy machine)")
    ap.add_argument("--json", default="", help="also write the figures to this JSON file")
    ap.add_argument("--data", choices=("synthetic", "analytic"), default="synthetic",
                    help="rendered frames of the synthetic dataset, or analytic views (no VTK)")
    ap.add_argument("--search", action="store_true",
                    help="time the nearest-point search alone: device search, cKDTree, brute force")
    ap.add_argument("--compare", action="store_true",
                    help="time the whole SDF loss, batched beside the former per-image form")
    a = ap.parse_args(argv)
    for name in ("batch", "size", "grid", "repeats", "bf_images"):
        if getattr(a, name) < 1:
            raise SystemExit(f"error: --{name.replace('_', '-')} must be >= 1")
    if a.size % 32:
        raise SystemExit("error: --size must be a multiple of 32")
    if not 1 <= a.bf_images <= a.batch:
        raise SystemExit("error: --bf-images must be between 1 and --batch")
    if a.threads < 0:
        raise SystemExit("error: --threads must be >= 0")
    if a.threads:
        torch.set_num_threads(a.threads)
        sdf.KDTREE_WORKERS = a.threads
    res = run(a.batch, a.size, a.grid, a.repeats, a.bf_images, a.device, not a.no_train_step, data=a.data,
              search_only=a.search, compare=a.compare)
    print(report(res))
    if a.json:
        finite = {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in res.items()}
        utils.write_json_atomic(a.json, finite)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

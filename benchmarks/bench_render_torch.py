"""Speed of the torch renderer's dataset pipeline, stage by stage (docs/dataset.md, "Renderer speed").

``python benchmarks/bench_render_torch.py [--manifest scenario_paper] [--scenes 2] [--device cpu] [--vtk]`` times,
on one thread, per scene of the manifest's train split: building the tube and its texture; per frame the pose;
the rest of the draws (exposure rays cast in one batch on the device, lights, appearance record); the batched
render of the scene's frames; the appearance step; the PNG and .npy encoding; with ``--vtk``, VTK rendering the
same frames one by one. Prints medians over the scenes (ms per frame, or per scene)."""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from geodepth_lite.data import appearance as ap
from geodepth_lite.data import images, synth
from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render as rd
from geodepth_lite.data import render_torch as rt
from geodepth_lite.data import tube as tb


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def time_scene(m: dict, scene: dict, renderer: rt.TorchRenderer, vtk=None) -> dict:
    """Seconds of each stage for one planned scene of the train split (and VTK's render of the same frames)."""
    t = {}
    t0 = time.perf_counter()
    tube = tb.build_tube(m["organ_presets"][scene["organ"]], scene["tube_seed"], m["resolution"])
    texture = synth.scene_texture(m, "train", scene)
    renderer.set_tube(tube, texture)
    t["scene setup"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    path = mf.split_path(m, "train")
    rngs = [synth.frame_rng(m, "train", scene["scene"], i) for i, _ in scene["frames"]]
    poses = [rd.sample_pose(tube, rng, path) for rng in rngs]
    t["poses"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    frames = synth.scene_draws(m, "train", scene, tube, renderer, rngs, poses)
    _sync(renderer.device)
    t["exposure+draws"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rgbs, depths = renderer.render_batch([f["T_world_cam"] for f in frames], [f["lights"] for f in frames],
                                         [f["tint"] for f in frames],
                                         [{k: m["lighting_sets"][n][k] for k in rd.MATERIAL_KEYS}
                                          for _, n in scene["frames"]])
    _sync(renderer.device)
    rgbs, depths = rgbs.cpu().numpy(), depths.cpu().numpy()
    t["render"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    finals = [ap.apply_appearance(rgb, f["appearance"]) for rgb, f in zip(rgbs, frames)]
    t["appearance"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    for rgb, depth in zip(finals, depths):
        images.encode_png(rgb, compress_level=1)  # as synth writes a frame
        images.encode_npy(depth)
    t["encode"] = time.perf_counter() - t0
    if vtk is not None:  # the same frames by VTK, one at a time (its scene set-up not counted)
        vtk.set_tube(tube, texture)
        t0 = time.perf_counter()
        for f, (_, name) in zip(frames, scene["frames"]):
            vtk.set_material({k: m["lighting_sets"][name][k] for k in rd.MATERIAL_KEYS})
            vtk.set_tint(f["tint"])
            vtk.render(f["T_world_cam"], f["lights"])
        t["vtk render"] = time.perf_counter() - t0
    return {k: v / (1 if k == "scene setup" else len(frames)) for k, v in t.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--manifest", default="scenario_paper")
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--vtk", action="store_true", help="also time VTK rendering the same frames")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    m = mf.load_manifest(args.manifest)
    c = m["camera"]
    dev = torch.device(args.device)
    renderer = rt.TorchRenderer(c["width"], c["height"], mf.intrinsics_of(m), near=c["near"], far=c["far"],
                                device=dev)
    plan = synth.scene_plan(m, "train")
    picks = [plan[k * len(plan) // args.scenes] for k in range(args.scenes)]
    vtk = rd.Renderer(c["width"], c["height"], mf.intrinsics_of(m), near=c["near"], far=c["far"]) if args.vtk else None
    time_scene(m, picks[0], renderer, vtk)  # warm-up
    rows = [time_scene(m, scene, renderer, vtk) for scene in picks]
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    per_frame = sum(v for k, v in med.items() if k not in ("scene setup", "vtk render"))
    print(f"{args.manifest} ({c['width']}x{c['height']}, {len(plan[0]['frames'])} frames per scene), {args.device}, "
          f"{args.threads} thread(s), median of {len(rows)} scenes ({', '.join(s['organ'] for s in picks)}):")
    for k, v in med.items():
        print(f"  {k:12s} {1e3 * v:8.1f} ms {'per scene' if k == 'scene setup' else 'per frame'}")
    if vtk is not None:
        print(f"  torch render / VTK render: {med['render'] / med['vtk render']:.2f}")
    print(f"  render alone: {1 / med['render']:.1f} frames/s; whole pipeline: "
          f"{1 / (per_frame + med['scene setup'] / len(plan[0]['frames'])):.1f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

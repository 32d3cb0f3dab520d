"""Renderer benchmark: frames/s at 320x320 for the colon preset (``python benchmarks/bench_render.py``).

Times what dataset generation does per frame once a scene is set up: sample a pose,
auto-exposure rays, lights, render, read back RGB + depth, and the appearance
post-process (``appearance.py``) with the recipe's settings. One scene (tube, texture)
is reused; the figure is the median over repeats of ``--frames`` frames each.
Scene set-up (tube mesh, texture) is reported separately.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def run(size: int = 320, frames: int = 60, repeats: int = 5, organ: str = "colon", seed: int = 0,
        resolution: dict | None = None) -> dict:
    """Returns {"fps": median frames/s, "fps_all": per-repeat list, "setup_s": scene set-up seconds, ...}.

    Uses the ``scenario_paper`` recipe (the one that renders 320x320 frames) at ``size``;
    ``resolution`` ({"n_theta", "ring_step"}) overrides its mesh resolution.
    """
    from geodepth_lite.data import appearance as ap
    from geodepth_lite.data import manifest as mf
    from geodepth_lite.data import render as rd
    from geodepth_lite.data import tube as tb

    overrides = {"camera": {"width": size, "height": size}}
    if resolution:
        overrides["resolution"] = resolution
    m = mf.load_manifest("scenario_paper", overrides)
    K = mf.intrinsics_of(m)
    lighting = m["lighting_sets"][m["lightings"][0]]
    t0 = time.perf_counter()
    tube = tb.build_tube(m["organ_presets"][organ], seed, m["resolution"])
    rng = np.random.default_rng(seed)
    texture = rd.make_texture(m["texture_sets"][m["textures"][0]], rng)
    renderer = rd.Renderer(size, size, K)
    renderer.set_tube(tube, texture, {k: lighting[k] for k in ("ambient", "diffuse", "specular", "specular_power")})
    setup = time.perf_counter() - t0
    fps = []
    try:
        for rep in range(repeats + 1):
            t = time.perf_counter()
            for _ in range(frames):
                T, _ = rd.sample_pose(tube, rng, mf.split_path(m, "train"))
                lights, tint = rd.sample_lighting(lighting, rng, float(tube.preset["radius"]),
                                                  rd.exposure_distance(tube, T, K, size, size))
                look = ap.sample_appearance(m["appearance"], rng)
                renderer.set_tint(tint)
                rgb, _depth = renderer.render(T, lights)
                ap.apply_appearance(rgb, look)
            if rep > 0:  # the first repeat warms up caches and the GL pipeline
                fps.append(frames / (time.perf_counter() - t))
    finally:
        renderer.close()
    return {"fps": statistics.median(fps), "fps_all": fps, "setup_s": setup, "triangles": tube.mesh.n_cells,
            "resolution": m["resolution"]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/bench_render.py", description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=320, help="image width = height (pixels)")
    p.add_argument("--frames", type=int, default=60, help="frames per repeat")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (median reported)")
    p.add_argument("--organ", default="colon", help="organ preset")
    p.add_argument("--n-theta", type=int, default=None, help="points per ring (default: the recipe's)")
    p.add_argument("--ring-step", type=float, default=None, help="ring spacing / radius (default: the recipe's)")
    args = p.parse_args(argv)
    res = {k: v for k, v in (("n_theta", args.n_theta), ("ring_step", args.ring_step)) if v is not None}
    r = run(args.size, args.frames, args.repeats, args.organ, resolution=res or None)
    mesh = r["resolution"]
    print(f"{args.organ} {args.size}x{args.size}, mesh {mesh['n_theta']} x {mesh['ring_step']} R, "
          f"{r['triangles']} triangles: {r['fps']:.1f} frames/s "
          f"(median of {args.repeats} x {args.frames} frames; "
          f"range {min(r['fps_all']):.1f}-{max(r['fps_all']):.1f}); "
          f"scene set-up {r['setup_s']:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

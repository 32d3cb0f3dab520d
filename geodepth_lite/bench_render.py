"""Renderer benchmark: frames/s at 320x320 for the colon preset (``python -m geodepth_lite.bench_render``).

Times what dataset generation does per frame once a scene is set up: sample a pose,
auto-exposure rays, lights, render, read back RGB + depth. One scene (tube, texture)
is reused; the figure is the median over repeats of ``--frames`` frames each.
Scene set-up (tube mesh, texture) is reported separately.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def run(size: int = 320, frames: int = 60, repeats: int = 5, organ: str = "colon", seed: int = 0) -> dict:
    """Returns {"fps": median frames/s, "fps_all": per-repeat list, "setup_s": scene set-up seconds}."""
    from . import synth
    from . import render as rd
    from . import tube as tb

    m = synth.load_manifest("scenario_paper", {"camera": {"width": size, "height": size}})
    K = synth.intrinsics_of(m)
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
                T, _ = rd.sample_pose(tube, rng, m["camera_path"])
                lights, tint = rd.sample_lighting(lighting, rng, float(tube.preset["radius"]),
                                                  rd.exposure_distance(tube, T, K, size, size))
                renderer.set_tint(tint)
                renderer.render(T, lights)
            if rep > 0:  # the first repeat warms up caches and the GL pipeline
                fps.append(frames / (time.perf_counter() - t))
    finally:
        renderer.close()
    return {"fps": statistics.median(fps), "fps_all": fps, "setup_s": setup, "triangles": tube.mesh.n_cells}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m geodepth_lite.bench_render", description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=320, help="image width = height (pixels)")
    p.add_argument("--frames", type=int, default=60, help="frames per repeat")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (median reported)")
    p.add_argument("--organ", default="colon", help="organ preset")
    args = p.parse_args(argv)
    r = run(args.size, args.frames, args.repeats, args.organ)
    print(f"{args.organ} {args.size}x{args.size}, {r['triangles']} triangles: {r['fps']:.1f} frames/s "
          f"(median of {args.repeats} x {args.frames} frames; range {min(r['fps_all']):.1f}-{max(r['fps_all']):.1f}); "
          f"scene set-up {r['setup_s']:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

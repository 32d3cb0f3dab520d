"""The torch renderer against VTK on a manifest's frames: the table of docs/dataset.md.

``python benchmarks/render_agreement.py [--manifest scenario_teach] [--split train] [--frames 60]``
renders the frames with both renderers on the CPU (one thread each) and prints per organ and in
all: the depth agreement share, the coverage mismatch, the mean absolute 8-bit differences
before and after the appearance step, each renderer's mean brightness, contrast and median depth,
and both renderers' milliseconds per frame.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render as rd
from geodepth_lite.data import render_agreement as ra
from geodepth_lite.data import render_torch as rt


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--manifest", default="scenario_teach")
    parser.add_argument("--split", default="train")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--json", default=None, help="also write the per-frame rows here")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    m = mf.load_manifest(args.manifest)
    c = m["camera"]
    inputs = ra.frame_inputs(m, args.split, args.frames)
    K = mf.intrinsics_of(m)
    t0 = time.perf_counter()
    with rd.Renderer(c["width"], c["height"], K, near=c["near"], far=c["far"]) as vr:
        vtk_frames = ra.render_with(vr, inputs)
    t1 = time.perf_counter()
    torch_frames = ra.render_with(rt.TorchRenderer(c["width"], c["height"], K, near=c["near"], far=c["far"],
                                                   device="cpu"), inputs)
    t2 = time.perf_counter()
    rows = ra.agreement(inputs, vtk_frames, torch_frames)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    print(f"{args.manifest} {args.split}, {len(rows)} frames; VTK {1e3 * (t1 - t0) / len(rows):.1f} ms/frame, "
          f"torch {1e3 * (t2 - t1) / len(rows):.1f} ms/frame (CPU, one thread; tube and texture changes included)")
    print("| frames | depth within 0.5% (min / mean) | coverage mismatch (max) | mean abs diff, render (mean / max) "
          "| mean abs diff, final (mean / max) | brightness VTK / torch | contrast VTK / torch "
          "| median depth VTK / torch |")
    print("|---|---|---|---|---|---|---|---|")
    for organ in sorted({r["organ"] for r in rows}) + ["all"]:
        sel = [r for r in rows if organ in ("all", r["organ"])]
        col = {k: np.array([r[k] for r in sel]) for k in ("depth_share", "coverage_mismatch", "mad_raw", "mad_final")}
        pair = {k: np.array([r[k] for r in sel]).mean(0) for k in ("brightness", "contrast", "depth_median")}
        print(f"| {organ} ({len(sel)}) | {100 * col['depth_share'].min():.2f}% / "
              f"{100 * col['depth_share'].mean():.3f}% | {100 * col['coverage_mismatch'].max():.3f}% | "
              f"{col['mad_raw'].mean():.2f} / {col['mad_raw'].max():.2f} | "
              f"{col['mad_final'].mean():.2f} / {col['mad_final'].max():.2f} | "
              f"{pair['brightness'][0]:.1f} / {pair['brightness'][1]:.1f} | "
              f"{pair['contrast'][0]:.1f} / {pair['contrast'][1]:.1f} | "
              f"{pair['depth_median'][0]:.3f} / {pair['depth_median'][1]:.3f} |")
    problems = ra.within_bounds(rows)
    print("within bounds" if not problems else "\n".join(problems))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

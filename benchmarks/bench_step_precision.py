"""The CPU's own speed levers on one training step: float32 against bfloat16 autocast and ``channels_last``.
``python benchmarks/bench_step_precision.py [--profile teach] [--case 4] [--frames 40] [--steps 30] [--repeats 3]``.

The step is the one ``train`` takes for the profile's ablation runs (64 px under ``teach``): the
profile's network, a batch of the profile's size from a dataset of the profile's manifest cut to
``--frames`` training frames (rendered into a folder of its own), forward, every loss term of the
case in float32, backward and the Adam step, on one thread, ground-truth SDF fields cached by frame
id as in training. Four variants: float32 (what ``teach`` trains), bfloat16 autocast of the forward
pass, ``channels_last`` memory format for the network and its input, and both. The variants take
turns within each repetition (A B C D, A B C D, ...), so a drift of the machine's speed reaches all
of them alike; each repetition times ``--steps`` steps (``--steps-bf16`` for the bfloat16 variants)
after one warm-up step, and the table gives the median over repetitions of each repetition's median
step time, with its ratio to float32.

It also reports how far each variant's loss in its first step lies from float32's, from the same
weights on the same batch: a variant that changes the numbers changes the trained models.
Nothing here changes how ``train`` trains.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

VARIANTS = {"fp32": (False, False), "bf16": (True, False), "channels_last": (False, True),
            "bf16+channels_last": (True, True)}


def load_batch(profile: str, case: int, frames: int) -> tuple[dict, dict, list]:
    """(the profile's configuration, one batch of its first training frames, their frame ids)."""
    from geodepth_lite.data import synth
    from geodepth_lite.data.datasets.synthetic import load_split
    from geodepth_lite.training import config, inference, train

    cfg = config.make_config(profile, case, 0)
    root = synth.ensure_dataset(cfg["dataset"], overrides={"splits": {"train": frames}}, progress=False)
    ds = load_split(root, "train", cfg["image_size"], cache=False)
    batch = inference.collate([ds[i] for i in range(min(cfg["batch_size"], len(ds)))])
    ids = train.batch_frame_ids(batch, train.frame_space(root, "train", cfg["image_size"]))
    return cfg, batch, ids


class Stepper:
    """One variant's network and optimizer, from the same initial weights as the others."""

    def __init__(self, net: torch.nn.Module, cfg: dict, batch: dict, ids: list, bf16: bool, channels_last: bool):
        self.net, self.cfg, self.ids, self.bf16 = copy.deepcopy(net), cfg, ids, bf16
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        self.net = self.net.to(memory_format=fmt)
        self.batch = dict(batch, image=batch["image"].contiguous(memory_format=fmt))
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg["lr"])
        self.first_loss = None  # the loss of its first step, from the weights every variant starts from

    def step(self) -> None:
        from geodepth_lite.training import train

        cast = torch.autocast("cpu", dtype=torch.bfloat16) if self.bf16 else contextlib.nullcontext()
        with cast:
            pred = self.net(self.batch["image"])
        loss, _ = train.compute_losses(pred, self.batch, self.cfg, self.ids)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        if self.first_loss is None:
            self.first_loss = float(loss.detach())


def measure(steppers: dict[str, Stepper], steps: dict[str, int], repeats: int) -> dict[str, list[float]]:
    """Per variant, each repetition's median seconds per step (variants interleaved per repetition)."""
    medians: dict[str, list[float]] = {name: [] for name in steppers}
    for _ in range(repeats):
        for name, s in steppers.items():
            s.step()  # warm-up
            times = []
            for _ in range(steps[name]):
                t0 = time.perf_counter()
                s.step()
                times.append(time.perf_counter() - t0)
            medians[name].append(statistics.median(times))
            print(f"repetition {len(medians[name])}, {name}: median {medians[name][-1] * 1e3:.1f} ms/step of "
                  f"{len(times)}", flush=True)
    return medians


def cpu_flags() -> dict:
    """The CPU's model name and the flags that decide native bfloat16 and matrix units."""
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")), "")
    flags = next((ln.split(":", 1)[1].split() for ln in text.splitlines() if ln.startswith("flags")), [])
    wanted = [f for f in flags if f.startswith(("avx512", "amx")) or f in ("avx2", "fma", "avx_vnni")]
    return {"model": model, "flags": wanted, "cores": os.cpu_count()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="teach")
    ap.add_argument("--case", type=int, default=4)
    ap.add_argument("--frames", type=int, default=40, help="training frames rendered for the batch")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--steps-bf16", type=int, default=None,
                    help="timed steps of the bfloat16 variants (default --steps): fewer where they are far slower")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
                    help="the variants to time (fp32 always among them: the ratios are over it)")
    ap.add_argument("--json", default=None, help="also write the record here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from geodepth_lite import utils
    from geodepth_lite.training import train

    cfg, batch, ids = load_batch(args.profile, args.case, args.frames)
    utils.seed_everything(0)
    net = train.build_network(cfg)
    net.train()
    chosen = ["fp32"] + [v for v in args.variants if v != "fp32"]
    steppers = {name: Stepper(net, cfg, batch, ids, *VARIANTS[name]) for name in chosen}
    load0 = os.getloadavg()[0]
    steps = {name: args.steps_bf16 if VARIANTS[name][0] and args.steps_bf16 else args.steps for name in chosen}
    medians = measure(steppers, steps, args.repeats)
    load1 = os.getloadavg()[0]
    base = statistics.median(medians["fp32"])
    record = {"profile": args.profile, "case": args.case, "image_size": cfg["image_size"],
              "batch_size": cfg["batch_size"], "threads": torch.get_num_threads(), "steps": steps,
              "repeats": args.repeats, "torch": torch.__version__, "cpu": cpu_flags(),
              "mkldnn_bf16": bool(getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: None)()),
              "load_1min": [round(load0, 2), round(load1, 2)], "variants": {}}
    print(f"{args.profile} Case {args.case}, {cfg['image_size']} px, batch {cfg['batch_size']}, one thread; "
          f"{args.repeats} repetitions of {steps} steps; load {load0:.2f} -> {load1:.2f}; CPU {record['cpu']}")
    print("| variant | median ms/step | per repetition | x fp32 | x fp32 per repetition | first step's loss "
          "| vs fp32 |")
    print("|---|---|---|---|---|---|---|")
    for name, s in steppers.items():
        med = statistics.median(medians[name])
        rel = abs(s.first_loss - steppers["fp32"].first_loss) / abs(steppers["fp32"].first_loss)
        paired = [m / b for m, b in zip(medians[name], medians["fp32"])]  # the same repetition: the same load
        record["variants"][name] = {"median_s": med, "repetitions_s": medians[name], "ratio": med / base,
                                    "paired_ratios": paired, "first_loss": s.first_loss, "loss_rel_diff": rel}
        print(f"| {name} | {med * 1e3:.1f} | {', '.join(f'{m * 1e3:.1f}' for m in medians[name])} | "
              f"{med / base:.2f} | {', '.join(f'{r:.2f}' for r in paired)} (median {statistics.median(paired):.2f}) "
              f"| {s.first_loss:.6g} | {rel:.2e} |")
    if args.json:
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Experiment: does more context at the image border help? Predict on a padded input, then crop.

    python benchmarks/exp_padded_input.py [--pad 16 32] [--modes reflect replicate]

No training: the teach profile's Case 4 models (seed 0; the ablation's 64 px one and the 96 px
one of ``predict``) see each validation image resized to their input size, padded by ``pad``
pixels on every side (``reflect`` mirrors the image, ``replicate`` repeats its edge), and the
prediction's middle is kept. If the border excess came from the missing context beyond the
image edge, this would lower the border error without raising the centre's. One row per model,
pad and mode is appended to ``benchmarks/tuning_log.jsonl`` (pad 0 is the plain prediction).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import checkpoint, config, evaluate, synth  # noqa: E402
from geodepth_lite.dataset import resize_image  # noqa: E402


def padded_predictor(model, size: int, pad: int, mode: str):
    """images B x 3 x H x W -> depth B x 1 x H x W predicted on the ``pad``-padded resized image."""
    def predict(images: torch.Tensor) -> torch.Tensor:
        H, W = images.shape[-2:]
        x = resize_image(images.float(), (size, size))
        if pad:
            x = F.pad(x, (pad,) * 4, mode=mode)
        depth = model(x).float()[..., pad:pad + size, pad:pad + size]  # (B, 1, size, size)
        return F.interpolate(depth, size=(H, W), mode="bilinear", align_corners=False)

    return predict


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pad", type=int, nargs="+", default=[16, 32], help="pixels added on every side (network input)")
    ap.add_argument("--modes", nargs="+", default=["reflect", "replicate"], choices=["reflect", "replicate"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--log", default=str(network_experiment.LOG))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    prof = config.get_profile("teach")
    sizes = sorted({prof["image_size"], prof["predict_image_size"]})
    for size in sizes:
        ckpt = checkpoint.ensure_checkpoint("teach", 4, 0, image_size=size)
        model, cfg = checkpoint.load_model(ckpt)
        val = evaluate.open_eval_dataset(cfg["dataset"], split="val")
        for pad, mode in [(0, "none")] + [(p, m) for p in args.pad for m in args.modes]:
            predict = padded_predictor(model, size, pad, mode)
            with torch.no_grad():
                result = evaluate.evaluate_predictor(predict, val, error_maps=0)
                row = {"name": f"teach_c4_size{size}_pad{pad}_{mode}", "case": 4, "seed": 0,
                       "settings": {"image_size": size}, "inference": f"input padded by {pad} px ({mode}), cropped",
                       "val_abs_rel": round(result["overall"]["abs_rel"], 4),
                       "val_rmse": round(result["overall"]["rmse"], 4)}
                row |= network_experiment.border_scores(predict, val)
            row |= {"generator": synth.GENERATOR_VERSION, "note": "no training: the teach checkpoint"}
            network_experiment.append_row(row, args.log)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

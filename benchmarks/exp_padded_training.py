"""Experiment: train on a padded input, so that no real pixel sits at the edge of the network's input.

    python benchmarks/exp_padded_training.py NAME [--pad 16] [--mode reflect] [--set image_size=96] [--seed 0]

``benchmarks/exp_border_context.py`` shows that a pixel predicted at the edge of the input gets
about 1.5x the error it gets inside the frame, whatever it shows, and ``exp_padded_input.py``
that padding the input at test time only evens the border out by raising the centre's error
(the network was never shown a padded frame). Here the network pads every input by ``pad``
pixels on each side (``reflect`` mirrors the image, ``replicate`` repeats its edge), runs on
the larger input and returns the middle, in training and in prediction alike, so it learns to
use the mirrored context. The parameters are DepthNet's; the step costs
((size + 2 pad) / size)^2 times as much. Trained and scored as in ``network_experiment.py``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import model  # noqa: E402

BaseDepthNet = model.DepthNet


def padded_network(pad: int, mode: str):
    """A DepthNet class whose forward pads the image by ``pad`` px (``mode``) and crops the depth back."""
    if pad < 0 or (2 * pad) % model.STRIDE:
        raise ValueError(f"pad must be a non-negative multiple of {model.STRIDE // 2}, got {pad}")

    class PaddedDepthNet(BaseDepthNet):
        def forward(self, image: torch.Tensor) -> torch.Tensor:
            self.check_input(image)
            if not pad:
                return super().forward(image)
            H, W = image.shape[-2:]
            depth = super().forward(F.pad(image, (pad,) * 4, mode=mode))
            return depth[..., pad:pad + H, pad:pad + W]

    return PaddedDepthNet


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(add_help=False)
    ap.add_argument("--pad", type=int, default=16)
    ap.add_argument("--mode", default="reflect", choices=["reflect", "replicate"])
    args, rest = ap.parse_known_args(argv)
    return network_experiment.run(padded_network(args.pad, args.mode),
                                  f"input padded by {args.pad} px ({args.mode}) in training and prediction, "
                                  "depth cropped back", rest, __doc__)


if __name__ == "__main__":
    raise SystemExit(main())

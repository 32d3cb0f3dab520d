"""Experiment: train on a mirrored input, so that no real pixel sits at the edge of the network's input.

    python benchmarks/exp_padded_training.py NAME [--pad 16] [--set image_size=96] [--set border_weight=2] [--seed 0]

``benchmarks/exp_border_context.py`` shows that a pixel predicted at the edge of the input gets
about 1.5x the error it gets inside the frame, whatever it shows, and ``exp_padded_input.py``
that mirroring the input at test time only evens the border out by raising the centre's error
(the network was never shown a mirrored frame). Here the network mirrors every input by ``pad``
pixels on each side, runs on the larger input and returns the middle, in training and in
prediction alike (``model.DepthNet(input_pad=pad)``), so it learns to use the mirrored context.
The parameters are DepthNet's; the network's compute grows by ((size + 2 pad) / size)^2.
Trained and scored as in ``network_experiment.py`` (the rows of ``config.VIEW_EVIDENCE`` named
``g3_c4_size96_pad*``); ``tune_teach.py --set input_pad=16`` trains the same weights.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import model  # noqa: E402

BaseDepthNet = model.DepthNet


def padded_network(pad: int):
    """The DepthNet class with ``input_pad=pad`` whatever its caller asks (train.fit, checkpoint.load_model)."""
    class PaddedDepthNet(BaseDepthNet):
        def __init__(self, *args, **kwargs):
            kwargs["input_pad"] = pad
            super().__init__(*args, **kwargs)

    return PaddedDepthNet


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(add_help=False)
    ap.add_argument("--pad", type=int, default=16)
    args, rest = ap.parse_known_args(argv)
    return network_experiment.run(padded_network(args.pad),
                                  f"input padded by {args.pad} px (reflect) in training and prediction, "
                                  "depth cropped back", rest, __doc__)


if __name__ == "__main__":
    raise SystemExit(main())

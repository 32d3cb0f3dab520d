"""Experiment: does partial-convolution padding remove the border bias?

    python benchmarks/exp_partial_padding.py NAME [--set image_size=96] [--case 4] [--seed 0]

A zero-padded 3x3 convolution sums fewer real inputs at the image border than inside it, so its
response there is weaker, and the network must learn to undo that. Partial-convolution padding
(Liu et al., 2018, "Partial Convolution based Padding") rescales each output by
kernel area / number of real inputs under the window: a constant image gives the same response
at the border as inside. Every zero-padded convolution of DepthNet (encoder, attention, decoder,
head) is rescaled so; the parameters are unchanged. Trained and scored as in
``network_experiment.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import model  # noqa: E402

BaseDepthNet = model.DepthNet


class PartialConv2d(nn.Conv2d):
    """nn.Conv2d whose zero-padded border outputs are rescaled by window area / real inputs."""

    def border_scale(self, x: torch.Tensor) -> torch.Tensor:
        """1 x 1 x H' x W': kernel area / count of real (non-padding) inputs under each window."""
        key = (tuple(x.shape[-2:]), x.device, x.dtype)
        if getattr(self, "_scale_key", None) != key:
            ones = torch.ones(1, 1, *x.shape[-2:], device=x.device, dtype=x.dtype)
            kernel = torch.ones(1, 1, *self.kernel_size, device=x.device, dtype=x.dtype)
            count = F.conv2d(ones, kernel, stride=self.stride, padding=self.padding, dilation=self.dilation)
            self._scale = (kernel.numel() / count).detach()
            self._scale_key = key
        return self._scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.conv2d(x, self.weight, None, self.stride, self.padding, self.dilation, self.groups)
        y = y * self.border_scale(x)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)


class PartialPaddingDepthNet(BaseDepthNet):
    """DepthNet with partial-convolution padding in every zero-padded convolution."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        for m in self.modules():
            if type(m) is nn.Conv2d and any(p > 0 for p in m.padding) and m.padding_mode == "zeros":
                m.__class__ = PartialConv2d


def main(argv=None) -> int:
    return network_experiment.run(PartialPaddingDepthNet, "partial-convolution padding in every padded convolution",
                                  argv, __doc__)


if __name__ == "__main__":
    raise SystemExit(main())

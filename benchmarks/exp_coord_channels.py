"""Experiment: does telling the network where each pixel is remove the border error?

    python benchmarks/exp_coord_channels.py NAME [--set image_size=96] [--case 4] [--seed 0]

A zero-padded network can only infer a pixel's position from the padding, yet position matters
for depth: the rendered depth is z-depth, while the light of the co-located lamp falls off with
the distance along the ray, which is z / cos(angle) and about 35% longer at the image border
than at the centre (84 degree field of view). CoordConv (Liu et al., 2018) gives the first
convolution two more input channels, the pixel's normalised x and y in [-1, 1], so the network
can map shading to z-depth per position instead of learning it from the padding. The RGB
weights are initialised as DepthNet's; the two new input channels start at zero. Trained and
scored as in ``network_experiment.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import model  # noqa: E402

BaseDepthNet = model.DepthNet


def coordinate_channels(batch: int, height: int, width: int, like: torch.Tensor) -> torch.Tensor:
    """B x 2 x H x W: each pixel centre's x and y, from -1 (left/top edge) to 1 (right/bottom edge)."""
    ys = (torch.arange(height, device=like.device, dtype=like.dtype) + 0.5) / height * 2 - 1
    xs = (torch.arange(width, device=like.device, dtype=like.dtype) + 0.5) / width * 2 - 1
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack((grid_x, grid_y)).unsqueeze(0).expand(batch, -1, -1, -1)


class CoordConv2d(nn.Conv2d):
    """A convolution over its input plus two channels holding each pixel's x and y (CoordConv)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(torch.cat((x, coordinate_channels(x.shape[0], *x.shape[-2:], x)), dim=1))


class CoordDepthNet(BaseDepthNet):
    """DepthNet whose first convolution also sees the pixel coordinates (5 input channels)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        old = self.encoder.conv1
        conv = CoordConv2d(5, 64, 7, 2, 3, bias=False, padding_mode=old.padding_mode)
        with torch.no_grad():
            conv.weight.zero_()
            conv.weight[:, :3] = old.weight
        self.encoder.conv1 = conv


def main(argv=None) -> int:
    return network_experiment.run(CoordDepthNet, "CoordConv: x, y coordinate channels at the first convolution",
                                  argv, __doc__)


if __name__ == "__main__":
    raise SystemExit(main())

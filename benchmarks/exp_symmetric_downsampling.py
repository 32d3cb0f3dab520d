"""Experiment: does a downsampling that treats both image edges alike remove the border bias?

    python benchmarks/exp_symmetric_downsampling.py NAME [--set image_size=96] [--case 4] [--seed 0]

With padding 1 on even sizes, each stride-2 convolution and the max-pool of the ResNet18
encoder centre their windows on columns 0, 2, ..., W-2: they see the zero padding at the left
and top edges and never at the right and bottom, and the 1x1 stride-2 shortcuts skip the last
column. Here every stride-2 operation becomes its stride-1 version followed by 2x2 average
pooling (windows centred at 0.5, 2.5, ..., W-1.5: both edges alike), the same number of
parameters. Trained and scored as in ``network_experiment.py``; the package's network is not
changed: this is the measurement a change would start from.
"""

from __future__ import annotations

import sys
from pathlib import Path

from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import model  # noqa: E402

BaseDepthNet = model.DepthNet


def symmetric(conv: nn.Conv2d) -> nn.Sequential:
    """A stride-2 convolution as the same convolution at stride 1, then 2x2 average pooling."""
    conv.stride = (1, 1)
    return nn.Sequential(conv, nn.AvgPool2d(2))


class SymmetricDepthNet(BaseDepthNet):
    """DepthNet whose encoder downsamples by stride-1 operations and 2x2 average pooling."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        e = self.encoder
        e.conv1 = symmetric(e.conv1)
        e.maxpool = nn.Sequential(nn.MaxPool2d(3, 1, 1), nn.AvgPool2d(2))
        for layer in (e.layer2, e.layer3, e.layer4):
            block = layer[0]
            block.conv1 = symmetric(block.conv1)
            conv, bn = block.downsample
            conv.stride = (1, 1)
            block.downsample = nn.Sequential(nn.AvgPool2d(2), conv, bn)


def main(argv=None) -> int:
    return network_experiment.run(SymmetricDepthNet,
                                  "encoder downsampling: stride-1 operations + 2x2 average pooling (symmetric edges)",
                                  argv, __doc__)


if __name__ == "__main__":
    raise SystemExit(main())

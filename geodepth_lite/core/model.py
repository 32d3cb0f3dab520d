"""The depth network of Section 3.B: ResNet18 encoder + spatial attention block, skip-connected decoder.

Shape of the network (Manydepth/monodepth2-style, with the paper's modifications)::

    image B x 3 x H x W in [0, 1]
      -> ImageNet normalisation (inside the model)
      -> conv1 7x7/2, bn1, ReLU                      f0: 64  x H/2  x W/2
      -> spatial attention block (SAB): f0 * sigmoid(conv([mean_c f0, max_c f0]))
      -> maxpool, layer1                             f1: 64  x H/4  x W/4
      -> layer2                                      f2: 128 x H/8  x W/8
      -> layer3                                      f3: 256 x H/16 x W/16
      -> layer4                                      f4: 512 x H/32 x W/32
    decoder, for scale i = 4 .. 0:
      x = upconv(i, 0)(x)            3x3 conv + BatchNorm + LeakyReLU
      x = upsample x2 (nearest), concatenate skip f(i-1) when i > 0
      x = upconv(i, 1)(x)            3x3 conv + BatchNorm + LeakyReLU
    head: 3x3 conv -> sigmoid s -> depth = exp(log d_min + s (log d_max - log d_min))
      depth: B x 1 x H x W, between d_min = 0.01 and d_max = 100 (the dataset's range, Sec. 3.A),
      or the configured head_range (the paper profile: 0.1-40, set from the scenario data)

The head is this workbook's own: the paper does not say how its last layer turns features into
depth. A sigmoid mapped to log depth keeps every prediction positive.

The encoder keeps torchvision's ``resnet18`` parameter names (``conv1``, ``bn1``,
``layer1.0.conv1``, ..., ``layer2.0.downsample.0``, ...), so a user's ImageNet
state dict loads with :func:`load_encoder_weights` (its ``fc.*`` entries are ignored).
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict

import torch
import torch.nn as nn
import torch.nn.functional as F

from .camera import DEPTH_RANGE
from .errors import UserError

# smallest and largest depth the head can output: the scene's depth range, core/camera.py's (scene units; Sec. 3.A)
MIN_DEPTH, MAX_DEPTH = DEPTH_RANGE
IMAGENET_MEAN = (0.485, 0.456, 0.406)  # RGB mean of ImageNet, for images in [0, 1]
IMAGENET_STD = (0.229, 0.224, 0.225)  # RGB standard deviation of ImageNet
ENCODER_CHANNELS = (64, 64, 128, 256, 512)  # f0..f4
DECODER_CHANNELS = (16, 32, 64, 128, 256)  # decoder width at scales 0..4 (monodepth2)
STRIDE = 32  # total downsampling of the encoder: H and W must be multiples of it
LEAKY_SLOPE = 0.1  # negative slope of the decoder's leaky ReLU


def sigmoid_to_depth(s: torch.Tensor, min_depth: float = MIN_DEPTH, max_depth: float = MAX_DEPTH) -> torch.Tensor:
    """Map a sigmoid output s in (0, 1) to depth, uniformly in log-depth between min and max depth."""
    lo, hi = math.log(min_depth), math.log(max_depth)
    return torch.exp(lo + s * (hi - lo))


def depth_to_sigmoid(depth: torch.Tensor, min_depth: float = MIN_DEPTH, max_depth: float = MAX_DEPTH) -> torch.Tensor:
    """Inverse of :func:`sigmoid_to_depth` (for tests and plots)."""
    lo, hi = math.log(min_depth), math.log(max_depth)
    return (torch.log(depth) - lo) / (hi - lo)


def check_depth_range(depth_range) -> tuple[float, float]:
    """The head's (smallest, largest) depth: None = (MIN_DEPTH, MAX_DEPTH); else two finite numbers,
    0 < smallest < largest; a clear error otherwise."""
    if depth_range is None:
        return (MIN_DEPTH, MAX_DEPTH)
    try:
        lo, hi = (float(v) for v in depth_range)
    except (TypeError, ValueError):
        raise UserError(f"depth_range must be two numbers (smallest, largest depth), got {depth_range!r}") from None
    if not (0 < lo < hi < math.inf):
        raise UserError(f"depth_range must satisfy 0 < smallest < largest < inf, got {depth_range!r}")
    return (lo, hi)


# ----------------------------------------------------------------------------- encoder
class BasicBlock(nn.Module):
    """ResNet basic block (two 3x3 convs + identity/1x1 shortcut); torchvision's names."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.downsample = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(nn.Conv2d(in_ch, out_ch, 1, stride, bias=False), nn.BatchNorm2d(out_ch))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class SpatialAttention(nn.Module):
    """Spatial attention block of EndoSLAM (Ozyoruk et al. 2021), used at the ResNet input (Sec. 3.B).

    Pools the feature map over channels (mean and max), convolves the 2-channel map to one
    channel and gates the input with its sigmoid: ``x * sigmoid(conv([mean_c x, max_c x]))``.
    B x C x h x w -> B x C x h x w.
    """

    def __init__(self, kernel_size: int = 7):
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel_size, padding=kernel_size // 2, bias=False)

    def attention(self, x: torch.Tensor) -> torch.Tensor:
        """The gate, B x 1 x h x w in (0, 1)."""
        pooled = torch.cat((x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)), dim=1)
        return torch.sigmoid(self.conv(pooled))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.attention(x)


class ResNet18Encoder(nn.Module):
    """ResNet18 (He et al. 2016) without its classifier; returns the five feature maps f0..f4.

    Parameter names equal torchvision's ``resnet18`` (its ``fc`` is not part of this module).
    """

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")


# ----------------------------------------------------------------------------- decoder
class ConvBlock(nn.Module):
    """3x3 convolution followed by batch normalisation and leaky ReLU (Sec. 3.B's decoder unit)."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv = nn.Conv2d(in_ch, out_ch, 3, padding=1, bias=False)
        self.bn = nn.BatchNorm2d(out_ch)
        self.act = nn.LeakyReLU(LEAKY_SLOPE, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class DepthDecoder(nn.Module):
    """Upsampling decoder with a skip connection from the encoder at every scale (monodepth2 shape)."""

    def __init__(self, enc_ch=ENCODER_CHANNELS, dec_ch=DECODER_CHANNELS):
        super().__init__()
        self.upconvs = nn.ModuleDict()
        for i in range(4, -1, -1):
            in_ch = enc_ch[-1] if i == 4 else dec_ch[i + 1]
            self.upconvs[f"{i}_0"] = ConvBlock(in_ch, dec_ch[i])
            skip = enc_ch[i - 1] if i > 0 else 0
            self.upconvs[f"{i}_1"] = ConvBlock(dec_ch[i] + skip, dec_ch[i])
        self.head = nn.Conv2d(dec_ch[0], 1, 3, padding=1)

    def forward(self, feats: list[torch.Tensor], return_features: bool = False):
        """feats f0..f4 -> sigmoid map B x 1 x H x W (and the decoder features of scales 4..0)."""
        x = feats[-1]
        outs = []
        for i in range(4, -1, -1):
            x = self.upconvs[f"{i}_0"](x)
            x = F.interpolate(x, scale_factor=2.0, mode="nearest")
            if i > 0:
                x = torch.cat((x, feats[i - 1]), dim=1)
            x = self.upconvs[f"{i}_1"](x)
            outs.append(x)
        s = torch.sigmoid(self.head(x))
        return (s, outs) if return_features else s


# ----------------------------------------------------------------------------- the network
PADDINGS = ("zeros", "replicate")  # DepthNet.set_padding


class DepthNet(nn.Module):
    """Image B x 3 x H x W in [0, 1] -> z-depth B x 1 x H x W in ``depth_range`` (default (0.01, 100); Sec. 3.B).

    H and W must be multiples of 32. ``encoder_weights``: optional path to a torchvision
    ``resnet18`` state dict (ImageNet weights); see :func:`load_encoder_weights`.

    ``input_pad``: pixels of mirrored image added on every side before the network runs; the
    depth of the padded frame is cropped back to the image. No real pixel then sits at the edge
    of what the network sees (a multiple of 16, so the padded size stays a multiple of 32; 0 = off).
    The same parameters, ((H + 2 pad) / H)^2 times the compute. ``encode`` sees the image as given.
    """

    def __init__(self, encoder_weights: str | os.PathLike | None = None, padding: str = "zeros",
                 input_pad: int = 0, depth_range: tuple[float, float] | None = None):
        super().__init__()
        if isinstance(input_pad, bool) or not isinstance(input_pad, int) or input_pad < 0 or input_pad % (STRIDE // 2):
            raise ValueError(f"input_pad must be a non-negative multiple of {STRIDE // 2}, got {input_pad!r}")
        self.input_pad = input_pad
        self.depth_range = check_depth_range(depth_range)
        self.encoder = ResNet18Encoder()
        self.sab = SpatialAttention()
        self.decoder = DepthDecoder()
        self.set_padding(padding)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if encoder_weights is not None:
            load_encoder_weights(self.encoder, encoder_weights)

    def set_padding(self, mode: str) -> None:
        """How every padded convolution extends its input beyond the image border (PADDINGS).

        "zeros" (torchvision's and the paper's ResNet) shows the network a dark frame around
        every image, from which it can learn position-dependent depth (a near wall at the
        border); "replicate" repeats the edge pixels. No parameter changes.
        """
        if mode not in PADDINGS:
            raise ValueError(f"padding must be one of {', '.join(PADDINGS)}, got {mode!r}")
        self.padding = mode
        for m in self.modules():
            if isinstance(m, nn.Conv2d) and any(p > 0 for p in m.padding):
                m.padding_mode = mode

    @staticmethod
    def check_input(image: torch.Tensor) -> None:
        """Clear errors for inputs the network cannot take."""
        if not isinstance(image, torch.Tensor) or image.dim() != 4 or image.shape[1] != 3:
            shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
            raise ValueError(f"image must be a B x 3 x H x W tensor, got {shape}")
        H, W = image.shape[-2:]
        if H % STRIDE or W % STRIDE or H == 0 or W == 0:
            raise ValueError(
                f"image height and width must be positive multiples of {STRIDE}, got {H} x {W} "
                f"(resize, e.g. to {max(STRIDE, round(H / STRIDE) * STRIDE)} x "
                f"{max(STRIDE, round(W / STRIDE) * STRIDE)})"
            )

    def encode(self, image: torch.Tensor) -> list[torch.Tensor]:
        """The encoder's five feature maps f0..f4 (f0 after the spatial attention block)."""
        self.check_input(image)
        e = self.encoder
        x = (image - self.mean) / self.std
        f0 = self.sab(e.relu(e.bn1(e.conv1(x))))
        f1 = e.layer1(e.maxpool(f0))
        f2 = e.layer2(f1)
        f3 = e.layer3(f2)
        f4 = e.layer4(f3)
        return [f0, f1, f2, f3, f4]

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        pad = self.input_pad
        if not pad:
            return self.depth_from_sigmoid(self.decoder(self.encode(image)))
        self.check_input(image)
        H, W = image.shape[-2:]
        if pad >= min(H, W):
            raise ValueError(f"input_pad {pad} needs an image larger than {pad} px on each side, got {H} x {W}")
        padded = F.pad(image, (pad, pad, pad, pad), mode="reflect")  # mirrored, without repeating the edge
        return self.depth_from_sigmoid(self.decoder(self.encode(padded)))[..., pad:pad + H, pad:pad + W]

    def depth_from_sigmoid(self, s: torch.Tensor) -> torch.Tensor:
        """The head's sigmoid map to depth in this network's ``depth_range`` (:func:`sigmoid_to_depth`)."""
        return sigmoid_to_depth(s, *self.depth_range)


# ----------------------------------------------------------------------------- helpers
def load_encoder_weights(encoder: ResNet18Encoder, weights) -> None:
    """Load a torchvision ``resnet18`` state dict (path or dict) into ``encoder``.

    Accepts the plain state dict or one wrapped under ``"state_dict"``/``"model"``, with an
    optional ``"module."`` prefix; ``fc.*`` entries are ignored and ``num_batches_tracked``
    is optional. Any other missing, unexpected or wrongly shaped entry is a ValueError that
    names it.
    """
    if isinstance(weights, (str, os.PathLike)):
        if not os.path.isfile(weights):
            raise FileNotFoundError(f"encoder weights file not found: {weights}")
        try:
            state = torch.load(weights, map_location="cpu", weights_only=True)
        except Exception as exc:  # unreadable / not a torch file
            raise UserError(f"encoder weights {weights}: cannot read a torch state dict ({exc})") from None
    else:
        state = weights
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and key in state and isinstance(state[key], dict):
            state = state[key]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise UserError("encoder weights: expected a state dict of name -> tensor (torchvision resnet18)")
    state = OrderedDict((k[len("module."):] if k.startswith("module.") else k, v) for k, v in state.items())
    state = OrderedDict((k, v) for k, v in state.items() if not k.startswith("fc."))
    own = encoder.state_dict()
    unexpected = sorted(k for k in state if k not in own)
    missing = sorted(k for k in own if k not in state and not k.endswith("num_batches_tracked"))
    if unexpected or missing:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} (e.g. {', '.join(missing[:3])})")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)} (e.g. {', '.join(unexpected[:3])})")
        raise UserError("encoder weights do not match torchvision resnet18: " + "; ".join(parts))
    for k, v in state.items():
        if tuple(v.shape) != tuple(own[k].shape):
            raise UserError(f"encoder weights: {k} has shape {tuple(v.shape)}, expected {tuple(own[k].shape)}")
    encoder.load_state_dict(state, strict=False)


def count_parameters(module: nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters (elements) of a module."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)


def parameter_table(model: DepthNet) -> list[tuple[str, int]]:
    """(part, parameter count) rows for the encoder, the SAB, the decoder and the whole network."""
    return [
        ("encoder (ResNet18, no fc)", count_parameters(model.encoder)),
        ("spatial attention block", count_parameters(model.sab)),
        ("decoder", count_parameters(model.decoder)),
        ("total", count_parameters(model)),
    ]


@torch.no_grad()
def feature_shapes(model: DepthNet | None = None, height: int = 320, width: int = 320) -> dict[str, list[tuple]]:
    """Shapes (C, h, w) of the encoder features f0..f4 and the decoder outputs at scales 4..0.

    Runs one image through the network in eval mode (restoring the mode afterwards).
    """
    model = DepthNet() if model is None else model
    was_training = model.training
    model.eval()
    try:
        p = next(model.parameters())
        image = torch.zeros(1, 3, height, width, dtype=p.dtype, device=p.device)
        feats = model.encode(image)
        s, dec = model.decoder(feats, return_features=True)
    finally:
        model.train(was_training)
    return {
        "encoder": [tuple(f.shape[1:]) for f in feats],
        "decoder": [tuple(f.shape[1:]) for f in dec],
        "output": [tuple(s.shape[1:])],
    }

"""TaxiNet networks and their image preprocessing (shared by training and the
`TaxiNet` LeafSystem, so both see exactly the same input).

Images enter as uint8 ``(N, H, W, 3)`` RGB tensors of any size; crops are given as
fractions of the image so one checkpoint states what it needs.
"""

import dataclasses as dc
import warnings
from typing import List

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

# Frames from Drake are read-only views; preprocessing only reads them (its first
# float conversion copies), so torch's warning about non-writable arrays is noise.
warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

#: Output units of every TaxiNet: [px_hat m, theta_hat deg].
ESTIMATE_UNITS = ("m", "deg")


#: The crop of the authors' TinyTaxiNet pipeline, as fractions of a 360x200 frame.
AUTHORS_CROP = [55 / 360, 5 / 200, 1.0, 135 / 200]


@dc.dataclass
class PreprocessConfig:
    """How an RGB frame becomes the network input.

    ``blockmax`` is the authors' TinyTaxiNet pipeline (their public code): grayscale,
    crop, resize to 128x256, mean of the ``top_k`` brightest pixels of each 16x16 block
    (8x16), shifted to mean 0.5 and clipped to [0, 1]. ``resize`` crops and resizes to
    ``height`` x ``width`` and standardises per image (for the CNN).
    ``crop`` = [left, top, right, bottom] as fractions of the frame. The authors' crop
    (55, 5, 360, 135) of a 360x200 frame, `AUTHORS_CROP`, framed their X-Plane camera;
    on ours it is half sky, so the default keeps the ground ahead (rows 42-100 %),
    which measured better at the nominal and at other hours (README, TaxiNet).
    """
    kind: str = "blockmax"
    crop: List[float] = dc.field(default_factory=lambda: [0.0, 0.42, 1.0, 1.0])
    height: int = 8
    width: int = 16
    top_k: int = 16
    grayscale: bool = True

    def validate(self):
        if self.kind not in ("blockmax", "resize"):
            raise ValueError(f"preprocess.kind must be blockmax or resize, got {self.kind}")
        l, t, r, b = self.crop
        if not (0 <= l < r <= 1 and 0 <= t < b <= 1):
            raise ValueError(f"preprocess.crop must be fractions 0 <= left < right <= 1, "
                             f"0 <= top < bottom <= 1, got {self.crop}")
        return self

    @property
    def channels(self) -> int:
        return 1 if self.grayscale else 3


def _crop(images, crop):
    """Crop ``(N, H, W, C)`` by fractions (a view: no pixels copied)."""
    h, w = images.shape[1:3]
    l, t, r, b = crop
    return images[:, round(t * h):max(round(b * h), round(t * h) + 1),
                  round(l * w):max(round(r * w), round(l * w) + 1)]


def preprocess(images: torch.Tensor, config: PreprocessConfig) -> torch.Tensor:
    """uint8 ``(N, H, W, 3)`` RGB or ``(N, H, W, 4)`` RGBA (alpha ignored), or one
    ``(H, W, C)`` image -> float network input. Alpha is dropped by a view, so a camera
    frame is copied once, by the float conversion of its crop."""
    if images.dim() == 3:
        images = images.unsqueeze(0)
    if images.dim() != 4 or images.shape[-1] not in (3, 4):
        raise ValueError(f"TaxiNet expects RGB or RGBA images shaped (N, H, W, 3|4), got "
                         f"{tuple(images.shape)}")
    x = _crop(images[..., :3], config.crop).permute(0, 3, 1, 2).float() / 255.0
    if config.grayscale:
        x = (0.299 * x[:, 0:1] + 0.587 * x[:, 1:2] + 0.114 * x[:, 2:3])
    if config.kind == "blockmax":
        x = F.interpolate(x, size=(config.height * 16, config.width * 16), mode="bilinear",
                          align_corners=False, antialias=True)
        n, c = x.shape[:2]
        blocks = F.unfold(x, kernel_size=16, stride=16)             # (N, C*256, 8*16)
        blocks = blocks.view(n, c, 256, -1)
        x = blocks.topk(config.top_k, dim=2).values.mean(dim=2)     # (N, C, 8*16)
        x = x.view(n, c, config.height, config.width)
        x = (x - x.mean(dim=(1, 2, 3), keepdim=True) + 0.5).clamp(0.0, 1.0)
        return x.flatten(1)
    x = F.interpolate(x, size=(config.height, config.width), mode="bilinear",
                      align_corners=False, antialias=True)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    std = x.std(dim=(1, 2, 3), keepdim=True).clamp_min(1e-3)
    return (x - mean) / std


def preprocess_batched(images, config: PreprocessConfig, batch: int = 256) -> torch.Tensor:
    """`preprocess` over a large uint8 ``(N, H, W, 3)`` numpy array, ``batch`` frames at
    a time (the float copy of a whole data set would not fit in memory)."""
    images = np.asarray(images)
    if len(images) == 0:
        raise ValueError("no images to preprocess")
    return torch.cat([preprocess(torch.from_numpy(images[i:i + batch]), config)
                      for i in range(0, len(images), batch)])


@dc.dataclass
class TaxiNetConfig:
    """Architecture: ``tiny`` (the authors' ReLU MLP 128-16-8-8-2) or ``cnn``."""
    arch: str = "tiny"
    hidden: List[int] = dc.field(default_factory=lambda: [16, 8, 8])
    channels: List[int] = dc.field(default_factory=lambda: [16, 32, 32])
    #: Output scale so the last layer works near unit range: [m, deg].
    output_scale: List[float] = dc.field(default_factory=lambda: [10.0, 30.0])


class TinyTaxiNet(nn.Module):
    """ReLU MLP from the 8x16 block-max image to [px_hat m, theta_hat deg]."""

    def __init__(self, config: TaxiNetConfig, in_features: int):
        super().__init__()
        layers, width = [], in_features
        for h in config.hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers.append(nn.Linear(width, 2))
        self.net = nn.Sequential(*layers)
        self.register_buffer("scale", torch.tensor(config.output_scale, dtype=torch.float32))

    def forward(self, x):
        return self.net(x) * self.scale


class SmallTaxiCNN(nn.Module):
    """A small CNN option: conv-ReLU-pool stacks, global average, linear head."""

    def __init__(self, config: TaxiNetConfig, in_channels: int):
        super().__init__()
        layers, c = [], in_channels
        for out in config.channels:
            layers += [nn.Conv2d(c, out, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)]
            c = out
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(c, 2)
        self.register_buffer("scale", torch.tensor(config.output_scale, dtype=torch.float32))

    def forward(self, x):
        return self.head(self.features(x).mean(dim=(2, 3))) * self.scale


def build_taxinet(config: TaxiNetConfig, preprocess_config: PreprocessConfig) -> nn.Module:
    """A freshly initialised TaxiNet for ``config`` and its input format."""
    if config.arch == "tiny":
        if preprocess_config.kind != "blockmax":
            raise ValueError("the tiny TaxiNet takes the blockmax preprocessing")
        n = preprocess_config.channels * preprocess_config.height * preprocess_config.width
        return TinyTaxiNet(config, n)
    if config.arch == "cnn":
        if preprocess_config.kind != "resize":
            raise ValueError("the cnn TaxiNet takes the resize preprocessing")
        return SmallTaxiCNN(config, preprocess_config.channels)
    raise ValueError(f"unknown TaxiNet arch '{config.arch}' (tiny or cnn)")

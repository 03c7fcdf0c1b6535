"""PS-FCN, PS-FCN+N and UPS-FCN (Chen, Han, Wong: "PS-FCN: A Flexible Learning Framework for
Photometric Stereo", ECCV 2018; "Deep Photometric Stereo for Non-Lambertian Surfaces", TPAMI 2020).

The network sees each image on its own, fuses the per-image features with an element-wise max,
and regresses one normal map:

    image k (3) [+ light direction k broadcast to H x W (3)]
        -> extractor: conv1..conv7                        -> feature_k   [128, H/2, W/2]
    fused = max_k feature_k                               (order-free, any number of images)
        -> regressor: deconv1, deconv2, deconv3, est_normal -> unit normals [3, H, W]

Layer for layer as the authors' release, so that their checkpoints load unchanged
(parameter names ``extractor.conv{1..7}.0.*``, ``regressor.deconv{1,2,3}.0.*``,
``regressor.est_normal.0.weight``; 2,210,048 parameters with lights). conv = Conv2d(3x3,
bias) + LeakyReLU(0.1); deconv = ConvTranspose2d(4, stride 2, pad 1, no bias) + LeakyReLU(0.1);
no batch norm. H and W must be multiples of 4 (two stride-2 layers); psctl.infer pads.

UPS-FCN is the same network without the light input (3 input channels).

+N (PS-FCN+N): before the network, each pixel's observations are divided by their L2 norm over
the images (``normalize_observations``), then multiplied by sqrt(t / q) at test time (t test
images, q training images) so that the values keep the scale seen in training.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from psctl.models import NORM_EPS

DEFAULT_CONFIG = {
    "lights": True,  # 6 input channels (RGB + light direction); False: UPS-FCN, 3 channels
    "fuse": "max",  # "max" (the paper) or "mean"
    "slope": 0.1,  # LeakyReLU negative slope
}

# The network's STRIDE (4), RECEPTIVE_RADIUS (23) and HALO (24) are in psctl/models/__init__.py:
# the inference engine reads them without importing torch.

# +N variants. "per-channel": each colour channel divided by its norm over the N images (the
# paper's definition; the authors' code does the same: pms_transforms.normalize reshapes each
# H x W x 3 image to a column of H*W*3 values, so the norm runs over images per pixel and per
# channel). "per-pixel": the concatenated 3N-vector of a pixel divided by its norm.
NORMALIZATIONS = ("none", "per-channel", "per-pixel")


def _conv(c_in: int, c_out: int, stride: int, slope: float) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=True), nn.LeakyReLU(slope, inplace=True))


def _deconv(c_in: int, c_out: int, slope: float) -> nn.Sequential:
    return nn.Sequential(nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=False), nn.LeakyReLU(slope, inplace=True))


class FeatExtractor(nn.Module):
    """Per-image features. [B, C_in, H, W] -> [B, 128, H/2, W/2]."""

    def __init__(self, c_in: int, slope: float = 0.1):
        super().__init__()
        self.conv1 = _conv(c_in, 64, 1, slope)
        self.conv2 = _conv(64, 128, 2, slope)  # H/2
        self.conv3 = _conv(128, 128, 1, slope)
        self.conv4 = _conv(128, 256, 2, slope)  # H/4
        self.conv5 = _conv(256, 256, 1, slope)
        self.conv6 = _deconv(256, 128, slope)  # back to H/2
        self.conv7 = _conv(128, 128, 1, slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in (self.conv1, self.conv2, self.conv3, self.conv4, self.conv5, self.conv6, self.conv7):
            x = layer(x)
        return x


class Regressor(nn.Module):
    """Fused features to unit normals. [B, 128, H/2, W/2] -> [B, 3, H, W]."""

    def __init__(self, slope: float = 0.1):
        super().__init__()
        # The authors call all of these deconv*, although only deconv3 is a transposed conv.
        self.deconv1 = _conv(128, 128, 1, slope)
        self.deconv2 = _conv(128, 128, 1, slope)
        self.deconv3 = _deconv(128, 64, slope)  # H
        self.est_normal = nn.Sequential(nn.Conv2d(64, 3, 3, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.deconv3(self.deconv2(self.deconv1(x)))
        # float32 for the unit length: under bf16 autocast the norm would be off by ~1e-2
        return F.normalize(self.est_normal(x).float(), p=2, dim=1)


class PSFCN(nn.Module):
    """PS-FCN (``lights=True``) or UPS-FCN (``lights=False``); see the module docstring."""

    def __init__(self, config: dict | None = None):
        super().__init__()
        self.config = {**DEFAULT_CONFIG, **(config or {})}
        if self.config["fuse"] not in ("max", "mean"):
            raise ValueError(f"fuse must be 'max' or 'mean', got {self.config['fuse']!r}")
        self.extractor = FeatExtractor(6 if self.config["lights"] else 3, self.config["slope"])
        self.regressor = Regressor(self.config["slope"])
        for m in self.modules():  # the authors' initialisation
            # not on the meta device (a network built for a weights file): there torch's
            # kaiming_normal_ imports torch._dynamo, 1.8-2.8 s of every psctl normals run
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)) and not m.weight.is_meta:
                nn.init.kaiming_normal_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    @property
    def uses_lights(self) -> bool:
        return bool(self.config["lights"])

    def network_input(self, images: torch.Tensor, lights: torch.Tensor | None) -> torch.Tensor:
        """images [B, 3, H, W], lights [B, 3] -> [B, 6, H, W] (or the images alone for UPS-FCN)."""
        if not self.uses_lights:
            return images
        if lights is None:
            raise ValueError("this network needs light directions")
        b, _, h, w = images.shape
        return torch.cat([images, lights.to(images.dtype).view(b, 3, 1, 1).expand(b, 3, h, w)], 1)

    def extract(self, images: torch.Tensor, lights: torch.Tensor | None = None) -> torch.Tensor:
        """Per-image features. images [B, 3, H, W], lights [B, 3] -> [B, 128, H/2, W/2]."""
        return self.extractor(self.network_input(images, lights))

    def regress(self, fused: torch.Tensor) -> torch.Tensor:
        """Fused features [B, 128, H/2, W/2] -> unit normals [B, 3, H, W] (x right, y up, z out)."""
        return self.regressor(fused)

    def forward(self, images: torch.Tensor, lights: torch.Tensor | None = None) -> torch.Tensor:
        """All images at once (training; inference streams through psctl.infer instead).

        Args:
            images: [B, N, 3, H, W], N images of each of B scenes, H and W multiples of 4.
            lights: [B, N, 3] unit light directions (None for UPS-FCN).
        Returns:
            [B, 3, H, W] unit normals.
        """
        b, n, c, h, w = images.shape
        feats = self.extract(images.reshape(b * n, c, h, w), None if lights is None else lights.reshape(b * n, 3))
        feats = feats.view(b, n, *feats.shape[1:])
        fused = feats.amax(1) if self.config["fuse"] == "max" else feats.mean(1)
        return self.regress(fused)


def normalize_observations(images: torch.Tensor, variant: str = "per-channel", q: int | None = None) -> torch.Tensor:
    """+N: divide each pixel's observations by their L2 norm over the images.

    Args:
        images: [..., N, 3, H, W] (image axis -4, channel axis -3), e.g. [N, 3, H, W] or
            a training batch [B, N, 3, H, W].
        variant: "per-channel" (norm over N per colour channel), "per-pixel" (norm of the
            3N-vector) or "none".
        q: number of images per sample in training. With q, the result is multiplied by
            sqrt(N / q), so each normalised vector has norm sqrt(N / q) instead of 1.
    Returns:
        a tensor of the same shape.
    """
    if variant == "none":
        return images
    if variant not in NORMALIZATIONS:
        raise ValueError(f"unknown normalization {variant!r}; choose from {', '.join(NORMALIZATIONS)}")
    dims = (-4,) if variant == "per-channel" else (-4, -3)
    norm = images.square().sum(dims, keepdim=True).sqrt()
    scale = 1.0 if q is None else math.sqrt(images.shape[-4] / q)
    return images * (scale / (norm + NORM_EPS))

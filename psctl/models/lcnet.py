"""LCNet, the lighting calibration network of SDPS-Net (Chen, Han, Shi, Matsushita, Wong:
"SDPS-Net: Self-calibrating Deep Photometric Stereo Networks", CVPR 2019; "Deep Photometric
Stereo for Non-Lambertian Surfaces", TPAMI 2020).

LCNet looks at all images of an object (each resized to 128 x 128, with the object mask as a 4th
channel) and classifies, for each image, the light's direction and intensity:

    image k (3) + mask (1)      [4, 128, 128]
        -> featExtractor: conv1..conv7                       -> feature_k  [256, 8, 8]
    global = max_k feature_k                                 (local-global fusion, order-free)
    concat(feature_k, global)   [512, 8, 8]
        -> classifier: conv1..conv4                          -> [256, 1, 1]
        -> dir_x_est (azimuth, 36 classes), dir_y_est (elevation, 36), int_est (intensity, 20)

Layer for layer as the authors' release (models/LCNet.py of guanyingc/SDPS-Net), so that their
``LCNet_CVPR2019.pth.tar`` loads unchanged: ``featExtractor.conv{1..7}.0.{weight,bias}``,
``classifier.conv{1..4}.0.{weight,bias}``, ``classifier.{dir_x_est,dir_y_est,int_est}.{0.0,1.0}.
{weight,bias}``; 4,409,692 parameters. conv = Conv2d(3x3, pad 1, bias) + LeakyReLU(0.1), no batch
norm; each head is a 1x1 conv 256->64 + LeakyReLU, then a 1x1 conv 64->K.

Discretisation (pure functions below). A direction (x, y, z) (x right, y up, z toward the
camera) has azimuth theta = atan(x / z) and elevation phi = atan(y / sqrt(x^2 + z^2)), both in
[-90, 90] degrees; class k = floor((angle + 90) / 180 * K) clamped to [0, K - 1]; a class decodes
to its bin centre (k + 0.5) / K * 180 - 90 and the unit vector is rebuilt as
(cos phi sin theta, sin phi, cos phi cos theta). Intensities use K_e bins over [0.2, 2.0] the
same way. Decoding takes the argmax class (the paper) or the soft-argmax (the probability-
weighted mean of the bin centres), an option psctl adds.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

DEFAULT_CONFIG = {
    "dirs_cls": 36,  # K_d: azimuth and elevation classes (5 degrees each)
    "ints_cls": 20,  # K_e: intensity classes
    "ints_range": [0.2, 2.0],  # intensities the classes cover
    "in_mask": True,  # the object mask as a 4th input channel
    "fuse": "max",  # "max" (the paper) or "mean"
    "slope": 0.1,  # LeakyReLU negative slope
    "size": 128,  # input side the images are resized to (at most 128: the classifier ends at 1x1)
}
MAX_SIZE = 128  # 128 / 16 (extractor) / 8 (classifier) = 1
FEATURES = 256  # extractor output channels
DECODINGS = ("argmax", "soft")


def _conv(c_in: int, c_out: int, k: int, stride: int, slope: float) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, k, stride, (k - 1) // 2, bias=True), nn.LeakyReLU(slope, inplace=True))


def _head(k: int, slope: float) -> nn.Sequential:
    return nn.Sequential(_conv(FEATURES, 64, 1, 1, slope), nn.Sequential(nn.Conv2d(64, k, 1, 1, 0, bias=True)))


class FeatExtractor(nn.Module):
    """Per-image features. [B, C_in, S, S] -> [B, 256, S/16, S/16]."""

    def __init__(self, c_in: int, slope: float = 0.1):
        super().__init__()
        self.conv1 = _conv(c_in, 64, 3, 2, slope)  # S/2
        self.conv2 = _conv(64, 128, 3, 2, slope)  # S/4
        self.conv3 = _conv(128, 128, 3, 1, slope)
        self.conv4 = _conv(128, 128, 3, 2, slope)  # S/8
        self.conv5 = _conv(128, 128, 3, 1, slope)
        self.conv6 = _conv(128, 256, 3, 2, slope)  # S/16
        self.conv7 = _conv(256, 256, 3, 1, slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in (self.conv1, self.conv2, self.conv3, self.conv4, self.conv5, self.conv6, self.conv7):
            x = layer(x)
        return x


class Classifier(nn.Module):
    """Own + global features to class scores. [B, 512, S/16, S/16] -> 3 x [B, K] logits."""

    def __init__(self, dirs_cls: int, ints_cls: int, slope: float = 0.1):
        super().__init__()
        self.conv1 = _conv(2 * FEATURES, 256, 3, 1, slope)
        self.conv2 = _conv(256, 256, 3, 2, slope)  # 8 -> 4
        self.conv3 = _conv(256, 256, 3, 2, slope)  # 4 -> 2
        self.conv4 = _conv(256, 256, 3, 2, slope)  # 2 -> 1
        self.dir_x_est = _head(dirs_cls, slope)
        self.dir_y_est = _head(dirs_cls, slope)
        self.int_est = _head(ints_cls, slope)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        x = self.conv4(self.conv3(self.conv2(self.conv1(x))))
        if x.shape[-2:] != (1, 1):
            raise ValueError(f"LCNet inputs must be at most {MAX_SIZE} px (classifier output {tuple(x.shape[-2:])})")
        return {"dir_x": self.dir_x_est(x).flatten(1), "dir_y": self.dir_y_est(x).flatten(1),
                "ints": self.int_est(x).flatten(1)}


class LCNet(nn.Module):
    """Lighting calibration network; see the module docstring."""

    def __init__(self, config: dict | None = None):
        super().__init__()
        self.config = {**DEFAULT_CONFIG, **(config or {})}
        c = self.config
        if c["fuse"] not in ("max", "mean"):
            raise ValueError(f"fuse must be 'max' or 'mean', got {c['fuse']!r}")
        if not 1 <= int(c["size"]) <= MAX_SIZE:
            raise ValueError(f"size must be in [1, {MAX_SIZE}], got {c['size']}")
        self.featExtractor = FeatExtractor(4 if c["in_mask"] else 3, c["slope"])
        self.classifier = Classifier(c["dirs_cls"], c["ints_cls"], c["slope"])
        for m in self.modules():  # the authors' initialisation (not on the meta device: see PSFCN)
            if isinstance(m, nn.Conv2d) and not m.weight.is_meta:
                nn.init.kaiming_normal_(m.weight)
                nn.init.zeros_(m.bias)

    def network_input(self, images: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """images [B, 3, S, S], mask [B, 1, S, S] (or None) -> [B, 4, S, S] (or the images)."""
        if not self.config["in_mask"]:
            return images
        if mask is None:
            raise ValueError("this LCNet takes the object mask as input")
        return torch.cat([images, mask.to(images.dtype).expand(images.shape[0], 1, *images.shape[2:])], 1)

    def extract(self, x: torch.Tensor) -> torch.Tensor:
        """Network inputs [B, 4, S, S] -> per-image features [B, 256, S/16, S/16]."""
        return self.featExtractor(x)

    def classify(self, feats: torch.Tensor, fused: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-image features [B, 256, h, w] and the global feature [B or 1, 256, h, w] ->
        logits {"dir_x": [B, K_d], "dir_y": [B, K_d], "ints": [B, K_e]}.

        The classifier always runs in the network's own dtype, outside any autocast: on the
        2-core development CPU (torch 2.13.0, oneDNN) the bf16 backward of its last stride-2
        conv on a 1 x 1 map (64 px inputs) gave non-zero, later NaN, weight gradients on kernel
        taps that only see zero padding, which is how the release LCNet got NaN weights
        (docs/weights-history.md, LCNet stage 2). Its maps are at most 8 x 8: cheap next to the extractor."""
        x = torch.cat([feats, fused.expand_as(feats)], 1)
        dtype = next(self.classifier.parameters()).dtype
        with torch.autocast(x.device.type, enabled=False):
            return self.classifier(x.to(dtype))

    def forward(self, images: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """All images at once (training; psctl.lights streams instead).

        Args:
            images: [B, N, 3, S, S], N images of each of B objects (already resized, masked).
            mask: [B, 1, S, S] object masks (float 0..1).
        Returns:
            logits {"dir_x": [B, N, K_d], "dir_y": [B, N, K_d], "ints": [B, N, K_e]}.
        """
        b, n, c, h, w = images.shape
        flat_mask = None if mask is None else mask[:, None].expand(b, n, 1, h, w).reshape(b * n, 1, h, w)
        feats = self.extract(self.network_input(images.reshape(b * n, c, h, w), flat_mask))
        feats = feats.view(b, n, *feats.shape[1:])
        fused = feats.amax(1) if self.config["fuse"] == "max" else feats.mean(1)
        out = self.classify(feats.flatten(0, 1), fused[:, None].expand_as(feats).flatten(0, 1))
        return {k: v.view(b, n, -1) for k, v in out.items()}

    @torch.no_grad()
    def estimate(self, images: torch.Tensor, mask: torch.Tensor, mode: str = "argmax") -> tuple[torch.Tensor, torch.Tensor]:
        """Lights of a batch: images [B, N, 3, H, W], mask [B, 1, H, W] (resized to ``size``
        when needed) -> (unit directions [B, N, 3], intensities [B, N]) decoded with ``mode``."""
        images, mask = resize_stack(images, mask, int(self.config["size"]))
        return decode(self(images, mask), self.config, mode)


def resize_inputs(images: torch.Tensor, mask: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Resize images [B, 3, H, W] and masks [B, 1, H, W] to size x size (bilinear, antialiased
    when shrinking, so that a large photo is averaged rather than point-sampled); the mask is
    thresholded at 0.5 and zeroes the images outside it. No-op when already size x size."""
    if images.shape[-2:] == (size, size):
        return images, mask
    images = F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    mask = (F.interpolate(mask.to(images.dtype), size=(size, size), mode="bilinear", align_corners=False,
                          antialias=True) > 0.5).to(images.dtype)
    return images * mask, mask


def resize_stack(images: torch.Tensor, mask: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``resize_inputs`` for stacks: images [B, N, 3, H, W], mask [B, 1, H, W] -> size x size."""
    if images.shape[-2:] == (size, size):
        return images, mask
    b, n = images.shape[:2]
    m = mask[:, None].expand(b, n, *mask.shape[1:]).flatten(0, 1)
    x, m = resize_inputs(images.flatten(0, 1), m, size)
    return x.view(b, n, *x.shape[1:]), m.view(b, n, *m.shape[1:])[:, 0]


# --- discretisation: pure functions over tensors ----------------------------------------------

def dirs_to_angles(dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit directions [..., 3] -> (azimuth theta, elevation phi) in degrees, each [...].

    theta = atan(x / z), phi = atan(y / sqrt(x^2 + z^2)), both in [-90, 90]. Directions behind
    the image plane (z < 0) are not representable; they get theta = +-90.
    """
    x, y, z = dirs.unbind(-1)
    theta = torch.rad2deg(torch.atan2(x, z.clamp_min(0)))
    phi = torch.rad2deg(torch.atan2(y, torch.sqrt(x * x + z.clamp_min(0) ** 2)))
    return theta, phi


def angles_to_dirs(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """(azimuth, elevation) in degrees -> unit directions [..., 3] (the inverse of dirs_to_angles)."""
    t, p = torch.deg2rad(theta), torch.deg2rad(phi)
    return torch.stack([torch.cos(p) * torch.sin(t), torch.sin(p), torch.cos(p) * torch.cos(t)], -1)


def _float(t: torch.Tensor) -> torch.Tensor:
    """Class indices as floats (soft-argmax gives fractional ones); float tensors unchanged."""
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())


def angles_to_classes(angle: torch.Tensor, k: int) -> torch.Tensor:
    """Angles in degrees [...] -> classes (int64) floor((angle + 90) / 180 * k), clamped to [0, k-1]."""
    return torch.floor((angle + 90.0) / 180.0 * k).clamp(0, k - 1).long()


def classes_to_angles(cls: torch.Tensor, k: int) -> torch.Tensor:
    """Classes [...] -> bin-centre angles in degrees, (cls + 0.5) / k * 180 - 90."""
    return (_float(cls) + 0.5) / k * 180.0 - 90.0


def dirs_to_classes(dirs: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions [..., 3] -> (azimuth class, elevation class), each [...] int64."""
    theta, phi = dirs_to_angles(dirs)
    return angles_to_classes(theta, k), angles_to_classes(phi, k)


def classes_to_dirs(cx: torch.Tensor, cy: torch.Tensor, k: int) -> torch.Tensor:
    """(azimuth class, elevation class) -> unit directions at the bin centres [..., 3]."""
    return angles_to_dirs(classes_to_angles(cx, k), classes_to_angles(cy, k))


def ints_to_classes(ints: torch.Tensor, k: int, lo: float = 0.2, hi: float = 2.0) -> torch.Tensor:
    """Intensities [...] -> classes floor((e - lo) / (hi - lo) * k), clamped to [0, k-1]."""
    return torch.floor((ints - lo) / (hi - lo) * k).clamp(0, k - 1).long()


def classes_to_ints(cls: torch.Tensor, k: int, lo: float = 0.2, hi: float = 2.0) -> torch.Tensor:
    """Intensity classes [...] -> bin-centre intensities lo + (cls + 0.5) / k * (hi - lo)."""
    return lo + (_float(cls) + 0.5) / k * (hi - lo)


def _expected_class(logits: torch.Tensor) -> torch.Tensor:
    """Soft-argmax: the probability-weighted mean class index (a float) of logits [..., K]."""
    p = torch.softmax(logits.float(), -1)
    return (p * torch.arange(logits.shape[-1], device=logits.device, dtype=p.dtype)).sum(-1)


def decode(logits: dict[str, torch.Tensor], config: dict | None = None,
           mode: str = "argmax") -> tuple[torch.Tensor, torch.Tensor]:
    """LCNet logits -> (unit directions [..., 3], intensities [...]).

    Args:
        logits: {"dir_x": [..., K_d], "dir_y": [..., K_d], "ints": [..., K_e]}.
        config: the network's config (class counts, intensity range); DEFAULT_CONFIG if None.
        mode: "argmax" (the class centre, as the paper) or "soft" (soft-argmax: the expected
            class index under the softmax, mapped linearly to an angle / intensity, so the
            estimate can fall between bin centres).
    """
    c = {**DEFAULT_CONFIG, **(config or {})}
    lo, hi = c["ints_range"]
    if mode == "argmax":
        cx, cy, ci = (logits[k].argmax(-1) for k in ("dir_x", "dir_y", "ints"))
        return classes_to_dirs(cx, cy, c["dirs_cls"]).float(), classes_to_ints(ci, c["ints_cls"], lo, hi).float()
    if mode == "soft":
        cx, cy, ci = (_expected_class(logits[k]) for k in ("dir_x", "dir_y", "ints"))
        return classes_to_dirs(cx, cy, c["dirs_cls"]), classes_to_ints(ci, c["ints_cls"], lo, hi)
    raise ValueError(f"unknown decoding {mode!r}; choose from {', '.join(DECODINGS)}")


def classification_loss(logits: dict[str, torch.Tensor], dirs: torch.Tensor, ints: torch.Tensor,
                        config: dict | None = None, weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
                        ) -> tuple[torch.Tensor, dict[str, float]]:
    """Cross-entropy on the three heads (the paper: weights 1).

    Args:
        logits: {"dir_x", "dir_y": [..., K_d], "ints": [..., K_e]} (any leading shape).
        dirs: [..., 3] true unit light directions; ints: [...] true intensities.
    Returns:
        (total loss, {"dir_x", "dir_y", "ints": each term as a float}).
    """
    c = {**DEFAULT_CONFIG, **(config or {})}
    lo, hi = c["ints_range"]
    cx, cy = dirs_to_classes(dirs, c["dirs_cls"])
    targets = {"dir_x": cx, "dir_y": cy, "ints": ints_to_classes(ints, c["ints_cls"], lo, hi)}
    terms = {k: F.cross_entropy(logits[k].float().flatten(0, -2), targets[k].flatten()) for k in targets}
    total = sum(w * terms[k] for w, k in zip(weights, ("dir_x", "dir_y", "ints")))
    return total, {k: float(v.detach()) for k, v in terms.items()}


__all__ = ["LCNet", "DEFAULT_CONFIG", "decode", "classification_loss", "resize_inputs", "dirs_to_classes",
           "classes_to_dirs", "ints_to_classes", "classes_to_ints"]

"""Distant directional lights: directions over the upper hemisphere and per-image intensities.

Directions are unit vectors (x right, y up, z toward the camera), drawn uniformly by area over
a band of zenith angles (angle from the view direction +z):

    hemisphere  0 .. max_zenith (90 by default: the paper's full 180 x 180 degree range)
    diligent    0 .. 45 degrees (DiLiGenT's 96 lights span 4.2 .. 43.8 degrees of zenith)
    poles       0 .. 30 degrees (lights near the view direction)
    equator     60 .. 90 degrees (grazing lights near the horizon of the hemisphere)

``max_zenith`` may also be a range (a, b): each sample (all but the last axis of ``shape``)
then draws its own cone, max zenith uniform in [a, b], and its lights fill that cone. Real
rigs differ in how wide their lights spread (DiLiGenT's stay within 44 degrees of the view
axis); a network that infers the lights from the images alone sees narrow and wide rigs.

Intensities (``sample_intensities``): unit, random (independent per image, the paper),
directional (a smooth function of the direction, drawn per sample) or mixed (either, per sample).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from psctl.errors import PsctlError

DISTRIBUTIONS = {"hemisphere": (0.0, 90.0), "diligent": (0.0, 45.0), "poles": (0.0, 30.0), "equator": (60.0, 90.0)}
INTENSITY_RANGE = (0.2, 2.0)


def zenith_band(distribution: str, max_zenith: float | Sequence[float] | None = None) -> tuple[float, float]:
    """(min, max) zenith in degrees of a named distribution; ``max_zenith`` overrides the max
    (for a range (a, b), the widest band: (min, b), after checking that a > min)."""
    if distribution not in DISTRIBUTIONS:
        raise PsctlError(None, f"unknown light distribution {distribution!r}; choose from {', '.join(DISTRIBUTIONS)}")
    lo, hi = DISTRIBUTIONS[distribution]
    if isinstance(max_zenith, (list, tuple)):
        if len(max_zenith) != 2 or not lo < float(max_zenith[0]) <= float(max_zenith[1]):
            raise PsctlError(None, f"max_zenith range must be (a, b) with {lo} < a <= b, got {list(max_zenith)}")
        max_zenith = max_zenith[1]
    if max_zenith is not None:
        hi = float(max_zenith)
    if not 0.0 <= lo < hi <= 90.0:
        raise PsctlError(None, f"light zenith band must lie in [0, 90] degrees, got [{lo}, {hi}]")
    return lo, hi


def sample_lights(shape: tuple[int, ...], gen: torch.Generator, distribution: str = "hemisphere",
                  max_zenith: float | Sequence[float] | None = None) -> Tensor:
    """[*shape, 3] unit light directions, uniform by area over the distribution's zenith band
    (per sample, over ``shape[:-1]``, when ``max_zenith`` is a range)."""
    lo, hi = zenith_band(distribution, max_zenith)
    dev = gen.device
    zmax = math.cos(math.radians(lo))
    if isinstance(max_zenith, (list, tuple)):
        a, b = (math.radians(float(v)) for v in max_zenith)
        cone = a + (b - a) * torch.rand((*shape[:-1], 1), generator=gen, device=dev)
        zmin = torch.cos(cone)
    else:
        zmin = math.cos(math.radians(hi))
    z = zmin + (zmax - zmin) * torch.rand(shape, generator=gen, device=dev)
    phi = 2 * math.pi * torch.rand(shape, generator=gen, device=dev)
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


# "directional" intensities: e = exp(a . l) x jitter, a drawn per sample. Real rigs' LEDs differ
# smoothly with their position: DiLiGenT's dim towards the rim (intensity vs zenith correlation
# -0.72 on cat, 0.42 at 40 degrees vs 1.20 at 4 degrees, i.e. a_z about 4.5). Drawn independently
# of the lights, as "random" is, an LCNet can learn that a bright image means a frontal light;
# with both modes in training (mixed) brightness says nothing about direction.
DIRECTIONAL_GAIN = (5.0, 1.5)  # |a_z| <= 5 (rim falloff or rise), |a_x|, |a_y| <= 1.5 (lateral gradients)
DIRECTIONAL_JITTER = 1.25  # per-image factor log-uniform in [1/1.25, 1.25]
INTENSITY_MODES = ("unit", "random", "directional", "mixed")


def check_intensities(mode: str, name: str = "intensities") -> str:
    """``mode`` if it is one of INTENSITY_MODES, else PsctlError naming the option ``name``."""
    if mode not in INTENSITY_MODES:
        raise PsctlError(None, f"unknown {name} {mode!r}; choose from {', '.join(INTENSITY_MODES)}")
    return mode


def sample_intensities(shape: tuple[int, ...], gen: torch.Generator, mode: str = "unit",
                       low: float = INTENSITY_RANGE[0], high: float = INTENSITY_RANGE[1],
                       lights: Tensor | None = None) -> Tensor:
    """[*shape] light intensities.

    unit         all 1
    random       uniform in [low, high], independently per image (the paper)
    directional  a smooth function of the light direction, exp(a . l) times a small per-image
                 jitter, with a per sample (DIRECTIONAL_GAIN), scaled to geometric mean 1 and
                 clamped to [low, high]; needs ``lights`` [*shape, 3]. The gains are large next
                 to the range, so the clamp is often hit (hemisphere lights: about 27% of the
                 images at ``high`` and 7% at ``low``; 45-degree cone: 9% and 0.1%): a smooth
                 ramp that saturates
    mixed        per sample, random or directional with equal chance
    """
    dev = gen.device
    if mode == "unit":
        return torch.ones(shape, device=dev)
    if mode == "random":
        return low + (high - low) * torch.rand(shape, generator=gen, device=dev)
    check_intensities(mode, "intensity mode")
    if lights is None or tuple(lights.shape) != (*shape, 3):
        raise ValueError(f"intensities {mode!r} need lights of shape {(*shape, 3)}")
    gz, gxy = DIRECTIONAL_GAIN
    u = 2.0 * torch.rand((*shape[:-1], 1, 3), generator=gen, device=dev) - 1.0
    a = u * torch.tensor([gxy, gxy, gz], device=dev)
    log_e = (lights.to(a.dtype) * a).sum(-1)
    log_e = log_e + math.log(DIRECTIONAL_JITTER) * (2.0 * torch.rand(shape, generator=gen, device=dev) - 1.0)
    e = torch.exp(log_e - log_e.mean(-1, keepdim=True)).clamp(low, high)
    if mode == "mixed":
        iid = low + (high - low) * torch.rand(shape, generator=gen, device=dev)
        pick = torch.rand((*shape[:-1], 1), generator=gen, device=dev) < 0.5
        e = torch.where(pick, e, iid)
    return e

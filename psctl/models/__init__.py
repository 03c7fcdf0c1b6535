"""Networks. One readable file per model; torch is imported only by the model modules.

    ps_fcn.py    PS-FCN, PS-FCN+N and UPS-FCN (Chen et al., ECCV 2018 / TPAMI 2020)
    lcnet.py     LCNet, the lighting calibration network of SDPS-Net (CVPR 2019 / TPAMI 2020)
    weights.py   finding, loading (ours and the authors' ``*.pth.tar``) and saving weights
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from psctl.errors import PsctlError

# method name -> what the network needs. "normalization" is the default +N variant for the
# method; our own weights files record the variant they were trained with (see weights.py).
# ps-fcn-dagger (PS-FCN†) is PS-FCN trained on the lights a frozen LCNet estimates (discretised
# directions, images divided by the estimated intensities): the second stage of `sdps`.
NETWORK_METHODS: dict[str, dict] = {
    "ps-fcn": {"architecture": "ps-fcn", "lights": True, "normalization": "none"},
    "ps-fcn-n": {"architecture": "ps-fcn", "lights": True, "normalization": "per-channel"},
    "ups-fcn": {"architecture": "ps-fcn", "lights": False, "normalization": "none"},
    "ps-fcn-dagger": {"architecture": "ps-fcn", "lights": True, "normalization": "none"},
}

# Networks that estimate lights, not normals (weights files of their own, same format).
LIGHT_METHODS: dict[str, dict] = {
    "lcnet": {"architecture": "lcnet", "normalization": "none"},
}

# Every method that has a weights file.
WEIGHTS_METHODS: dict[str, dict] = {**NETWORK_METHODS, **LIGHT_METHODS}

# Two stride-2 convolutions: inputs must have sides that are a multiple of this.
STRIDE = 4
# Receptive field radius of the whole network (extractor + regressor) in input pixels, measured
# (tests/test_ps_fcn.py checks it on the real model): one output pixel depends on inputs at most
# 23 px away. Tiles and crops keep this much context (rounded up to STRIDE) so that tiling and
# cropping give the same normals as one pass over the full image.
RECEPTIVE_RADIUS = 23
HALO = -(-RECEPTIVE_RADIUS // STRIDE) * STRIDE  # 24
NORM_EPS = 1e-10  # +N: added to the norm, as the authors do


def check_downsample(k: object) -> int:
    """``--downsample`` (``psctl.infer.run_downsampled``): ``k`` if it is an integer >= 1, else a
    one-line error. Here, not in psctl.infer, so that l2 runs check it without importing torch."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or int(k) < 1:
        raise PsctlError(None, f"--downsample must be a whole number >= 1, got {k!r}")
    return int(k)


# ``--precision``: the network methods' arithmetic. float32 (the default) gives the same normals
# on any CPU; bf16 / fp16 run the convolutions under autocast (psctl.infer._autocast).
PRECISIONS = ("float32", "bf16", "fp16")


def check_precision(precision: object) -> str:
    """``--precision`` spelled float32, bf16 or fp16 (any case; returned in lower case), else a
    one-line error before any work. Here, not in psctl.infer, so that l2 runs check it without torch."""
    if isinstance(precision, str) and precision.lower() in PRECISIONS:
        return precision.lower()
    raise PsctlError(None, f"unknown --precision {precision!r}; choose from {', '.join(PRECISIONS)}")


def precision_autocast(precision: object, device: str = "auto") -> str | None:
    """``psctl.infer.DEFAULT_INFER["autocast"]`` for ``--precision``: None for float32 (without
    importing torch: l2 runs check the option too), else "bf16" / "fp16" once checked against
    ``device`` (``psctl.infer.check_autocast``) before any work."""
    kind = check_precision(precision)
    if kind == "float32":
        return None
    from psctl.infer import check_autocast

    check_autocast(kind, device)
    return kind


def check_device_name(name: str | None) -> str:
    """``--device`` spelled auto, cpu, cuda or cuda:K (lower case returned); one-line error
    otherwise, before any work (also for methods that do not use it)."""
    if name is not None and not isinstance(name, str):  # 0 would pass as "auto", 1 fail on .lower()
        raise PsctlError(None, f"--device must be a name (auto, cpu, cuda or cuda:K), not {name!r}")
    name = (name or "auto").lower()
    if name in ("auto", "cpu", "cuda") or (name.startswith("cuda:") and name[5:].isdigit()):
        return name
    raise PsctlError(None, f"unknown --device {name!r}; choose from auto, cpu, cuda or cuda:K (K: the GPU's index)")


__all__ = ["LIGHT_METHODS", "NETWORK_METHODS", "PRECISIONS", "WEIGHTS_METHODS", "check_device_name", "check_precision",
           "precision_autocast"]


def __getattr__(name: str) -> ModuleType:  # submodules on first use (psctl._submodule)
    from psctl import _submodule

    return _submodule(__name__, name)

"""Synthetic photometric-stereo data: geometry, materials, lights, rendering, on the fly.

    shapes.py     G-buffers (normal, depth, mask): analytic sphere, procedural blobby SDF shapes
    meshes.py     OBJ meshes rasterised under rotations; a cache of training views
    materials.py  MERL ABC fits, GGX (dielectric, metallic), Lambertian; blends and textures
    lights.py     directional lights over the upper hemisphere; intensities
    render.py     m = e f(n, l, v) max(n.l, 0) visibility; cast shadows; noise, quantisation
    stream.py     the training stream (batches of crops, made on the fly; torch only)
    write.py      DiLiGenT-style folders and a contact sheet (``psctl synth``)

See docs/synthetic.md. Importing this package is cheap (no torch): the modules above are
imported where needed.
"""

from __future__ import annotations

from types import ModuleType

from psctl.errors import PsctlError

PRESETS = {
    "syntest": "sphere, bunny, dragon, armadillo x K MERL materials (K default 4, 100 = the paper's SynTest)",
    "dragon-svbrdf": "dragon x ramp / checker / irregular blends of two MERL materials, K pairs (default 1)",
    "blobby": "K procedural blobby shapes with training-like materials (default 8)",
}
DEFAULT_K = {"syntest": 4, "dragon-svbrdf": 1, "blobby": 8}


def physical_memory() -> float:
    """This machine's memory in bytes (inf where the system does not say: no sysconf on
    Windows), for the guards that refuse work that cannot fit (psctl synth, psctl train)."""
    import os

    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return float("inf")


def check_preset(preset: str) -> str:
    """The preset name in lower case (as the command line takes it: SYNTEST is syntest), or a
    PsctlError listing the valid ones."""
    if isinstance(preset, str):
        preset = preset.lower()
    if preset not in PRESETS:
        raise PsctlError(None, f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    return preset


def __getattr__(name: str) -> ModuleType:  # submodules on first use (psctl._submodule)
    from psctl import _submodule

    return _submodule(__name__, name)

"""The training stream: endless batches of synthetic photometric-stereo samples, made on the fly.

    >>> from psctl.synth.stream import SynthStream
    >>> stream = SynthStream({"batch_size": 32, "n_images": 32, "seed": 0})
    >>> batch = next(iter(stream))
    >>> batch["images"].shape     # [B, N, 3, 32, 32]

How a batch is made (why it is fast enough not to slow training down):
  1. Geometry lives in a pool of G-buffers (normal, mask and a horizon map for cast shadows)
     rendered at ``size`` (128). Each batch replaces ``batch_size / reuse`` of them with new
     ones (procedural blobby shapes, or random views of the training meshes), so rendering
     geometry costs little per sample while the pool keeps changing.
  2. Each sample picks a pool entry and samples its crop straight from the G-buffer: random
     rescale (the paper's ``size -> [crop, size]``), rotation about the view axis, mirror,
     then a ``crop x crop`` window around a random object pixel. Shading happens after the
     crop, so it only touches crop x crop pixels.
  3. Random materials (MERL ABC fits, GGX, Lambertian; two-material blends; albedo
     textures), random lights (and intensities), shading with cast shadows from the horizon
     map (and, optionally, diffuse interreflections from per-pixel transfer), exposure,
     saturation, the paper's uniform noise.

Test shapes (bunny, dragon, armadillo, sphere) are never used. Without mesh files the stream
uses procedural shapes only (or views from a .npz made by ``python -m psctl.synth.meshes``).
The stream never imports OpenImageIO, so it runs where only torch is installed.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from psctl.errors import PsctlError
from psctl.synth import lights as L
from psctl.synth import materials as M
from psctl.synth import render as R
from psctl.synth.shapes import GBuffer, blobby_gbuffers, check_blobby

DEFAULT_CONFIG: dict = {
    "batch_size": 32,
    "n_images": 32,  # images (lights) per sample
    "size": 128,  # resolution the geometry pool is rendered at
    "crop": 32,  # output side; None: the whole view (size x size)
    "scale": None,  # (lo, hi) rescaled side before cropping; None: (crop, size) as in the paper
    # how the rescaled side is drawn in `scale`: "uniform" (the paper's) or "log" (log-uniform:
    # as many samples per octave, so a wide range still sees its small end often)
    "scale_law": "uniform",
    "rotate": True,  # random rotation about the view axis
    "flip": True,  # random mirror
    "windows": None,  # side w: also draw one w x w window per sample around a random object pixel
    #                   (batch key "windows", [B, 2] top-left row and column), for PS-FCN† crops
    "pool": 64,  # G-buffers kept in memory
    "reuse": 128,  # samples drawn per G-buffer (on average) before it is replaced
    "refresh_chunk": 8,  # new G-buffers are rendered this many at a time (GPU: fewer, larger calls)
    "shapes": {"blobby": 1.0, "mesh": 0.25},  # relative frequency of the geometry sources
    "meshes": ["lucy"],  # training meshes (test shapes are refused)
    "mesh_dir": None,  # folder of .obj files (None: psctl.synth.meshes.mesh_dir())
    "mesh_cache": None,  # .npz of prerendered views, used when the .obj files are absent
    "require_meshes": False,  # True: error when no mesh source is found
    "blobby": {},  # overrides of psctl.synth.shapes.BLOBBY
    "lights": "hemisphere",  # hemisphere | diligent | poles | equator
    "max_zenith": None,  # degrees; overrides the distribution's band
    "intensities": "unit",  # unit | random (uniform in [0.2, 2.0] per image) | directional | mixed (psctl.synth.lights)
    "materials": {"merl": 0.5, "ggx": 0.35, "lambert": 0.15},
    "merl": None,  # path of the ABC table (None: psctl.synth.materials.find_merl_file())
    "merl_names": None,  # restrict MERL draws to these materials
    "blend": 0.25,  # chance of a two-material blend (ramp / checker / irregular)
    "texture": 0.3,  # chance of a random albedo texture
    "shadows": True,
    "horizon_dirs": 32,  # azimuths of the horizon map
    "ambient": 0.0,  # ambient strength drawn uniformly in [0, ambient]; scaled by the intensities with the image (docs/synthetic.md)
    # diffuse interreflections: with chance p a sample's surface also lights itself, as a
    # Lambertian source of albedo a * kd / max(kd), a uniform in `albedo` (the material's own
    # kd only sets the colour: exposure hides absolute albedo, and real objects are often
    # brighter than the MERL fits). G-buffers then store light-independent transfer
    # (render.interreflection_transfer); cast shadows on the sources are ignored.
    "interreflection": None,  # None or {"p": 0.5, "albedo": [0.0, 0.9]}
    # mis-calibrated intensities (PS-FCN and PS-FCN+N training only): with chance p a sample's
    # images each join, with a chance drawn uniformly in `share`, a group whose true intensity is
    # one factor (log-uniform in `scale`) off what the network is told, as DiLiGenT's bear, whose
    # first 20 images are ~11-27 % brighter, relative to the rest, than light_intensities.txt
    # lists (docs/training.md). The factor applies before the camera (clipping, noise, rounding);
    # the `intensities` batch key is the listed one, unchanged. Not for LCNet, whose labels are
    # the intensities, nor for networks that are never told them (UPS-FCN, PS-FCN†).
    "intensity_error": None,  # None or {"p": 0.5, "share": [0.0, 0.4], "scale": [0.7, 1.4]}
    # mis-calibrated directions (PS-FCN and PS-FCN+N training only): with chance p a sample's
    # listed directions are its true ones with every zenith angle times one factor (uniform in
    # `zenith_scale`: an error that grows with the zenith angle), each
    # then turned by a small random angle (Gaussian per component, sd uniform in `jitter`
    # degrees per sample): a listed direction is a measurement too (docs/training.md, "Listed
    # light directions"). The images are rendered with the true lights; the `lights` batch key
    # is the listed one.
    "direction_error": None,  # None or {"p": 0.5, "zenith_scale": [0.94, 1.06], "jitter": [0.0, 1.0]}
    # near point lights: with chance p a sample's lights are points at a distance of `radii`
    # object radii (uniform per sample) from the object's centroid along their directions, as
    # DiLiGenT's (16-23 radii, docs/near-lights.md): per-pixel directions and 1/r^2 falloff in the
    # shading; cast shadows and the `lights` batch key stay the central directions.
    "near_lights": None,  # None or {"p": 0.5, "radii": [10.0, 40.0]}
    "exposure": (0.1, 0.5),  # mean radiance of the object, log-uniform in this range
    "clip": 1.0,  # sensor saturation of e * radiance (None: no clipping)
    "noise": 0.025,  # uniform noise in [-noise, noise] (the paper's augmentation)
    "quantize": None,  # bits (8, 16) or None
    # an integer camera at a dark exposure: with chance p a sample is scaled to a mean object
    # pixel drawn log-uniformly in `mean`, clipped, rounded to `bits` and scaled back (the
    # network sees the usual brightness, with the capture's rounding and black clipping).
    # DiLiGenT's 8-bit crops have mean object pixels of 0.018 (pot2) to 0.073 (ball).
    # "floor": truncate instead of rounding (DiLiGenT's 8-bit crops are the 16-bit images shifted
    # right by 8 bits, floor(v / 256): everything under one step is black)
    "capture": None,  # None or {"p": 0.5, "mean": [0.01, 0.1], "bits": 8, "floor": False}
    "mask_images": True,  # zero the images outside the object
    "device": "cpu",
    "seed": 0,
}


def intensity_errors(b: int, n: int, opts: dict, gen: torch.Generator, device: torch.device | str) -> Tensor:
    """[b, n] true / listed intensity factors for ``intensity_error`` (1 where listed is true)."""
    lo_s, hi_s = opts.get("share", (0.0, 0.4))
    lo_f, hi_f = opts.get("scale", (0.7, 1.4))
    on = torch.rand(b, generator=gen, device=device) < float(opts.get("p", 0.5))
    share = lo_s + (hi_s - lo_s) * torch.rand(b, generator=gen, device=device)
    member = torch.rand(b, n, generator=gen, device=device) < (share * on)[:, None]
    u = torch.rand(b, generator=gen, device=device)
    factor = torch.exp(math.log(lo_f) + (math.log(hi_f) - math.log(lo_f)) * u)
    return torch.where(member, factor[:, None], torch.ones((), device=device))


def direction_errors(lights: Tensor, opts: dict, gen: torch.Generator) -> Tensor:
    """[b, n, 3] listed directions for ``direction_error`` from the true unit ``lights`` [b, n, 3]
    (the true ones where a sample drew no error)."""
    b, n, _ = lights.shape
    dev = lights.device
    lo_z, hi_z = opts.get("zenith_scale", (0.94, 1.06))
    lo_j, hi_j = opts.get("jitter", (0.0, 1.0))
    on = torch.rand(b, generator=gen, device=dev) < float(opts.get("p", 0.5))
    f = lo_z + (hi_z - lo_z) * torch.rand(b, generator=gen, device=dev)
    sd = math.radians(1.0) * (lo_j + (hi_j - lo_j) * torch.rand(b, generator=gen, device=dev))
    noise = torch.randn(b, n, 3, generator=gen, device=dev) * sd[:, None, None]
    return torch.where(on[:, None, None], turn_directions(lights, f[:, None], noise), lights)


def turn_directions(d: Tensor, factor: Tensor, noise: Tensor) -> Tensor:
    """Unit directions [..., 3] with every zenith angle times ``factor`` (broadcast to [...];
    capped at 89 degrees: a listed light stays above the horizon), then moved by the tangent part
    of ``noise`` [..., 3] (radians) and renormalised. Also used by benchmarks/miscalibrated_set.py."""
    zen = (torch.acos(d[..., 2].clamp(-1.0, 1.0)) * factor).clamp(max=math.radians(89.0))
    azi = torch.atan2(d[..., 1], d[..., 0])
    out = torch.stack([zen.sin() * azi.cos(), zen.sin() * azi.sin(), zen.cos()], -1)
    out = out + noise - (noise * out).sum(-1, keepdim=True) * out
    return out / out.norm(dim=-1, keepdim=True)


INTENSITY_ERROR_KEYS = ("p", "share", "scale")
DIRECTION_ERROR_KEYS = ("p", "zenith_scale", "jitter")
NEAR_LIGHTS_KEYS = ("p", "radii")


def _error_opts(name: str, opts, keys: tuple[str, ...]) -> Callable[[str, tuple], tuple[float, float]] | None:
    """Shared checks of the ``*_error`` options (a mapping of known keys); returns a reader of
    [lo, hi] pairs, or None for ``opts`` None."""
    if opts is None:
        return None
    where = f"synth stream option '{name}'"
    if not isinstance(opts, dict):
        raise PsctlError(None, f"{where}: expected a mapping with keys {', '.join(keys)}, got {opts!r}")
    bad = set(opts) - set(keys)
    if bad:
        raise PsctlError(None, f"{where}: unknown key(s) {', '.join(sorted(map(str, bad)))} (known: {', '.join(keys)})")
    try:
        p = float(opts.get("p", 0.5))
    except (TypeError, ValueError):
        raise PsctlError(None, f"{where}: 'p' must be a number, got {opts.get('p')!r}") from None
    if not 0.0 <= p <= 1.0:
        raise PsctlError(None, f"{where}: need 0 <= p <= 1, got {p}")

    def pair(key: str, default: tuple) -> tuple[float, float]:
        v = opts.get(key, default)
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise PsctlError(None, f"{where}: '{key}' must be two numbers [lo, hi], got {v!r}") from None
        return lo, hi

    return pair


def check_direction_error(opts: dict | None) -> None:
    """Raise PsctlError unless ``opts`` is None or a valid ``direction_error`` dict (keys p,
    zenith_scale, jitter; 0 <= p <= 1, 0 < zenith_scale lo <= hi <= 1.5, 0 <= jitter lo <= hi <= 10)."""
    pair = _error_opts("direction_error", opts, DIRECTION_ERROR_KEYS)
    if pair is None:
        return
    where = "synth stream option 'direction_error'"
    (z_lo, z_hi), (j_lo, j_hi) = pair("zenith_scale", (0.94, 1.06)), pair("jitter", (0.0, 1.0))
    if not 0.0 < z_lo <= z_hi <= 1.5:
        raise PsctlError(None, f"{where}: need 0 < zenith_scale lo <= hi <= 1.5, got [{z_lo}, {z_hi}]")
    if not 0.0 <= j_lo <= j_hi <= 10.0:
        raise PsctlError(None, f"{where}: need 0 <= jitter lo <= hi <= 10 (degrees), got [{j_lo}, {j_hi}]")


def check_intensity_error(opts: dict | None) -> None:
    """Raise PsctlError unless ``opts`` is None or a valid ``intensity_error`` dict (keys p, share,
    scale; 0 <= p <= 1, 0 <= share lo <= hi <= 1, 0 < scale lo <= hi)."""
    pair = _error_opts("intensity_error", opts, INTENSITY_ERROR_KEYS)
    if pair is None:
        return
    where = "synth stream option 'intensity_error'"
    (s_lo, s_hi), (f_lo, f_hi) = pair("share", (0.0, 0.4)), pair("scale", (0.7, 1.4))
    if not 0.0 <= s_lo <= s_hi <= 1.0:
        raise PsctlError(None, f"{where}: need 0 <= share lo <= hi <= 1, got [{s_lo}, {s_hi}]")
    if not (0.0 < f_lo <= f_hi and math.isfinite(f_hi)):
        raise PsctlError(None, f"{where}: need 0 < scale lo <= hi, got [{f_lo}, {f_hi}]")


def check_near_lights(opts: dict | None) -> None:
    """Raise PsctlError unless ``opts`` is None or a valid ``near_lights`` dict (keys p, radii;
    0 <= p <= 1, 2 <= radii lo <= hi, finite: a light must clear the object)."""
    pair = _error_opts("near_lights", opts, NEAR_LIGHTS_KEYS)
    if pair is None:
        return
    lo, hi = pair("radii", (10.0, 40.0))
    if not (2.0 <= lo <= hi and math.isfinite(hi)):
        raise PsctlError(None, f"synth stream option 'near_lights': need 2 <= radii lo <= hi, got [{lo}, {hi}]")


SCALE_LAWS = ("uniform", "log")


def rescaled_sides(lo: float, hi: float, law: str, b: int, gen: torch.Generator,
                   device: torch.device | str = "cpu") -> Tensor:
    """[b] sides in [lo, hi] each view is rescaled to before cropping, drawn uniformly or
    log-uniformly (``law``: "uniform" or "log")."""
    u = torch.rand(b, generator=gen, device=device)
    if law == "log":
        return lo * (hi / lo) ** u
    return lo + (hi - lo) * u


# the largest seed psctl takes: generators are seeded with seed + k, and torch takes 64 bits
MAX_SEED = 2**62
# ranges of the options with a plain number as default (their kind is the default's)
_POSITIVE = ("batch_size", "n_images", "size", "pool", "reuse", "refresh_chunk", "horizon_dirs")
_NUMBERS = ("reuse",)  # an average: 0.5 (a G-buffer every other sample) is as good as 128
_NON_NEGATIVE = ("ambient", "noise", "seed")
_CHANCES = ("blend", "texture")
CAPTURE_KEYS = ("p", "mean", "bits", "floor")
INTERREFLECTION_KEYS = ("p", "albedo")


def _check_options(cfg: dict) -> None:
    """Each option of the kind and in the range the stream needs: a one-line error naming it,
    not a torch error (or a silently odd stream) later."""
    from psctl.errors import is_number, like_default

    def where(k: str) -> str:
        return f"synth stream option '{k}'"

    for k, default in DEFAULT_CONFIG.items():
        if isinstance(default, (bool, int, float)) and not (k in ("clip", "crop") and cfg[k] is None):  # null: none, whole view
            cfg[k] = like_default(where(k), cfg[k], float(default) if k in _NUMBERS else default)
    for k in _POSITIVE:
        if not cfg[k] > 0:
            raise PsctlError(None, f"{where(k)} must be positive, not {cfg[k]!r}")
    for k in _NON_NEGATIVE:
        if not cfg[k] >= 0:
            raise PsctlError(None, f"{where(k)} must be 0 or more, not {cfg[k]!r}")
    for k in _CHANCES:
        if not 0 <= cfg[k] <= 1:
            raise PsctlError(None, f"{where(k)} is a chance: 0 to 1, not {cfg[k]!r}")
    ex = cfg["exposure"]
    if not (isinstance(ex, (list, tuple)) and len(ex) == 2 and all(map(is_number, ex)) and 0 < ex[0] <= ex[1]):
        raise PsctlError(None, f"{where('exposure')} must be [lo, hi] with 0 < lo <= hi, not {ex!r}")
    if cfg["clip"] is not None and not (is_number(cfg["clip"]) and cfg["clip"] > 0):
        raise PsctlError(None, f"{where('clip')} must be a positive number or null (no clipping), not {cfg['clip']!r}")
    if cfg["quantize"] is not None and (isinstance(cfg["quantize"], bool) or cfg["quantize"] not in range(1, 33)):
        raise PsctlError(None, f"{where('quantize')} must be a number of bits (1 to 32) or null, not {cfg['quantize']!r}")
    for k, known in (("shapes", ("blobby", "mesh")), ("materials", ("merl", "ggx", "lambert"))):
        v = cfg[k]
        if not (isinstance(v, dict) and v and all(is_number(x) and x >= 0 for x in v.values())
                and sum(v.values()) > 0):
            raise PsctlError(None, f"{where(k)} must map {', '.join(known)} to relative frequencies (0 or more, "
                                   f"not all 0), not {v!r}")
        bad = sorted(map(str, set(v) - set(known)))
        if bad:
            raise PsctlError(None, f"{where(k)}: unknown {', '.join(bad)}; choose from {', '.join(known)}")
    pair = _error_opts("capture", cfg["capture"], CAPTURE_KEYS)
    if pair is not None:
        cap = cfg["capture"]
        lo, hi = pair("mean", (0.01, 0.1))
        if not 0 < lo <= hi <= 1:
            raise PsctlError(None, f"{where('capture')}: need 0 < mean lo <= hi <= 1, got [{lo}, {hi}]")
        if cap.get("bits", 8) not in range(1, 17):
            raise PsctlError(None, f"{where('capture')}: bits must be 1 to 16, not {cap.get('bits')!r}")
        if not isinstance(cap.get("floor", False), bool):
            raise PsctlError(None, f"{where('capture')}: floor must be true or false, not {cap.get('floor')!r}")
    pair = _error_opts("interreflection", cfg["interreflection"], INTERREFLECTION_KEYS)
    if pair is not None:
        lo, hi = pair("albedo", (0.0, 0.9))
        if not 0 <= lo <= hi < 1:
            raise PsctlError(None, f"{where('interreflection')}: need 0 <= albedo lo <= hi < 1, got [{lo}, {hi}]")
    cfg["blobby"] = check_blobby(cfg["blobby"], where("blobby"))
    sc = cfg["scale"]
    if sc is not None and not (isinstance(sc, (list, tuple)) and len(sc) == 2 and
                               all(is_number(v) and float(v).is_integer() for v in sc)):
        raise PsctlError(None, f"{where('scale')} must be [lo, hi], two whole numbers of pixels, or null "
                               f"((crop, size)), not {sc!r}")
    w = cfg["windows"]
    if w is not None and not (is_number(w) and float(w).is_integer()):
        raise PsctlError(None, f"{where('windows')} must be a whole number of pixels or null, not {w!r}")
    for k in ("meshes", "merl_names"):  # a name alone is a list of one (not its letters)
        v = cfg[k]
        if isinstance(v, str):
            cfg[k] = [v]
        elif v is not None and not (isinstance(v, (list, tuple)) and all(isinstance(n, str) and n for n in v)):
            raise PsctlError(None, f"{where(k)} must be a list of names{' or null' if k == 'merl_names' else ''}, "
                                   f"not {v!r}")
    if cfg["merl_names"] is not None and not cfg["merl_names"]:
        raise PsctlError(None, f"{where('merl_names')} is empty: give at least one MERL material, or null for all")
    for k, kind in (("mesh_cache", "file"), ("mesh_dir", "folder"), ("merl", "file")):
        v = cfg[k]
        if v is None or (k == "mesh_dir" and cfg["mesh_cache"] is not None):  # (the cache stands in for the folder)
            continue
        if not isinstance(v, (str, os.PathLike)) or not str(v):
            raise PsctlError(None, f"{where(k)} must be a path or null, not {v!r}")
        if not (Path(v).is_file() if kind == "file" else Path(v).is_dir()):
            raise PsctlError(v, f"not found ({where(k)} names this {kind})")


def _check_named_meshes(cfg: dict) -> None:
    """Meshes a recipe names (``meshes`` or ``mesh_dir``) with a positive mesh weight: each must be
    found, or the run would train on procedural shapes alone with only a note."""
    from psctl.synth import meshes

    if not cfg["meshes"]:
        raise PsctlError(None, "synth stream option 'meshes' is empty but shapes gives mesh a positive weight")
    meshes.check_training_meshes(list(cfg["meshes"]))
    folder = Path(cfg["mesh_dir"]) if cfg["mesh_dir"] else meshes.mesh_dir()
    for name in cfg["meshes"]:
        meshes.find_mesh(name, folder)  # raises, naming what it looked for


def make_config(config: dict | None = None, **overrides: Any) -> dict:
    """DEFAULT_CONFIG updated by ``config`` and keyword overrides; unknown keys, and values of
    the wrong kind or out of range, are errors."""
    if config is not None and not isinstance(config, dict):
        raise PsctlError(None, f"synth stream options must be a mapping, not {config!r}")
    cfg = {**DEFAULT_CONFIG, **(config or {}), **overrides}
    bad = set(cfg) - set(DEFAULT_CONFIG)
    if bad:
        raise PsctlError(None, f"unknown synth stream option(s): {', '.join(sorted(map(str, bad)))}")
    _check_options(cfg)
    given = set(config or {}) | set(overrides)
    if cfg["shapes"].get("mesh", 0) > 0 and given & {"meshes", "mesh_dir"} and cfg["mesh_cache"] is None:
        _check_named_meshes(cfg)  # named ones must be there (the default, lucy, may be absent: a note)
    if cfg["crop"] is None:
        cfg["crop"] = cfg["size"]
    unset = cfg["scale"] is None
    if unset:
        cfg["scale"] = (cfg["crop"], cfg["size"])
    lo, hi = cfg["scale"]
    if not (0 < cfg["crop"] <= cfg["size"] and cfg["crop"] <= lo <= hi):
        scale = "unset, so (crop, size)" if unset else str(tuple(cfg["scale"]))
        raise PsctlError(None, f"need 0 < crop <= size and crop <= scale lo <= hi (crop {cfg['crop']}, "
                               f"size {cfg['size']}, scale {scale}; in a recipe: crop is train.crop or "
                               f"val.size, size data.size, scale data.scale or val.data.scale)")
    if cfg["scale_law"] not in SCALE_LAWS:
        raise PsctlError(None, f"synth stream option 'scale_law': must be one of {', '.join(SCALE_LAWS)}, got {cfg['scale_law']!r}")
    if cfg["windows"] is not None and not (0 < int(cfg["windows"]) <= cfg["crop"]):
        raise PsctlError(None, f"need 0 < windows <= crop (windows {cfg['windows']}, crop {cfg['crop']})")
    L.zenith_band(cfg["lights"], cfg["max_zenith"])  # validates
    L.check_intensities(cfg["intensities"])  # before the geometry pool is built
    check_intensity_error(cfg["intensity_error"])
    check_direction_error(cfg["direction_error"])
    check_near_lights(cfg["near_lights"])
    return cfg


class GeometryPool:
    """A pool of M G-buffers stored pixel-major for fast cropping: ``data`` [M, S*S, 4] holds
    the normal (3) and mask (1) of every pixel, ``horizon`` [M, S*S, K] its horizon angles
    (float16: they are compared with light elevations to a degree or so).

    Entries are replaced first-in first-out, ``refresh_chunk`` at a time. Each chunk is rendered
    from its own seed (drawn from the stream's generator), so the pool can be rebuilt exactly
    from the seeds alone: that is the pool's state in ``state_dict``.
    """

    def __init__(self, cfg: dict, gen: torch.Generator):
        self.cfg = cfg
        self.gen = gen
        self.device = torch.device(cfg["device"])
        self.size = cfg["size"]
        self.k = cfg["horizon_dirs"]
        self.notes: list[str] = []
        self.sources = self._sources()
        m = cfg["pool"]
        self.data = torch.zeros(m, self.size * self.size, 4, device=self.device)
        self.horizon = torch.zeros(m, self.size * self.size, self.k, dtype=torch.float16, device=self.device)
        self.transfer = None  # [M, S*S, 10] with interreflections
        if cfg["interreflection"]:
            self.transfer = torch.zeros(m, self.size * self.size, 10, device=self.device)
        self.cum = torch.zeros(m, self.size * self.size, device=self.device)  # cumulative mask
        self.names = [""] * m
        self.records = torch.zeros(m, 3, dtype=torch.int64)  # per slot: chunk seed, chunk size, index in chunk
        self._pending = 0.0
        self._ring = 0  # next slot to replace
        self._new(m)

    def _new(self, n: int) -> None:
        """Replace the n oldest entries, ``refresh_chunk`` at a time."""
        m = len(self.names)
        chunk = max(1, int(self.cfg["refresh_chunk"]))
        while n > 0:
            k = min(chunk, n, m)
            seed = int(torch.randint(0, 2**62, (1,), generator=self.gen, device=self.device))
            slots = [(self._ring + i) % m for i in range(k)]
            self._ring = (self._ring + k) % m
            self._fill(seed, k, list(range(k)), slots)
            n -= k

    def _fill(self, seed: int, k: int, which: list[int], slots: list[int]) -> None:
        """Render the chunk ``seed`` (k entries) and store its entries ``which`` in ``slots``."""
        g = self._render(k, torch.Generator(device=self.device).manual_seed(seed))
        hz = R.horizon_map(g.depth, self.k) if self.cfg["shadows"] else torch.zeros(k, self.k, *g.size, device=self.device)
        idx = torch.tensor(which, device=self.device)
        dst = torch.tensor(slots, device=self.device)
        self.data[dst] = torch.cat([g.normals, g.mask.float()], 1)[idx].flatten(2).transpose(1, 2)
        self.horizon[dst] = hz[idx].flatten(2).transpose(1, 2).half()
        self.cum[dst] = g.mask[idx].flatten(1).float().cumsum(1)
        if self.transfer is not None:
            for w, slot in zip(which, slots):
                kern = R.interreflection_kernel(g.depth[w:w + 1], g.normals[w:w + 1])
                self.transfer[slot] = R.interreflection_transfer(kern, g.normals[w].flatten(1), g.mask[w].flatten())
        for w, s in zip(which, slots):
            self.names[s] = g.names[w]
            self.records[s] = torch.tensor([seed, k, w])

    def refresh(self, n_samples: int) -> None:
        """Replace pool entries in proportion to the samples drawn (``reuse`` per entry)."""
        self._pending += n_samples / self.cfg["reuse"]
        chunk = max(1, int(self.cfg["refresh_chunk"]))
        n = int(self._pending // chunk) * chunk
        if n:
            self._pending -= n
            self._new(n)

    def state_dict(self) -> dict:
        return {"records": self.records.clone(), "pending": self._pending, "ring": self._ring}

    def load_state_dict(self, state: dict) -> None:
        """Rebuild the pool from its chunk seeds (as long as filling it at start)."""
        rec = state["records"].to(torch.int64)
        if rec.shape != self.records.shape:
            raise PsctlError(None, f"stream state is for a pool of {len(rec)} entries, this pool has {len(self.records)}")
        chunks: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for slot, (seed, k, w) in enumerate(rec.tolist()):
            chunks.setdefault((seed, k), []).append((w, slot))
        for (seed, k), entries in chunks.items():
            self._fill(seed, k, [w for w, _ in entries], [s for _, s in entries])
        self._pending = float(state["pending"])
        self._ring = int(state["ring"])

    # --- geometry sources -------------------------------------------------------------------
    def _sources(self) -> list[tuple[str, float]]:
        from psctl.synth import meshes

        cfg = self.cfg
        weights = dict(cfg["shapes"])
        bad = set(weights) - {"blobby", "mesh"}
        if bad:
            raise PsctlError(None, f"unknown shape source(s) {sorted(bad)}; choose blobby, mesh")
        self.mesh_data: list[tuple[str, Tensor, Tensor]] = []
        self.mesh_bank: GBuffer | None = None
        folder = None
        if weights.get("mesh", 0) > 0:
            names = list(cfg["meshes"])
            meshes.check_training_meshes(names)
            folder = Path(cfg["mesh_dir"]) if cfg["mesh_dir"] else meshes.mesh_dir()
            for n in names:
                try:
                    path = meshes.find_mesh(n, folder)
                except PsctlError:
                    continue
                v, f = meshes.load_obj(path)
                self.mesh_data.append((path.stem, v.to(self.device), f.to(self.device)))
            if not self.mesh_data and cfg["mesh_cache"] and Path(cfg["mesh_cache"]).is_file():
                bank = meshes.load_views(cfg["mesh_cache"], self.device)
                meshes.check_training_meshes(sorted(set(bank.names)))
                if bank.size != (self.size, self.size):
                    bank = _resize(bank, self.size)
                self.mesh_bank = bank
            if not self.mesh_data and self.mesh_bank is None:
                if cfg["require_meshes"]:
                    raise PsctlError(folder, f"no training mesh found ({', '.join(names)}.obj) and no mesh_cache")
                self.notes.append(f"no training meshes under {folder}: procedural shapes only")
                weights["mesh"] = 0.0
        out = [(k, float(w)) for k, w in weights.items() if w > 0]
        if not out:
            raise PsctlError(folder, "no geometry source left: shapes gives only mesh a positive weight and no "
                                     "training mesh was found here (and no mesh_cache)")
        return out

    def _render(self, n: int, gen: torch.Generator) -> GBuffer:
        """n new G-buffers from the sources, in a random mix drawn from ``gen``."""
        w = torch.tensor([w for _, w in self.sources], device=self.device)
        pick = torch.multinomial(w / w.sum(), n, replacement=True, generator=gen).tolist()
        parts: list[GBuffer] = []
        n_blobby = sum(1 for p in pick if self.sources[p][0] == "blobby")
        if n_blobby:
            parts.append(blobby_gbuffers(n_blobby, self.size, gen, self.cfg["blobby"], chunk=max(8, n_blobby)))
        n_mesh = n - n_blobby
        if n_mesh:
            parts.append(self._mesh_views(n_mesh, gen))
        return GBuffer.cat(parts)

    def _mesh_views(self, n: int, gen: torch.Generator) -> GBuffer:
        from psctl.synth import meshes
        from psctl.synth.shapes import random_rotations

        if self.mesh_bank is not None:
            idx = torch.randint(len(self.mesh_bank), (n,), generator=gen, device=self.device)
            return self.mesh_bank.take(idx)
        which = torch.randint(len(self.mesh_data), (n,), generator=gen, device=self.device).tolist()
        rots = random_rotations((n,), gen)
        fill = 0.6 + 0.35 * torch.rand(n, generator=gen, device=self.device)
        out = []
        for i, j in enumerate(which):
            name, v, f = self.mesh_data[j]
            out.append(meshes.mesh_views(v, f, rots[i:i + 1], self.size, fill=float(fill[i]), name=name))
        return GBuffer.cat(out)


def _resize(g: GBuffer, size: int) -> GBuffer:
    import torch.nn.functional as F

    n = F.normalize(F.interpolate(g.normals, size=(size, size), mode="bilinear", align_corners=False), dim=1)
    m = F.interpolate(g.mask.float(), size=(size, size), mode="bilinear", align_corners=False) > 0.5
    d = F.interpolate(g.depth, size=(size, size), mode="nearest")
    return GBuffer(n * m, d, m, g.names)


def sample_crops(pool: GeometryPool, b: int, cfg: dict, gen: torch.Generator) -> dict[str, Tensor]:
    """Crop b samples out of the pool (bilinear), with rescale, rotation and mirror.

    Returns normals [b, 3, P] in the output frame, mask [b, 1, P] (float 0/1), horizon
    [b, K, P] in the source frame, the 2 x 2 map ``to_src`` taking output-frame (x, y-up)
    directions to source-frame ones, ``slot`` [b], and ``transfer`` [b, 10, P] (source frame;
    None without interreflections); with ``cfg["near_lights"]`` also ``src_xy`` [b, 2, P], each
    pixel's source position in source pixels from the G-buffer's object centroid (x right, y up,
    for ``render.near_field``),
    and ``radius`` [b], the object's radius in source pixels (its area as a disk).
    """
    dev = pool.device
    s, c = pool.size, cfg["crop"]
    slot = torch.randint(len(pool.names), (b,), generator=gen, device=dev)
    data = pool.data
    # crop centre: a random object pixel of the chosen G-buffer (inverse-CDF draw), plus jitter
    cum = pool.cum[slot]  # [b, S*S] running count of object pixels
    u = torch.rand(b, 1, generator=gen, device=dev) * cum[:, -1:]
    pix = torch.searchsorted(cum, u, right=True)[:, 0].clamp_max(s * s - 1)
    cx = ((pix % s).float() + 0.5) / s * 2 - 1  # grid coordinates: x right, y down
    cy = ((pix // s).float() + 0.5) / s * 2 - 1
    lo, hi = cfg["scale"]
    sw = rescaled_sides(lo, hi, cfg["scale_law"], b, gen, dev)  # rescaled sides (paper: randint)
    sh = rescaled_sides(lo, hi, cfg["scale_law"], b, gen, dev)
    ex, ey = c / sw, c / sh  # half-extent of the window in source grid units
    cx = cx + (torch.rand(b, generator=gen, device=dev) - 0.5) * ex
    cy = cy + (torch.rand(b, generator=gen, device=dev) - 0.5) * ey
    # keep the window inside the view when it fits (a window larger than the view is centred)
    cx = torch.where(ex < 1, torch.maximum(torch.minimum(cx, 1 - ex), -1 + ex), torch.zeros_like(cx))
    cy = torch.where(ey < 1, torch.maximum(torch.minimum(cy, 1 - ey), -1 + ey), torch.zeros_like(cy))
    theta = 2 * math.pi * torch.rand(b, generator=gen, device=dev) if cfg["rotate"] else torch.zeros(b, device=dev)
    flip = torch.where(torch.rand(b, generator=gen, device=dev) < 0.5, -1.0, 1.0) if cfg["flip"] \
        else torch.ones(b, device=dev)
    cos, sin = torch.cos(theta), torch.sin(theta)
    # source = centre + Rot(theta) diag(ex, ey) diag(flip, 1) (u, v), all in grid coordinates
    g = (torch.arange(c, device=dev, dtype=torch.float32) + 0.5) / c * 2 - 1
    v, u = torch.meshgrid(g, g, indexing="ij")
    u, v = u.reshape(1, -1), v.reshape(1, -1)  # [1, P]
    a = (flip * ex)[:, None] * u
    bb = ey[:, None] * v
    gx = cx[:, None] + cos[:, None] * a - sin[:, None] * bb
    gy = cy[:, None] + sin[:, None] * a + cos[:, None] * bb
    px = (gx + 1) / 2 * s - 0.5  # pixel coordinates in the source
    py = (gy + 1) / 2 * s - 0.5
    x0, y0 = px.floor(), py.floor()
    fx, fy = (px - x0)[..., None], (py - y0)[..., None]
    # normal and mask: bilinear; horizon: nearest pixel (it is only compared with light angles)
    out = 0.0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        inb = ((xi >= 0) & (xi < s) & (yi >= 0) & (yi < s))[..., None]
        idx = (yi.clamp(0, s - 1) * s + xi.clamp(0, s - 1)).long()
        out = out + data[slot[:, None], idx] * (w * inb)  # [b, P, 4]
    out = out.transpose(1, 2)  # [b, 4, P]
    idx = (py.round().clamp(0, s - 1) * s + px.round().clamp(0, s - 1)).long()
    horizon = pool.horizon[slot[:, None], idx].transpose(1, 2).float()  # [b, K, P]
    pool_transfer = getattr(pool, "transfer", None)  # (a pool-like object may lack it)
    transfer = None if pool_transfer is None else pool_transfer[slot[:, None], idx].transpose(1, 2)  # [b, 10, P]
    msk = (out[:, 3:4] > 0.5).float()
    n_src = torch.nn.functional.normalize(out[:, :3], dim=1)
    # directions: output (x, y-up) -> grid (x, y-down) is diag(1, -1); output_grid = F Rot(-theta) source_grid
    nxg, nyg = n_src[:, 0], -n_src[:, 1]
    rx = cos[:, None] * nxg + sin[:, None] * nyg
    ry = -sin[:, None] * nxg + cos[:, None] * nyg
    normals = torch.stack([flip[:, None] * rx, -ry, n_src[:, 2]], 1) * msk
    # output (x, y-up) -> source (x, y-up): undo the mirror, rotate by theta (grid), back to y-up
    d = torch.diag(torch.tensor([1.0, -1.0], device=dev))
    rot = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)  # [b, 2, 2] grid
    fl = torch.diag_embed(torch.stack([flip, torch.ones_like(flip)], -1))
    to_src = d @ rot @ fl @ d
    out = {"normals": normals, "mask": msk, "horizon": horizon, "to_src": to_src, "slot": slot, "transfer": transfer}
    if cfg.get("near_lights"):  # where the object's centre is, for near_field (no random draws)
        inside = (data[slot, :, 3] > 0.5).float()  # [b, S*S]
        area = inside.sum(1).clamp_min(1.0)
        grid = torch.arange(s * s, device=dev)
        col, row = (grid % s).float(), (grid // s).float()
        ccol, crow = (inside * col).sum(1) / area, (inside * row).sum(1) / area
        out["src_xy"] = torch.stack([px - ccol[:, None], crow[:, None] - py], 1)  # y up
        out["radius"] = (area / math.pi).sqrt()
    return out


def object_mean(img: Tensor, msk: Tensor) -> Tensor:
    """Mean object pixel of each sample: images [b, n, 3, p], masks [b, 1, p] -> [b]."""
    count = (msk.sum((1, 2)) * img.shape[1] * 3).clamp_min(1.0)
    return (img.clamp_min(0.0) * msk[:, None]).sum((1, 2, 3)) / count


def capture_rounding(img: Tensor, msk: Tensor, gen: torch.Generator, capture: dict) -> Tensor:
    """Images [b, n, 3, p] as an integer camera at a random dark exposure would record them (see
    DEFAULT_CONFIG["capture"]), at their own brightness; masks [b, 1, p]. Samples not drawn
    (chance 1 - p) are returned unchanged."""
    b, dev = img.shape[0], img.device
    lo, hi = capture["mean"]
    pick = torch.rand(b, generator=gen, device=dev) < float(capture.get("p", 0.5))
    want = torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * torch.rand(b, generator=gen, device=dev))
    s = (want / object_mean(img, msk).clamp_min(1e-8))[:, None, None, None]
    peak = float(2 ** int(capture.get("bits", 8)) - 1)
    to_int = torch.floor if capture.get("floor", False) else torch.round
    rounded = to_int((img * s).clamp(0.0, 1.0) * peak) / (peak * s)
    return torch.where(pick[:, None, None, None], rounded, img)


def object_windows(mask: Tensor, side: int, w: int, gen: torch.Generator) -> Tensor:
    """One w x w window per sample, centred (as far as the view allows) on a random object pixel.

    mask [B, side * side] (0/1) -> [B, 2] long (top row, left column); an empty mask gives the
    view's centre.
    """
    b = mask.shape[0]
    cum = mask.float().cumsum(1)
    u = torch.rand(b, 1, generator=gen, device=mask.device) * cum[:, -1:]
    pix = torch.searchsorted(cum, u, right=True)[:, 0].clamp_max(side * side - 1)
    pix = torch.where(cum[:, -1] > 0, pix, torch.full_like(pix, side * side // 2 + side // 2))
    top = (pix // side - w // 2).clamp(0, side - w)
    left = (pix % side - w // 2).clamp(0, side - w)
    return torch.stack([top, left], 1)


class SynthDataset(torch.utils.data.IterableDataset):
    """The stream for a torch DataLoader with worker processes (``batch_size=None``: the
    stream already batches). Worker w uses seed ``seed + 7919 * w`` and one torch thread: on a
    CPU, a few single-threaded workers are much faster than one multi-threaded stream, and
    multi-threaded torch collapses when the cores are shared.

        loader = DataLoader(SynthDataset(cfg), batch_size=None, num_workers=2, persistent_workers=True)
    """

    def __init__(self, config: dict | None = None, **overrides):
        super().__init__()
        self.cfg = make_config(config, **overrides)
        # the mesh options the caller did not name: make_config filled in the defaults, which
        # SynthStream would take for named meshes and refuse where lucy is absent (a fresh clone)
        self._unnamed = {"meshes", "mesh_dir"} - set(config or {}) - set(overrides)

    def __iter__(self) -> Iterator[dict]:
        info = torch.utils.data.get_worker_info()
        cfg = {k: v for k, v in self.cfg.items() if k not in self._unnamed}
        if info is not None:
            torch.set_num_threads(1)  # this process is a worker: its own thread budget
            cfg["seed"] = int(cfg["seed"]) + 7919 * info.id
        return iter(SynthStream(cfg))


class SynthStream:
    """An endless, seeded iterator of training batches (see the module docstring).

    Each batch is a dict:
        images      [B, N, 3, H, W] float32, e * radiance * exposure (clipped, noisy)
        lights      [B, N, 3] unit directions (x right, y up, z toward the camera)
        intensities [B, N] light intensities e (1 when intensities="unit")
        normals     [B, 3, H, W] unit normals, 0 outside the mask
        masks       [B, 1, H, W] float 0/1
        shapes      list of B source names ("blobby", "lucy", ...)
        windows     [B, 2] long, only with the ``windows`` option: top-left corner of a random
                    window around an object pixel (PS-FCN† trains on it; LCNet sees the view)
    The same config (seed included) gives the same batches on the same device.
    """

    def __init__(self, config: dict | None = None, **overrides):
        self.cfg = make_config(config, **overrides)
        cfg = self.cfg
        self.device = torch.device(cfg["device"])
        self.gen = torch.Generator(device=self.device).manual_seed(int(cfg["seed"]))
        probs = dict(cfg["materials"])
        self.table = None
        if probs.get("merl", 0) > 0:
            self.table = M.load_merl(cfg["merl"], self.device)
        self.probs = probs
        self.pool = GeometryPool(cfg, self.gen)
        self.notes = self.pool.notes

    def __iter__(self) -> Iterator[dict]:
        while True:
            yield self.next_batch()

    def state_dict(self) -> dict:
        """What it takes to continue with exactly the same batches (a few KB): the generator
        state and the geometry pool's chunk seeds. Same config and device needed."""
        return {"generator": self.gen.get_state(), "pool": self.pool.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Continue from ``state_dict()`` (re-renders the geometry pool from its seeds)."""
        self.pool.load_state_dict(state["pool"])
        self.gen.set_state(state["generator"].cpu())

    def next_batch(self) -> dict:
        cfg, gen, dev = self.cfg, self.gen, self.device
        b, n, c = cfg["batch_size"], cfg["n_images"], cfg["crop"]
        crops = sample_crops(self.pool, b, cfg, gen)
        normals, msk = crops["normals"], crops["mask"]
        p = normals.shape[-1]

        # materials: one per sample, a second one and a blend map for some, textures for some
        mat = M.sample_materials(b, gen, self.table, self.probs, cfg["merl_names"])
        mat = M.take(mat, torch.argsort((~mat["abc"]).to(torch.int8), stable=True))  # ABC first: see lobes()
        blend = torch.rand(b, generator=gen, device=dev) < cfg["blend"]
        kinds = [M.BLENDS[i] for i in torch.randint(3, (b,), generator=gen, device=dev).tolist()]
        sv = blend.nonzero()[:, 0]
        mat_b, weights = None, None
        if len(sv):
            mat_b = M.sample_materials(len(sv), gen, self.table, self.probs, cfg["merl_names"])
            mat_b = M.take(mat_b, torch.argsort((~mat_b["abc"]).to(torch.int8), stable=True))
            weights = M.blend_weights([kinds[i] for i in sv.tolist()], c, c, gen).reshape(len(sv), 1, p)
        textured = torch.rand(b, generator=gen, device=dev) < cfg["texture"]
        texture = None
        if bool(textured.any()):
            tex = M.albedo_texture(b, c, c, gen).reshape(b, 3, p)
            texture = torch.where(textured[:, None, None], tex, torch.ones_like(tex))

        # lights
        lights = L.sample_lights((b, n), gen, cfg["lights"], cfg["max_zenith"])
        ints = L.sample_intensities((b, n), gen, cfg["intensities"], lights=lights)
        vis = None
        l_src = torch.cat([torch.einsum("bij,bnj->bni", crops["to_src"], lights[..., :2]), lights[..., 2:]], -1)
        if cfg["shadows"]:
            vis = R.horizon_visibility(crops["horizon"], l_src)
        ambient = cfg["ambient"] * torch.rand(b, generator=gen, device=dev) if cfg["ambient"] else None
        indirect = None
        if cfg["interreflection"]:  # (draws only when enabled: older recipes keep their batches)
            ir = cfg["interreflection"]
            lo_a, hi_a = ir.get("albedo", (0.0, 0.9))
            on = torch.rand(b, generator=gen, device=dev) < float(ir.get("p", 0.5))
            a = (lo_a + (hi_a - lo_a) * torch.rand(b, generator=gen, device=dev)) * on
            kd = mat["kd"]
            rho = a[:, None] * kd / kd.amax(1, keepdim=True).clamp_min(1e-6)
            indirect = R.indirect_irradiance(crops["transfer"], l_src, rho)

        shade_lights, fall = lights, None
        if cfg["near_lights"]:  # (draws only when enabled: older recipes keep their batches)
            near = cfg["near_lights"]
            lo_r, hi_r = near.get("radii", (10.0, 40.0))
            on = torch.rand(b, generator=gen, device=dev) < float(near.get("p", 0.5))
            radii = lo_r + (hi_r - lo_r) * torch.rand(b, generator=gen, device=dev)
            dist = torch.where(on, radii * crops["radius"], torch.full_like(radii, math.inf))
            shade_lights, fall = R.near_field(l_src, crops["src_xy"], crops["to_src"], dist)

        img = R.shade(normals, shade_lights, mat, vis, texture=texture, ambient=ambient, indirect=indirect,
                      falloff=fall)  # [b, n, 3, p]
        if mat_b is not None:  # blends: f = w f_A + (1 - w) f_B on the blended samples only
            img_b = R.shade(normals[sv], shade_lights[sv], mat_b, None if vis is None else vis[sv],
                            texture=None if texture is None else texture[sv], ambient=None if ambient is None else ambient[sv],
                            indirect=None if indirect is None else indirect[sv], falloff=None if fall is None else fall[sv])
            w = weights[:, None]
            img[sv] = w * img[sv] + (1.0 - w) * img_b
        # exposure: scale each sample so its mean object radiance hits a random target
        lo, hi = cfg["exposure"]
        target = torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * torch.rand(b, generator=gen, device=dev))
        mean = object_mean(img, msk)  # shading is non-negative: the clamp there changes nothing
        true_ints = ints
        if cfg["intensity_error"]:  # (draws only when enabled: older recipes keep their batches)
            true_ints = ints * intensity_errors(b, n, cfg["intensity_error"], gen, dev)
        img.mul_(((target / mean.clamp_min(1e-8))[:, None] * true_ints)[..., None, None])  # exposure x intensity
        if cfg["clip"] is not None:
            img.clamp_(max=cfg["clip"])
        if cfg["noise"]:
            R.uniform_noise(img, gen, cfg["noise"])
        if cfg["quantize"]:
            img = R.quantize(img, cfg["quantize"])
        if cfg["capture"]:
            img = capture_rounding(img, msk, gen, cfg["capture"])
        if cfg["mask_images"]:
            img.mul_(msk[:, None])

        shapes = [self.pool.names[i] for i in crops["slot"].tolist()]
        out = {
            "images": img.reshape(b, n, 3, c, c),
            "lights": lights,
            "intensities": ints,
            "normals": normals.reshape(b, 3, c, c),
            "masks": msk.reshape(b, 1, c, c),
            "shapes": shapes,
        }
        if cfg["windows"] is not None:  # drawn here, from the stream's generator: a resume repeats them
            out["windows"] = object_windows(msk.reshape(b, c * c), c, int(cfg["windows"]), gen)
        if cfg["direction_error"]:  # drawn last, only when enabled: the batch is otherwise unchanged
            out["lights"] = direction_errors(lights, cfg["direction_error"], gen)  # listed; rendered with `lights`
        self.pool.refresh(b)
        return out

"""The inference engine for PS-FCN-style networks: memory independent of the number of images and
growing slowly with the image size (the network's activations and fused features are capped;
what remains is a few whole-frame arrays: about 65 MB a megapixel above about 0.9 GB, helper-171),
results equal to one pass of the network over the whole stack.

The authors' test code stacks every image, runs the extractor on each, keeps every feature map
and takes the max at the end: memory grows with the number of images (about 14 GB for one
96-image DiLiGenT object). Here:

1. Crop. Only the mask's bounding box is processed, grown by ``margin`` (>= the network's
   receptive field radius, so the crop does not change the result) and aligned to multiples of 4
   (the network's stride, so the sampling grid stays that of the full image). Pixels outside the
   mask are zeroed (as the authors do); the result is pasted back into the full frame.
2. Streaming fusion. Images are read one at a time and go through the extractor in chunks of
   ``chunk``; the fused feature keeps a running max (or sum for mean fusion). Memory: one fused
   map [128, h/2, w/2] plus one chunk, whatever the number of images.
3. +N needs every image of a pixel before any goes through the network (the norm runs over the
   images). A first pass accumulates the per-pixel sum of squares ([h, w, 3], cheap) and keeps up
   to ``cache_mb`` of the cropped images; the second pass re-reads only the images not kept.
4. Tiling. Regions larger than ``tile`` are cut into tiles, each grown by ``halo`` (>= the
   receptive field radius, a multiple of 4): the max fusion is per pixel and the halo holds every
   input an inner pixel sees, so tiled == untiled (the zero padding at a tile border only reaches
   the halo). Tiles are grouped so that at most ``group_mb`` of fused features are held at once;
   each group is one pass over the images. Passes after the first read only the group's part of
   each image where the reader can (``reader.band``: psctl.io.capture.ImageCheck.reader decodes
   the rows down to the part's last, not the whole image, and does not check again what the
   first pass checked); the hot pixels the first pass clamped are set alike. 12 MP 16-bit PNGs, 8
   groups: the 8 group passes' reads took 0.32 s a image instead of 0.76 (CPU, helper-178).

channels_last and torch.inference_mode throughout; ``device`` auto | cpu | cuda | cuda:K. Autocast
(``config["autocast"]``: bf16 on CUDA and on CPUs with native bf16, fp16 on CUDA) is off by default:
on the CPU it moved the normals by 0.07-0.09 degrees on average, at most 0.6 (docs/performance.md,
"bf16 autocast on the CPU, trained weights"), and results should not depend on the machine.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.classic import dark_pixels
from psctl.errors import PsctlError, naming
from psctl.hotpixels import clamp_hot_pixels, hot_pixel_notes
# the constants from psctl.models, not ps_fcn: importing this module does not import torch, so that
# the images can be decoded while torch imports (psctl.io.prefetch)
from psctl.models import HALO, NETWORK_METHODS, NORM_EPS, STRIDE, check_device_name, check_downsample

if TYPE_CHECKING:
    import torch

    from psctl.api import ProgressFactory
    from psctl.io.capture import Capture, DecodeMemo
    from psctl.models.ps_fcn import PSFCN

DEFAULT_INFER = {
    "device": "auto",  # auto | cpu | cuda (| cuda:N)
    "chunk": None,  # images per extractor batch: None = 2 on CPU, 32 on CUDA (fewer for large tiles, see work_mb)
    "crop": True,  # process only the mask's bounding box (+ margin)
    "margin": HALO,  # context kept around the mask's bounding box, pixels
    "tile": 512,  # tile side (kept output), pixels; larger regions are tiled
    "halo": HALO,  # context kept around each tile, pixels (>= receptive field radius)
    "group_mb": 256,  # fused features held per pass over the images
    # cropped images kept from the first pass for the next ones (RSS stays flat); the ensemble keeps
    # up to this much more, its first network's reads for the second (ReadMemo), and sdps as much,
    # the images as decoded for its passes (psctl.io.capture.DecodeMemo)
    "cache_mb": 64,
    "work_mb": None,  # extractor activations per chunk, caps chunk for large tiles: None = 256 CPU, 4096 CUDA
    "channels_last": True,
    "autocast": None,  # None | "bf16" (CUDA, CPUs with native bf16) | "fp16" (CUDA); off by default
    # a helper process decodes the images (cut to the region) into a ring of shared memory of at most
    # this many MB while this one imports torch and loads the weights (psctl.io.prefetch); 0 = off
    "prefetch_mb": 256,
    # symmetric views averaged (psctl.symmetry): 1 = one pass (the paper); 8 = the capture turned
    # and mirrored about the view axis, each view's normals turned back, their unit mean. 8x the work.
    "views": 1,
    # the network runs on the capture shrunk by this integer factor (each k x k block's mean over
    # the object, images and mask), its normals interpolated back to full size: about 1/k^2 of the
    # work, for a quick look; detail is lost (docs/models.md, "Downsampling"). 1 = full size.
    "downsample": 1,
    # where PS-FCN (no +N) takes the mean its exposure scale brings to the trained one: "mask" (the
    # mask's pixels), "found" (the same, the mask being the object found without a mask file: the
    # words differ) or "lit" (lit_pixels: the bright part of the frame). The runs without a mask
    # (no mask.png, mask=None) use "found" where an object is found for the networks (psctl.api),
    # else "lit": a dark background would halve the frame's mean
    "exposure_pixels": "mask",
    # normals are also given this many pixels beyond the mask (a square step per pixel), the network's
    # answer there read from the object beside them, their own observations not read: the object
    # found without a mask misses part of its dark rim (psctl.api, FOUND_GROW). 0 = the mask only
    "grow": 0,
}
EXPOSURE_PIXELS = ("mask", "lit", "found")  # found: the mask is the object found without a file

FEATURES = 128  # extractor output channels
_BYTES_PER_PIXEL = 400  # extractor activations per input pixel and image (fp32, channels_last: 384 measured)

# reader(start, box) yields images start, start + 1, ... as float32 [h, w, 3] cropped to box.
Reader = Callable[[int, tuple[slice, slice]], Iterator[np.ndarray]]


@dataclass
class InferResult:
    normals: np.ndarray  # [H, W, 3] float32 unit normals, 0 outside the mask
    dark: np.ndarray  # [H, W] bool: mask pixels dark in every image (the network still answers)
    info: dict = field(default_factory=dict)  # device, region, tiles, passes, seconds, ...
    notes: list[str] = field(default_factory=list)
    # [H, W] float32 degrees, the ensemble only: the largest angle between its members' normals
    # (0 outside the mask); None for one network
    spread: np.ndarray | None = None


# --- geometry ---------------------------------------------------------------------------------

def _ceil(v: int, m: int) -> int:
    return -(-v // m) * m


def region_box(mask: np.ndarray, cfg: dict) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the region ``run_network`` processes under the config ``cfg``."""
    H, W = mask.shape
    return crop_region(mask, cfg["margin"]) if cfg["crop"] else (0, _ceil(H, STRIDE), 0, _ceil(W, STRIDE))


def check_grow(grow: object) -> int:
    """The ``grow`` setting: a whole number of pixels, 0 to HALO (beyond HALO the network sees
    nothing of the object)."""
    if isinstance(grow, bool) or not isinstance(grow, (int, np.integer)) or not 0 <= grow <= HALO:
        raise PsctlError(None, f"grow must be a whole number of pixels from 0 to {HALO}, not {grow!r}")
    return int(grow)


def grow_mask(mask: np.ndarray, grow: int) -> np.ndarray:
    """[H, W] bool ``mask`` grown by ``grow`` pixels (3 x 3 steps: a square of side 2 grow + 1 about
    each pixel); ``mask`` itself for 0."""
    if grow == 0:
        return mask
    from scipy import ndimage

    return ndimage.binary_dilation(mask, np.ones((2 * grow + 1, 2 * grow + 1), bool))


def read_box(box: tuple[int, int, int, int], shape: tuple[int, int]) -> tuple[slice, slice]:
    """The part of a region ``box`` inside an image of ``shape`` (H, W): what is read of each image."""
    y0, y1, x0, x1 = box
    return slice(y0, min(y1, shape[0])), slice(x0, min(x1, shape[1]))


def crop_region(mask: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the mask's bounding box grown by ``margin``, corners on multiples of
    STRIDE. y1/x1 may pass the image by < STRIDE (zero padding, as the authors pad)."""
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    y0 = max(int(ys.min()) - margin, 0) // STRIDE * STRIDE
    x0 = max(int(xs.min()) - margin, 0) // STRIDE * STRIDE
    y1 = _ceil(min(int(ys.max()) + 1 + margin, h), STRIDE)
    x1 = _ceil(min(int(xs.max()) + 1 + margin, w), STRIDE)
    return y0, y1, x0, x1


@dataclass(frozen=True)
class Tile:
    inner: tuple[int, int, int, int]  # y0, y1, x0, x1 of the output kept, region coordinates
    outer: tuple[int, int, int, int]  # inner grown by the halo, clipped to the region

    @property
    def fused_bytes(self) -> int:
        y0, y1, x0, x1 = self.outer
        return FEATURES * (y1 - y0) // 2 * (x1 - x0) // 2 * 4


def plan_tiles(h: int, w: int, tile: int, halo: int) -> list[Tile]:
    """Tiles covering an h x w region (multiples of STRIDE), row-major."""
    if h % STRIDE or w % STRIDE:
        raise ValueError(f"region {h}x{w} is not a multiple of {STRIDE}")
    if tile < STRIDE or tile % STRIDE or halo % STRIDE or halo < 0:
        raise PsctlError(None, f"tile ({tile}) and halo ({halo}) must be multiples of {STRIDE}, tile >= {STRIDE}")
    tiles = []
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            outer = (max(y0 - halo, 0), min(y1 + halo, h), max(x0 - halo, 0), min(x1 + halo, w))
            tiles.append(Tile((y0, y1, x0, x1), outer))
    return tiles


def group_tiles(tiles: list[Tile], limit_bytes: int) -> list[list[Tile]]:
    """Consecutive tiles whose fused features together stay under ``limit_bytes`` (>= 1 tile)."""
    groups: list[list[Tile]] = []
    size = 0
    for t in tiles:
        if groups and size + t.fused_bytes <= limit_bytes:
            groups[-1].append(t)
            size += t.fused_bytes
        else:
            groups.append([t])
            size = t.fused_bytes
    return groups


def _bbox(tiles: list[Tile]) -> tuple[int, int, int, int]:
    return (min(t.outer[0] for t in tiles), max(t.outer[1] for t in tiles),
            min(t.outer[2] for t in tiles), max(t.outer[3] for t in tiles))


# --- devices ----------------------------------------------------------------------------------

def _one_thread_after_fork() -> None:
    import torch  # (imported in the parent: this costs nothing)

    torch.set_num_threads(1)


_FORK_HOOK: list[bool] = []  # registered once per process (os.register_at_fork cannot be undone)


def pick_device(name: str = "auto") -> "torch.device":
    """auto: CUDA when torch sees a GPU, else CPU. Asking for cuda without one is a user error.

    Once psctl has picked the CPU for a network, a process forked from this one (a
    ProcessPoolExecutor's worker on Linux) runs torch on one thread: GNU OpenMP's thread pool
    does not survive a fork, and the child's first parallel operation would wait for the
    parent's threads for ever (an audit: psctl.run_normals mapped over folders hung after a
    psctl call in the parent). A spawn or forkserver context gives workers their own thread
    pools instead. The hook lasts for the process's life: a fork-based server that loads psctl
    and picks the CPU before forking (gunicorn --preload, celery prefork) gets one torch thread
    per worker."""
    import torch

    name = check_device_name(name)
    if name == "auto" and torch.cuda.is_available():
        return torch.device("cuda")
    if name in ("auto", "cpu"):
        if not _FORK_HOOK and hasattr(os, "register_at_fork"):
            os.register_at_fork(after_in_child=_one_thread_after_fork)
            _FORK_HOOK.append(True)
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise PsctlError(None, f"--device {name}: torch sees no CUDA GPU (torch {torch.__version__}); "
                                   "use --device cpu or auto")
        return torch.device(name)
    raise AssertionError(name)  # check_device_name let it through


def cpu_has_bf16() -> bool:
    """True when this CPU runs bf16 matrix kernels natively (AVX512-BF16 or AMX); elsewhere
    torch emulates them and autocast would be slower than float32.

    Not ``torch.ops.mkldnn._is_mkldnn_bf16_supported()``: oneDNN also says yes on AVX-512 CPUs
    without AVX512-BF16 (it emulates bf16 there), where training PS-FCN measured 1.23 samples/s
    in bf16 against 3.52 in float32 (a 2-core Cascade Lake, 2026-11-27)."""
    import torch

    try:
        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    except (AttributeError, RuntimeError):  # private API: read the flags the kernel reports
        try:
            flags = Path("/proc/cpuinfo").read_text().split()
        except OSError:
            return False
        return "avx512_bf16" in flags or "amx_bf16" in flags or "amx_tile" in flags


def _autocast(device: "torch.device", kind: str | None):
    import contextlib

    import torch

    if kind is None:
        return contextlib.nullcontext()
    dtypes = {"bf16": torch.bfloat16, "fp16": torch.float16}
    if kind not in dtypes:
        raise PsctlError(None, f"unknown autocast {kind!r}; choose from bf16, fp16")
    if device.type == "cpu" and kind == "bf16":
        if not cpu_has_bf16():  # emulated bf16 is slower than float32
            raise PsctlError(None, "bf16 needs a CUDA GPU or a CPU with native bf16 (AVX512-BF16 or AMX); this CPU "
                                   "would emulate it, slower than float32: use --precision float32")
        return torch.autocast("cpu", dtype=torch.bfloat16)
    if device.type != "cuda":
        raise PsctlError(None, f"{kind} is for CUDA devices (bf16 also on CPUs with native bf16), not {device}: "
                               f"use --precision float32" + (" or bf16" if cpu_has_bf16() else ""))
    if kind == "bf16" and torch.cuda.get_device_capability(device)[0] < 8:
        # torch.cuda.is_bf16_supported() says yes on older GPUs too, which emulate it, slowly
        raise PsctlError(None, f"bf16 needs an Ampere or newer GPU ({torch.cuda.get_device_name(device)} would emulate it, "
                               "slower than float32): use --precision fp16 or float32")
    return torch.autocast("cuda", dtype=dtypes[kind])


def check_autocast(kind: str, device: str = "auto") -> None:
    """Autocast ``kind`` ("bf16", "fp16") on ``device``, checked before any work: bf16 on a CPU or
    GPU that would emulate it, or fp16 off CUDA, is a one-line error (``psctl.models.precision_autocast``)."""
    _autocast(pick_device(device), kind)


# --- the image stream -------------------------------------------------------------------------

class _RegionImages:
    """The N images cropped to the region, masked, zero padded: [h, w, 3] float32 each.

    Iterable several times. The first pass keeps the first images up to ``cache_bytes``, records
    each pixel's brightest observation, and checks the values; later passes re-read only the
    images not kept.
    """

    def __init__(self, reader: Reader, n: int, box: tuple[int, int, int, int], mask: np.ndarray,
                 cache_bytes: int, advance: Callable[[int], None]):
        y0, y1, x0, x1 = box
        H, W = mask.shape
        self.reader, self.n, self.advance = reader, n, advance
        self.read_box = read_box(box, (H, W))
        self.rh, self.rw = min(y1, H) - y0, min(x1, W) - x0
        self.shape = (y1 - y0, x1 - x0)
        self.mask = mask[self.read_box].astype(np.float32)[..., None]
        self.cache: list[np.ndarray] = []
        self.cache_bytes = cache_bytes
        self.peak = np.zeros(self.shape, np.float32)
        self.passes = 0
        self.inside = np.zeros(self.shape, bool)  # the mask over the padded region
        self.inside[: self.rh, : self.rw] = self.mask[..., 0] > 0
        self.hot: dict[int, int] = {}  # image index -> values clamp_hot_pixels set (first pass)
        # image index -> (rows, columns, channels, values) clamp_hot_pixels set, region coordinates: what a
        # later pass over part of the image sets (the clamp's level is the whole image's mean)
        self.fixes: dict[int, tuple[np.ndarray, ...]] = {}

    def _prepare(self, img: np.ndarray, k: int, part: tuple[int, int, int, int] | None = None) -> np.ndarray:
        y0, y1, x0, x1 = part or (0, self.shape[0], 0, self.shape[1])
        rh, rw = max(min(y1, self.rh) - y0, 0), max(min(x1, self.rw) - x0, 0)  # what the image holds of part
        if img.ndim == 2:  # grey: the network takes RGB
            img = img[..., None]
        if img.shape[:2] != (rh, rw):
            raise PsctlError(None, f"image {k + 1}: size changed while reading")
        out = np.zeros((y1 - y0, x1 - x0, 3), np.float32)
        np.multiply(img[..., :3], self.mask[y0:y0 + rh, x0:x0 + rw], out=out[:rh, :rw])
        return out

    def part(self, y0: int, y1: int, x0: int, x1: int) -> Iterator[np.ndarray]:
        """The images cut to rows y0:y1, columns x0:x1 of the region: the first pass's images cut
        (it reads them whole), later passes' read as that part only where the reader can
        (``reader.band``: the rows decoded down to y1, not the whole image; psctl.io.capture),
        with the hot pixels the first pass found set alike. The same values either way."""
        band = getattr(self.reader, "band", None)
        if self.passes == 0 or band is None or (y0, y1, x0, x1) == (0, *self.shape[:1], 0, self.shape[1]):
            for x in self:
                yield x[y0:y1, x0:x1]
            return
        self.passes += 1
        for x in self.cache:
            self.advance(1)
            yield x[y0:y1, x0:x1]
        k = len(self.cache)
        (ry, rx), inside = self.read_box, y0 < self.rh and x0 < self.rw
        box = (slice(ry.start + y0, ry.start + min(y1, self.rh)), slice(rx.start + x0, rx.start + min(x1, self.rw)))
        for img in band(k, box) if inside else (np.zeros((0, 0, 3), np.float32) for _ in range(k, self.n)):
            x = self._prepare(img, k, (y0, y1, x0, x1)) if inside else np.zeros((y1 - y0, x1 - x0, 3), np.float32)
            fix = self.fixes.get(k)
            if fix is not None and inside:
                ys, xs, cs, v = fix
                sel = (ys >= y0) & (ys < y1) & (xs >= x0) & (xs < x1)
                x[ys[sel] - y0, xs[sel] - x0, cs[sel]] = v[sel]
            self.advance(1)
            yield x
            k += 1
        if k != self.n:
            raise PsctlError(None, f"expected {self.n} images, got {k}")

    def __iter__(self) -> Iterator[np.ndarray]:
        first = self.passes == 0
        self.passes += 1
        for x in self.cache:  # later passes: cached images count on the progress bar too
            self.advance(1)
            yield x
        k = len(self.cache)
        for img in self.reader(k, self.read_box):
            x = self._prepare(img, k)
            if first and not np.isfinite(x).all():
                raise PsctlError(None, f"image {k + 1} contains NaN or infinite values")
            clamped, hot = clamp_hot_pixels(x, self.inside)  # the same in every pass: it sees one image
            if first and hot:
                self.hot[k] = hot
                where = np.nonzero(clamped != x)
                self.fixes[k] = (*where, clamped[where])
            x = clamped
            if first:
                for c in range(3):  # channel by channel: x.max(-1) over a length-3 axis is ~15x slower
                    np.maximum(self.peak, x[..., c], out=self.peak)
                if len(self.cache) == k and (k + 1) * x.nbytes <= self.cache_bytes:
                    self.cache.append(x)
            self.advance(1)
            yield x
            k += 1
        if k != self.n:
            raise PsctlError(None, f"expected {self.n} images, got {k}")


# --- the engine -------------------------------------------------------------------------------

def lit_pixels(brightness: np.ndarray, bins: int = 256) -> np.ndarray:
    """[H, W] each pixel's summed brightness over the images -> [H, W] bool, the lit part of the
    frame: Otsu's threshold on log brightness (parameter-free, independent of exposure), so a
    capture without a mask takes its exposure from the object rather than the dark background
    around it. Where the brightness does not split (all pixels alike), every lit pixel counts.

    Chosen on psctl's synthetic test set (16 objects, 64 lights) with a dark Lambertian
    background added (albedo 0, 0.01, 0.03, plus noise; benchmarks/exposure_no_mask.py): the lit
    pixels' mean was on average 1.01 to 1.05 times the mask's (worst 1.27, a dark material), the
    whole frame's 0.45 to 0.50 (worst 0.32); a threshold at a fixed fraction of the 99th
    percentile failed on dark materials before a 0.03 background (as low as 0.46). The release
    PS-FCN there, without the mask: 4.73 / 5.06 / 5.37 degrees by this rule, 6.60 / 6.82 / 6.97
    by the whole frame's mean, 4.70 with the mask (session 62).
    """
    b = np.asarray(brightness, np.float64)
    positive = b > 0
    if not positive.any():
        return positive
    # pixels at 0 (a render's or a pre-masked background) join the darkest bin: left out, Otsu
    # would split the object itself (its lit mean 1.16x the mask's on a sphere, 1.05x so)
    log = np.empty(b.shape, np.float32)  # float32: 4 bytes a pixel for a 12 MP frame's map
    with np.errstate(invalid="ignore", divide="ignore"):  # numpy's buffered cast may touch the masked-out pixels
        np.log(b, out=log, where=positive, casting="same_kind")
    lo, hi = float(log[positive].min()), float(log[positive].max())
    log[~positive] = lo
    if not hi - lo > 1e-6:
        return positive
    hist, edges = np.histogram(log.ravel(), bins, (lo, hi))
    centre = (edges[:-1] + edges[1:]) / 2
    below = np.cumsum(hist)[:-1].astype(np.float64)  # pixels in bins 0..k, for a split after bin k
    above = log.size - below
    mass = np.cumsum(hist * centre)
    total, mass = mass[-1], mass[:-1]
    with np.errstate(divide="ignore", invalid="ignore"):  # empty sides: scored -1 below
        between = below * above * (mass / below - (total - mass) / above) ** 2
    between[(below == 0) | (above == 0)] = -1.0
    threshold = edges[int(np.argmax(between)) + 1]
    return positive & (log >= threshold)


def lit_mean(pixel_sum: np.ndarray, n: int) -> float:
    """The mean observation over the lit pixels: ``pixel_sum`` [H, W] each pixel's sum over
    ``n`` RGB images; 0.0 where no pixel is lit. The "lit" exposure of PS-FCN and LCNet's guard."""
    lit = lit_pixels(pixel_sum)
    count = int(lit.sum())
    return float(pixel_sum[lit].sum()) / (3.0 * n * count) if count else 0.0


_EXPOSURE_WHERE = {"mask": "inside the mask", "lit": "over the lit pixels",
                   "found": "inside the object found without a mask"}


def exposure_where(exposure_pixels: str) -> str:
    """The words for where an exposure mean is taken (messages), refusing an unknown rule."""
    if exposure_pixels not in EXPOSURE_PIXELS:
        raise PsctlError(None, f"exposure_pixels must be {' or '.join(EXPOSURE_PIXELS)}, not {exposure_pixels!r}")
    return _EXPOSURE_WHERE[exposure_pixels]


def check_float32_scale(factor: float, mean: float, where: str = "inside the mask") -> float:
    """``factor``, the exposure scale of a capture whose mean ``where`` is ``mean``, if float32
    can hold it; a capture of denormal values (mean ~1e-40) is a user error instead of inf."""
    f32 = np.finfo(np.float32)
    if not float(f32.tiny) < factor < float(f32.max):
        raise PsctlError(None, f"the images' mean {where} is {mean:.3g}: too far from 1 to scale in "
                               f"float32; rescale them")
    return factor


def run_network(model: "PSFCN", reader: Reader, n: int, lights: np.ndarray | None, mask: np.ndarray,
                normalization: str = "none", train_images: int | None = None, config: dict | None = None,
                progress: "ProgressFactory | None" = None, label: str = "network",
                input_mean: float | None = None, input_clip: float | None = None) -> InferResult:
    """Normals from a stream of images, memory independent of N and capped in the network's
    activations and features whatever the image size (module docstring).

    Args:
        model: a PSFCN in eval mode (its device is set here).
        reader: see ``Reader``; called once per pass over the images.
        n: number of images.
        lights: [n, 3] unit light directions (None for UPS-FCN).
        mask: [H, W] bool, pixels to estimate (the full image size).
        normalization: "none", "per-channel" or "per-pixel" (+N).
        train_images: q for the sqrt(t / q) factor of +N.
        config: overrides of DEFAULT_INFER.
        input_mean: without +N, scale all images by one factor so that their mean over the mask
            (all images and channels; config ``exposure_pixels`` "lit": over the lit pixels,
            ``lit_pixels``) is this: the exposure the network was trained at (weights metadata
            ``input_mean``). None: the images as they are.
        input_clip: with ``input_mean``, clip the scaled images at this value: the sensor
            saturation of the training data (the recipe's ``data.clip``), so highlights scaled
            far above it look as they did in training. None: no clipping.
    Returns:
        InferResult with [H, W, 3] normals (zero outside the mask).
    """
    import torch

    cfg = {**DEFAULT_INFER, **(config or {})}
    t_start = time.perf_counter()
    exposure_where(cfg["exposure_pixels"])  # an unknown rule is an error before any work
    if n < 1:
        raise PsctlError(None, "no images")
    if model.uses_lights:
        if lights is None:
            raise PsctlError(None, "this network needs light directions (light_directions.txt)")
        lights = np.asarray(lights, np.float32)
        if lights.shape != (n, 3):
            raise PsctlError(None, f"lights must be [{n}, 3], got {lights.shape}")
    if normalization != "none" and not train_images:
        raise PsctlError(None, "+N normalisation needs the training image count q")
    if normalization != "none":
        input_mean = None  # +N removes any global scale
    elif input_mean is not None and not (math.isfinite(input_mean) and input_mean > 0):
        raise PsctlError(None, f"input_mean must be a positive number, got {input_mean!r}")
    if input_clip is not None and not (math.isfinite(input_clip) and input_clip > 0):
        raise PsctlError(None, f"input_clip must be a positive number, got {input_clip!r}")
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise PsctlError(None, "mask is empty (no foreground pixel)")
    keep = grow_mask(mask, check_grow(cfg["grow"]))  # where normals are given
    device = pick_device(cfg["device"])
    fmt = torch.channels_last if cfg["channels_last"] else torch.contiguous_format
    model = model.to(device=device, memory_format=fmt).eval()

    H, W = mask.shape
    box = region_box(keep, cfg)
    h, w = box[1] - box[0], box[3] - box[2]
    tiles = plan_tiles(h, w, cfg["tile"], cfg["halo"])
    groups = group_tiles(tiles, cfg["group_mb"] << 20)
    passes = len(groups) + (normalization != "none" or input_mean is not None)
    advance = (progress or (lambda d, t: (lambda k: None)))(label, n * passes)
    stream = _RegionImages(reader, n, box, mask, cfg["cache_mb"] << 20, advance)

    # pass 1 where asked: +N's factor per pixel (and channel), or one exposure factor for the capture
    scale, exposure = None, None
    if normalization != "none":
        scale = _observation_scale(stream, normalization, n, train_images)
    elif input_mean is not None:  # (+N removes any global scale: input_mean is None with it)
        exposure = _exposure_scale(stream, n, input_mean, cfg["exposure_pixels"])
        scale = np.full((1, 1, 1), exposure, np.float32)

    out = np.zeros((h, w, 3), np.float32)
    dtype = next(model.parameters()).dtype  # float32; float64 in tests that check exactness
    scale_t = None if scale is None else torch.from_numpy(scale).to(device=device, dtype=dtype)
    del scale
    light_t = None if lights is None or not model.uses_lights else torch.from_numpy(lights).to(device=device, dtype=dtype)
    cuda = device.type == "cuda"
    chunk_cfg = cfg["chunk"] or (32 if cuda else 2)
    work_bytes = (cfg["work_mb"] or (4096 if cuda else 256)) << 20
    chunk_used = chunk_cfg
    with torch.inference_mode(), _autocast(device, cfg["autocast"]):
        for group in groups:
            gy0, gy1, gx0, gx1 = _bbox(group)
            largest = max((t.outer[1] - t.outer[0]) * (t.outer[3] - t.outer[2]) for t in group)
            chunk = max(1, min(chunk_cfg, work_bytes // (largest * _BYTES_PER_PIXEL)))
            chunk_used = min(chunk_used, chunk)
            fused: list[torch.Tensor | None] = [None] * len(group)
            pending: list[np.ndarray] = []
            k0 = 0
            for k, img in enumerate(stream.part(gy0, gy1, gx0, gx1)):
                pending.append(img)
                if len(pending) < chunk and k < n - 1:
                    continue
                xt = torch.from_numpy(np.stack(pending))  # [c, gh, gw, 3] on the host
                lt = None if light_t is None else light_t[k0 : k + 1]
                for i, t in enumerate(group):
                    oy0, oy1, ox0, ox1 = t.outer
                    # each tile to the device first, then scaled and given its light channels there
                    # (on a GPU, less host work per chunk); tile by tile, the device holds one tile's
                    # chunk, not the group's (a laptop GPU)
                    sub = xt[:, oy0 - gy0 : oy1 - gy0, ox0 - gx0 : ox1 - gx0].to(device=device, dtype=dtype)
                    if scale_t is not None:  # out of place: on the CPU, sub may be a view of xt (halos overlap)
                        sub = sub * (scale_t if exposure is not None else scale_t[oy0:oy1, ox0:ox1])
                        if exposure is not None and input_clip is not None:
                            sub.clamp_(max=input_clip)
                    if lt is not None:  # light direction as 3 more channels, built in NHWC
                        sub = torch.cat([sub, lt[:, None, None, :].expand(*sub.shape[:3], 3)], -1)
                    inp = sub.permute(0, 3, 1, 2).contiguous(memory_format=fmt)
                    feat = model.extractor(inp)  # [c, 128, th/2, tw/2]
                    # element-wise per image: amax(0) over a channels_last batch is several times slower
                    first = 0
                    if fused[i] is None:
                        fused[i], first = feat[:1].clone(), 1
                    for j in range(first, feat.shape[0]):
                        if model.config["fuse"] == "max":
                            torch.maximum(fused[i], feat[j : j + 1], out=fused[i])
                        else:
                            fused[i] += feat[j : j + 1]
                    del feat, inp
                pending, k0 = [], k + 1
            for i, t in enumerate(group):
                f = fused[i] if model.config["fuse"] == "max" else fused[i] / n
                nrm = model.regress(f.contiguous(memory_format=fmt))[0].float().permute(1, 2, 0).cpu().numpy()
                fused[i] = None
                iy0, iy1, ix0, ix1 = t.inner
                oy0, ox0 = t.outer[0], t.outer[2]
                out[iy0:iy1, ix0:ix1] = nrm[iy0 - oy0 : iy1 - oy0, ix0 - ox0 : ix1 - ox0]

    if not np.isfinite(out).all():  # a bug, never a user error: fail loudly
        raise RuntimeError("internal error: non-finite normals")
    normals = np.zeros((H, W, 3), np.float32)
    region = stream.read_box
    inside = mask[region]
    normals[region] = np.where(keep[region][..., None], out[: stream.rh, : stream.rw], 0.0)
    dark = np.zeros((H, W), bool)
    dark[region][inside] = dark_pixels(stream.peak[: stream.rh, : stream.rw][inside])  # the rule L2 uses
    info = {
        "device": str(device), "region": [int(v) for v in box], "tiles": len(tiles), "passes": passes,
        "chunk": int(chunk_used), "cached_images": len(stream.cache), "normalization": normalization,
        "train_images": train_images, "seconds": round(time.perf_counter() - t_start, 3),
    }
    if stream.hot:
        info["hot_pixels"] = dict(sorted(stream.hot.items()))
    if cfg["grow"]:
        info["grow"] = int(cfg["grow"])
    if exposure is not None:
        info["exposure_scale"] = float(f"{exposure:.6g}")  # significant digits: a 1e30-scaled capture gets 1e-31, not 0
        info["exposure_pixels"] = cfg["exposure_pixels"]
    if not (stream.peak[: stream.rh, : stream.rw][inside] > 0).any():  # PS-FCN+N would answer anyway
        raise PsctlError(None, "all images are black inside the mask")
    return InferResult(normals, dark, info)


def _observation_scale(stream: "_RegionImages", normalization: str, n: int, train_images: int) -> np.ndarray:
    """+N's factor, from one pass over the ``n`` images [h, w, 3] of ``stream`` (h, w: its shape):
    sqrt(t / q) / ||observations|| per pixel [h, w, 1] ("per-pixel") or per pixel and channel
    [h, w, 3] ("per-channel"), 0 where every observation is 0 (t = ``n``, q = ``train_images``).
    Multiplying each image by it is ``psctl.models.ps_fcn.normalize_observations`` times
    sqrt(t / q), without holding the images."""
    h, w = stream.shape
    # float64: the sum (so the result) does not depend on the order of the images
    # (squared in float64 too: float32 squares of values below 1e-19 or above 1e19 leave its range)
    sumsq = np.zeros((h, w, 3 if normalization == "per-channel" else 1), np.float64)
    for img in stream:
        sq = np.square(img, dtype=np.float64)
        sumsq += sq if normalization == "per-channel" else sq.sum(-1, keepdims=True)
    scale = np.sqrt(sumsq, out=sumsq)  # in place: for a large region these maps are big
    lit = scale > 0
    # the authors' epsilon, relative to the capture's level so that its units do not matter (an
    # absolute 1e-10 swamped the norms of a capture scaled by 1e-10 or less, session 38)
    top = float(scale.max())
    scale += NORM_EPS * (top if top > 0 else 1.0)
    np.divide(math.sqrt(n / train_images), scale, out=scale)
    scale[~lit] = 0.0  # observations all 0 there: any factor gives 0
    if float(scale.max()) > float(np.finfo(np.float32).max):
        raise PsctlError(None, f"the images are too dark to normalise in float32 (largest per-pixel norm "
                               f"{top:.3g}): rescale them")
    return scale


def _exposure_scale(stream: "_RegionImages", n: int, input_mean: float, exposure_pixels: str) -> float:
    """The one factor that brings the ``n`` images' mean to ``input_mean`` (the exposure the
    network was trained at), from one pass over ``stream``: the mean over its mask (all images and
    channels), or with ``exposure_pixels`` "lit" over the lit pixels (``lit_mean``). One factor
    for the whole capture keeps albedo and shading ratios."""
    where = exposure_where(exposure_pixels)
    lit = exposure_pixels == "lit"
    if lit:  # no mask: the lit pixels' mean, not the dark background's too
        pixel_sum = np.zeros(stream.shape, np.float64)
        for img in stream:
            pixel_sum += img.sum(-1, dtype=np.float64)
        mean = lit_mean(pixel_sum[: stream.rh, : stream.rw], n)  # not the zero padding (the stream is masked)
        black = mean == 0  # no pixel above 0
    else:
        total = math.fsum(float(img.sum(dtype=np.float64)) for img in stream)
        mean, black = total / (float(stream.mask.sum()) * 3 * n), total == 0
    if not mean > 0:
        raise PsctlError(None, f"all images are black{'' if lit else ' inside the mask'}" if black else
                         f"the images' mean {where} is {mean:.3g}: linear images are not negative")
    return check_float32_scale(input_mean / mean, mean, where)


def run_views(model: "PSFCN", reader: Reader, n: int, lights: np.ndarray | None, mask: np.ndarray,
              normalization: str = "none", train_images: int | None = None, config: dict | None = None,
              progress: "ProgressFactory | None" = None, label: str = "network",
              input_mean: float | None = None, input_clip: float | None = None) -> InferResult:
    """``run_network`` over ``config["views"]`` symmetric views of the capture (psctl.symmetry):
    each view turns / mirrors the images, the mask and the lights together, its normals are
    turned back into the capture's frame, and the result is their unit mean. views = 1 is
    ``run_network`` itself. Same arguments and result as ``run_network``."""
    from psctl.symmetry import SYMMETRIES, box_in_capture, check_views, transform_dirs, transform_images, \
        untransform_dirs, untransform_images

    cfg = {**DEFAULT_INFER, **(config or {})}
    views = check_views(cfg["views"])
    k = check_downsample(cfg["downsample"])
    if k > 1:
        return run_downsampled(model, reader, n, lights, mask, k, normalization, train_images, cfg, progress, label,
                               input_mean, input_clip)
    args = (normalization, train_images, cfg)
    if views == 1:
        return run_network(model, reader, n, lights, mask, *args, progress, label, input_mean, input_clip)
    t0 = time.perf_counter()
    mask = np.asarray(mask, bool)
    H, W = mask.shape
    total = np.zeros((H, W, 3), np.float64)
    first = None  # SYMMETRIES[0] is the identity: its info and dark map are the capture's own
    for v, sym in enumerate(SYMMETRIES[:views]):
        view_shape = (W, H) if sym[0] else (H, W)

        def view_reader(start: int, box: tuple[slice, slice], sym=sym, view_shape=view_shape) -> Iterator[np.ndarray]:
            for img in reader(start, box_in_capture(box, sym, view_shape)):
                yield np.ascontiguousarray(transform_images(img, sym, axes=(0, 1)))

        mask_v = np.ascontiguousarray(transform_images(mask, sym, axes=(0, 1)))
        lights_v = None if lights is None else transform_dirs(np.asarray(lights, np.float32), sym)
        res = run_network(model, view_reader, n, lights_v, mask_v, *args, progress,
                          f"{label} (view {v + 1}/{views})", input_mean, input_clip)
        total += untransform_dirs(untransform_images(res.normals, sym, axes=(0, 1)), sym)
        if first is None:
            first = res
    norm = np.linalg.norm(total, axis=-1, keepdims=True)
    keep = grow_mask(mask, check_grow(cfg["grow"]))  # each view's normals cover the mask grown alike
    normals = np.where(keep[..., None] & (norm > 0), total / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
    info = {**first.info, "views": views, "seconds": round(time.perf_counter() - t0, 3)}
    return InferResult(normals, first.dark, info, first.notes)


def block_mean(img: np.ndarray, mask: np.ndarray, k: int) -> np.ndarray:
    """Shrink by ``k``: [h, w, C] (or [h, w]) -> [ceil(h / k), ceil(w / k), C], each k x k block's mean
    over its ``mask`` [h, w] pixels, 0 where it has none. Over the mask only, so that an edge
    block is the object's colour, not a blend with the background the network never sees."""
    h, w = mask.shape
    hk, wk = -(-h // k), -(-w // k)
    x = np.zeros((hk * k, wk * k) + img.shape[2:], np.float32)
    x[:h, :w] = np.where(mask.reshape(mask.shape + (1,) * (img.ndim - 2)), img, 0)
    c = np.zeros((hk * k, wk * k), np.float32)
    c[:h, :w] = mask
    sums = x.reshape(hk, k, wk, k, *img.shape[2:]).sum((1, 3))
    counts = c.reshape(hk, k, wk, k).sum((1, 3)).reshape((hk, wk) + (1,) * (img.ndim - 2))
    return np.divide(sums, np.maximum(counts, 1), dtype=np.float32)


def upsample_normals(normals: np.ndarray, mask: np.ndarray, k: int) -> np.ndarray:
    """[h, w, 3] normals of a capture shrunk by ``k`` (0 outside its mask) -> [H, W, 3] unit normals
    on the full-size ``mask`` [H, W], bilinear between block centres. The zeros outside the small
    mask drop out when each vector is normalised, so edge pixels take only the object's normals;
    every mask pixel's own block is in the small mask, so none is left without one. Only the
    object's box (and one block around it, zeros, as the frame beyond is) is interpolated."""
    import torch

    H, W = mask.shape
    h, w = normals.shape[:2]
    out = np.zeros((H, W, 3), np.float32)
    ys, xs = np.nonzero(np.abs(normals).sum(-1) > 0)
    if ys.size == 0:
        return out
    y0, y1 = max(int(ys.min()) - 1, 0), min(int(ys.max()) + 2, h)
    x0, x1 = max(int(xs.min()) - 1, 0), min(int(xs.max()) + 2, w)
    t = torch.from_numpy(np.ascontiguousarray(normals[y0:y1, x0:x1], np.float32)).permute(2, 0, 1)[None]
    up = torch.nn.functional.interpolate(t, size=((y1 - y0) * k, (x1 - x0) * k), mode="bilinear",
                                         align_corners=False)
    Y1, X1 = min(y1 * k, H), min(x1 * k, W)
    up = up[0].permute(1, 2, 0).numpy()[: Y1 - y0 * k, : X1 - x0 * k]
    norm = np.sqrt(np.einsum("...c,...c->...", up, up))[..., None]  # float32 throughout: a 12 MP map is 144 MB
    inside = mask[y0 * k:Y1, x0 * k:X1, None] & (norm > 0)
    np.divide(up, np.maximum(norm, 1e-30), out=out[y0 * k:Y1, x0 * k:X1], where=inside)
    return out


MIN_SIDE = 8  # px: the shrunk object's longest side, at least (the networks' stride is 4)


def run_downsampled(model: "PSFCN", reader: Reader, n: int, lights: np.ndarray | None, mask: np.ndarray, k: int,
                    normalization: str = "none", train_images: int | None = None, config: dict | None = None,
                    progress: "ProgressFactory | None" = None, label: str = "network",
                    input_mean: float | None = None, input_clip: float | None = None) -> InferResult:
    """``run_views`` on the capture shrunk by ``k`` (``block_mean`` of every image over the mask;
    the small mask: blocks with any mask pixel), normals brought back to full size by
    ``upsample_normals``. The lights are unchanged (shrinking does not turn the surface). Hot
    pixels are clamped and the dark map found at full size, as without shrinking (a block mean
    would dilute a hot pixel below the clamp's level, and a dark pixel into its block).
    Same arguments and result as ``run_views``; info["downsample"] = k."""
    t0 = time.perf_counter()
    mask = np.asarray(mask, bool)
    H, W = mask.shape
    if mask.any():
        ys, xs = np.nonzero(mask)
        side = int(max(ys.max() - ys.min(), xs.max() - xs.min())) + 1
        if -(-side // k) < MIN_SIDE:
            what = {"found": "the object found without a mask", "lit": "the frame, without a mask"}.get(
                {**DEFAULT_INFER, **(config or {})}["exposure_pixels"], "the mask")
            raise PsctlError(None, f"downsample {k} would leave the object {-(-side // k)} px across ({what} is "
                                   f"{side} px); use at most {max(side // MIN_SIDE, 1)}")
    small = block_mean(mask.astype(np.float32), np.ones_like(mask), k) > 0
    peak = np.zeros((H, W), np.float32)  # each pixel's brightest observation, as run_network keeps it
    hot: dict[int, int] = {}

    def small_reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        ys, xs = box
        # the block rows / columns of box, in full-size pixels (the last block may be cut by the frame)
        full = (slice(ys.start * k, min(ys.stop * k, H)), slice(xs.start * k, min(xs.stop * k, W)))
        sub = mask[full]
        for i, img in enumerate(reader(start, full), start):
            if not np.isfinite(img).all():  # outside the mask too, as run_network checks
                raise PsctlError(None, f"image {i + 1} contains NaN or infinite values")
            img, count = clamp_hot_pixels(img, sub)
            if count:
                hot.setdefault(i, count)  # every pass sees the same image
            grey = img if img.ndim == 2 else img[..., :3].max(-1)
            np.maximum(peak[full], np.where(sub, grey, 0), out=peak[full])
            yield block_mean(img, sub, k)

    grow = check_grow({**DEFAULT_INFER, **(config or {})}["grow"])
    res = run_views(model, small_reader, n, lights, small, normalization, train_images,
                    {**(config or {}), "downsample": 1, "grow": -(-grow // k)}, progress, f"{label} (1/{k} size)",
                    input_mean, input_clip)
    normals = upsample_normals(res.normals, grow_mask(mask, grow), k)
    dark = np.zeros((H, W), bool)
    dark[mask] = dark_pixels(peak[mask])  # the rule run_network and L2 use
    info = {**res.info, "downsample": k, "seconds": round(time.perf_counter() - t0, 3)}
    if grow:
        info["grow"] = grow  # (in full-size pixels)
    if hot:
        info["hot_pixels"] = dict(sorted(hot.items()))
    return InferResult(normals, dark, info, res.notes)


# --- entry points -----------------------------------------------------------------------------

def _prepare_network(method: str, weights: str | Path | None, config: dict | None):
    from psctl.models.weights import load_network

    unknown = sorted(set(config or {}) - set(DEFAULT_INFER))
    if unknown:  # a misspelt setting would otherwise be ignored without a word
        raise PsctlError(None, f"unknown inference setting {', '.join(map(repr, unknown))}; "
                               f"the settings are {', '.join(DEFAULT_INFER)}")
    cfg = {**DEFAULT_INFER, **(config or {})}
    device = pick_device(cfg["device"])
    model, run, w = load_network(method, weights, device="cpu")
    if cfg["autocast"] is not None:
        _autocast(device, cfg["autocast"])  # validate before any work
    note = f"{method}: weights {w.path}" + (" (the authors' checkpoint)" if w.official else "")
    return model, run, note


def _note_exposure(res: InferResult, method: str, input_mean: float | None) -> None:
    if "exposure_scale" in res.info:
        rule = res.info.get("exposure_pixels", "mask")  # the mask's: said by no note
        lit = "" if rule == "mask" else f" (their mean {_EXPOSURE_WHERE[rule]}{': no mask' if rule == 'lit' else ''})"
        res.notes.append(f"{method}: images scaled by {res.info['exposure_scale']:.4g}{lit} to the mean brightness "
                         f"the network was trained at ({input_mean:.3g})")


def array_normals(images: np.ndarray, lights: np.ndarray | None, mask: np.ndarray | None, method: str,
                  weights: str | Path | None = None, config: dict | None = None,
                  progress: "ProgressFactory | None" = None) -> InferResult:
    """A network method on in-memory images [N, H, W, 3] (or [N, H, W]), lights [N, 3].
    ``method`` "ensemble": the installed ENSEMBLE networks, averaged (``ensemble_normals``)."""
    from psctl.arrays import as_images, as_lights, as_mask, check_not_black
    from psctl.errors import _short

    known = (*NETWORK_METHODS, "ensemble")
    if not isinstance(method, str) or method.lower() not in known:
        raise PsctlError(None, f"array_normals runs {', '.join(known)}, not {_short(method)} "
                               "(psctl.estimate_normals runs l2, sdps and auto as well)")
    method = method.lower()
    if method == "ensemble":
        return ensemble_normals([array_normals(images, lights, mask, m, _no_weights(weights), config, progress)
                                 for m in ENSEMBLE])
    model, run, note = _prepare_network(method, weights, config)
    if model.uses_lights and lights is None:
        raise PsctlError(None, f"{method} needs light directions (lights=None)")
    if not model.uses_lights and lights is not None:  # they would be dropped without a word
        raise PsctlError(None, f"{method} estimates normals from the images alone: pass lights=None")
    images = as_images(images, len(lights) if hasattr(lights, "__len__") else None)  # as image files are
    n, H, W = images.shape[:3]
    mask = as_mask(mask, (H, W))
    lights = as_lights(lights, n)
    check_not_black(images, mask)
    if mask is None:  # the whole frame; the exposure from its lit part
        mask, config = np.ones((H, W), bool), {"exposure_pixels": "lit", **(config or {})}

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        for k in range(start, n):
            yield images[k][box]

    reader.band = reader  # (part of the region: the same slices)
    res = run_views(model, reader, n, lights, mask, run["normalization"], run["train_images"], config, progress, method,
                    run.get("input_mean"), run.get("input_clip"))
    res.notes.append(note)
    res.notes += hot_pixel_notes(res.info, [f"image {k + 1}" for k in range(n)])
    _note_exposure(res, method, run.get("input_mean"))
    return res


def capture_normals(capture: "Capture", mask: np.ndarray, method: str, weights: str | Path | None = None,
                    config: dict | None = None, progress: "ProgressFactory | None" = None,
                    memo: "DecodeMemo | None" = None, reuse: dict | None = None) -> InferResult:
    """A network method on a capture folder, streaming its images from disk. ``method``
    "ensemble": the installed ENSEMBLE networks, averaged; the images are read from disk once
    for all of them where ``cache_mb`` holds the cropped images (``ReadMemo``), else again.
    ``memo`` (``psctl.io.capture.DecodeMemo``): images decoded by an earlier pass over this
    capture, and this pass's kept there (sdps' passes). A capture without a mask file takes
    its exposure from its lit pixels (config ``exposure_pixels``) unless the config says
    otherwise (``psctl.api`` passes "found" with the object it found). ``reuse`` (a dict, kept
    by the caller across runs): each network's result, kept under what it was computed from
    (``reuse_key``), and taken out of it, with a note, by a later run of the same network on
    the same inputs (psctl eval's comparisons: the ensemble's members and the runs of them)."""
    if capture.mask_path is None:
        config = {"exposure_pixels": "lit", **(config or {})}
    # each network's key, made once (it stats every image and hashes the mask)
    keys = {} if reuse is None else {m: reuse_key(capture, mask, m, weights, config)
                                     for m in (ENSEMBLE if method == "ensemble" else (method,))}
    kept = bool(keys) and all(k in reuse for k in keys.values())
    # (every result kept: no helper process decoding images that nothing reads)
    with contextlib.nullcontext(None) if kept else _prefetch(capture, mask, config, memo) as decoded:
        if method == "ensemble":
            from psctl.io.capture import ImageCheck

            # one check and one read of the images for all members: the second network takes the
            # images the first read from memory (up to cache_mb), not from disk again
            _no_weights(weights)
            check = ImageCheck(capture)
            reads = ReadMemo(check.reader(capture, mask, decoded, memo),
                             {**DEFAULT_INFER, **(config or {})}["cache_mb"] << 20)
            res = ensemble_normals([_reused(reuse, keys.get(m), m, lambda m=m: _capture_member(
                capture, mask, m, None, config, progress, check, reads, decoded)) for m in ENSEMBLE])
        else:
            res = _reused(reuse, keys.get(method), method, lambda: _capture_member(
                capture, mask, method, weights, config, progress, decoded=decoded, memo=memo))
        res.info["prefetched"] = 0 if decoded is None else decoded.served
    return res


REUSE_MB = 1024  # psctl eval's comparisons keep at most this much of networks' results for later runs
REUSED_NOTE = "normals taken from an earlier run"  # how a report's note says so (compare_methods looks for it)


class KeptNormals(dict):
    """A ``reuse`` dict with a memory budget (``budget_mb``; None: REUSE_MB): a result that would
    take it over is not kept (computed again where asked for), and a result taken is let go."""

    def __init__(self, budget_mb: float | None = None):
        super().__init__()
        self.budget, self.used = int((REUSE_MB if budget_mb is None else budget_mb) * 2**20), 0


def _nbytes(res: InferResult) -> int:
    return res.normals.nbytes + res.dark.nbytes + (0 if res.spread is None else res.spread.nbytes)


def reuse_key(capture: "Capture", mask: np.ndarray, method: str, weights: str | Path | None,
              config: dict | None) -> tuple:
    """What a network's result on a capture is computed from: the images and the ambient image
    (paths, sizes, modification times: a capture taken again into the same names is another),
    how they are read (encoding, near lights), the pixels read, the lights and intensities given,
    the network's file (path, size, modification time) and the settings (DEFAULT_INFER with the
    run's config over it)."""
    import hashlib

    from psctl.models.weights import installed_path

    def stamp(p: "Path | None") -> tuple | None:
        if p is None:
            return None
        try:
            st = os.stat(p)
        except OSError:
            return (str(p), None)
        return (str(p), st.st_size, st.st_mtime_ns)

    h = hashlib.sha256()
    for a in (np.asarray(mask, bool), capture.lights if capture.lights is not None else np.zeros(0),
              capture.intensities):
        h.update(repr(np.asarray(a).shape).encode() + np.ascontiguousarray(a).tobytes())
    path = Path(weights) if weights is not None else installed_path(method)
    return (method, os.path.realpath(capture.path), tuple(map(stamp, capture.image_paths)), capture.encoding,
            stamp(capture.ambient_path), repr(capture.near), h.hexdigest(),
            None if path is None else (os.path.realpath(path), *stamp(path)[1:]),
            repr(sorted({**DEFAULT_INFER, **(config or {})}.items())))


def _reused(reuse: dict | None, key: tuple | None, method: str, compute: Callable[[], InferResult]) -> InferResult:
    """``compute()``, or (with ``reuse``) the result an earlier run kept there under ``key``
    (``reuse_key``), taken out of it (each is reused once: the ensemble its members', or a member
    the ensemble's), with a note that its time is not in this run's. A result computed is kept
    (a copy; in a ``KeptNormals`` only within its budget)."""
    import copy

    if reuse is None:
        return compute()
    if key in reuse:
        res = reuse.pop(key)
        if isinstance(reuse, KeptNormals):
            reuse.used -= _nbytes(res)
        res.notes.append(f"{method}: {REUSED_NOTE} on the same images and options (psctl eval's comparisons reuse "
                         f"them), not computed again: its time is not in this run's seconds")
        res.info["reused"] = True
        return res
    res = compute()
    if not isinstance(reuse, KeptNormals) or reuse.used + _nbytes(res) <= reuse.budget:
        reuse[key] = copy.deepcopy(res)
        if isinstance(reuse, KeptNormals):
            reuse.used += _nbytes(res)
    return res


def _prefetch(capture: "Capture", mask: np.ndarray, config: dict | None, memo: "DecodeMemo | None" = None):
    """The helper process that decodes ``capture``'s images for the first pass over them
    (``psctl.io.prefetch.prefetch``: only before torch is imported). Off (an object that serves
    nothing) with ``prefetch_mb`` 0, ``downsample`` > 1 (the network reads shrunk images), an
    empty mask, or where ``memo`` holds every image already (decoded by an earlier pass: the
    search for the object without a mask, sdps' LCNet)."""
    from psctl.io.prefetch import check_prefetch_mb, prefetch

    cfg = {**DEFAULT_INFER, **(config or {})}
    mb = check_prefetch_mb(cfg["prefetch_mb"])  # (a bad setting is an error whether a helper starts or not)
    box = first_read_box(capture, mask, cfg)
    held = memo is not None and box is not None and all(memo.holds(p, box) for p in capture.image_paths)
    return prefetch(capture.image_paths, box, (capture.width, capture.height), 0 if held else mb)


def first_read_box(capture: "Capture", mask: np.ndarray, config: dict | None = None) -> tuple[slice, slice] | None:
    """What ``capture_normals`` reads of each image at full resolution (the helper's box, and
    the box a ``DecodeMemo`` must hold to serve it); None where it reads shrunk images
    (``downsample`` > 1) or the mask is empty or not the capture's size."""
    cfg = {**DEFAULT_INFER, **(config or {})}
    mask = np.asarray(mask, bool)
    on = check_downsample(cfg["downsample"]) == 1 and mask.any() and mask.shape == (capture.height, capture.width)
    return read_box(region_box(grow_mask(mask, check_grow(cfg["grow"])), cfg), mask.shape) if on else None


def _capture_member(capture: "Capture", mask: np.ndarray, method: str, weights: str | Path | None,
                    config: dict | None, progress: "ProgressFactory | None", check=None,
                    reads: "ReadMemo | None" = None, decoded=None, memo=None) -> InferResult:
    from psctl.io.capture import ImageCheck

    model, run, note = _prepare_network(method, weights, config)
    if model.uses_lights and not capture.calibrated:
        from psctl.io.capture import missing_lights_hint

        raise PsctlError(capture.path / "light_directions.txt", f"missing: {method} needs calibrated light directions"
                                                                + missing_lights_hint(capture.path))
    unused = []
    if not model.uses_lights:
        # a network without light input (UPS-FCN) is trained on images as captured, under unknown
        # intensities: like sdps, it reads them undivided and the folder's light files are not used
        unused = [n for n, used in (("light_directions.txt", capture.calibrated),
                                    ("light_intensities.txt", capture.intensities_given)) if used]
        capture = replace(capture, intensities=np.ones_like(capture.intensities), intensities_given=False)

    if check is None:
        check = ImageCheck(capture)  # black images, negative values: notes
    # UPS-FCN reads the images undivided (capture replaced above): never through the shared reads
    reader = reads if reads is not None and model.uses_lights else check.reader(capture, mask, decoded, memo)
    with naming(capture.path):  # all images black, ...
        res = run_views(model, reader, capture.n_images, capture.lights, mask, run["normalization"],
                        run["train_images"], config, progress, f"{capture.name}: reading + {method}",
                        run.get("input_mean"), run.get("input_clip"))
    res.notes.append(note)
    res.notes += check.notes() + hot_pixel_notes(res.info, [p.name for p in capture.image_paths])
    if unused:
        res.notes.append(f"{method}: {' and '.join(unused)} not used (it estimates normals from the images alone)")
    _note_exposure(res, method, run.get("input_mean"))
    return res


class ReadMemo:
    """A ``Reader`` that keeps what it reads: per box, the images from the first on, until they take
    ``budget`` bytes; a later call for the same box yields those from memory and reads the rest.
    The readers never change the arrays they are given (run_network copies before it scales)."""

    def __init__(self, reader: Reader, budget: int):
        self.reader = reader
        self.budget = budget
        self.used = 0
        self.kept: dict[tuple, list[np.ndarray]] = {}

    def __call__(self, start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        kept = self.kept.setdefault(tuple((s.start, s.stop, s.step) for s in box), [])
        k = start
        while k < len(kept):
            yield kept[k]
            k += 1
        for img in self.reader(k, box):
            if k == len(kept) and self.used + img.nbytes <= self.budget:
                kept.append(img)
                self.used += img.nbytes
            yield img
            k += 1

    @property
    def band(self) -> "Reader | None":
        """``reader.band`` through the memo (run_network's later passes: part of a box read whole
        before), or None where the reader has none."""
        band = getattr(self.reader, "band", None)
        if band is None:
            return None

        def read(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
            from psctl.io.capture import box_within

            kept: list[np.ndarray] = []
            for key, imgs in self.kept.items():
                if len(imgs) > start and box_within(box, key):
                    (r0, _, _), (c0, _, _) = key
                    kept = [x[box[0].start - r0:box[0].stop - r0, box[1].start - c0:box[1].stop - c0] for x in imgs]
                    break
            k = start
            while k < len(kept):
                yield kept[k]
                k += 1
            yield from band(k, box)

        return read


# The "ensemble" method: the calibrated networks whose normals it averages. On psctl's synthetic
# test sets the average of the release files beat either alone (benchmarks/ensemble.py, docs/usage.md).
# Without a mask the networks take the whole frame for the object (QA helpers' findings: nothing
# was said). Measured in session 62 (PS-FCN's exposure from the lit pixels; from the whole frame
# in session 60 it was 6.68, the ensemble 6.17): `psctl eval` on the dev split's five folders
# with mask.png left out (the same pixels scored)
NO_MASK_NETWORKS_WHY = ("the networks read the whole frame as the object, the background beside it included; a "
                        "mask of the object makes the normals more accurate (the DiLiGenT dev split read whole: "
                        "the ensemble 6.04 degrees against 5.66 with its masks, PS-FCN+N 6.00 against 5.59, "
                        "PS-FCN 6.35 against 6.01)")
ENSEMBLE = ("ps-fcn", "ps-fcn-n")
# Without a mask the networks read the object psctl.masks.find_object finds, not the whole frame: the
# background beside the object, put through +N's per-pixel normalisation or PS-FCN's exposure, spoils
# the normals along its outline. The object found misses part of its dark rim (its pixels are lit in
# few images), so the normals are also given FOUND_GROW pixels beyond it, where the network answers
# from the object beside them (the setting "grow"). Chosen on synthetic objects before dark, lit and
# textured backgrounds (benchmarks/auto_mask_normals.py, docs/models.md "Without a mask")
FOUND_GROW = 4


def _no_weights(weights: str | Path | None) -> None:
    if weights is not None:  # psctl.api.resolve_method refuses this with a message for the user
        raise ValueError("the ensemble uses the installed weights; one file cannot be passed to it")


def ensemble_normals(results: list[InferResult]) -> InferResult:
    """The unit mean of several networks' answers for one capture (the ``ensemble`` method).

    Each result's normals are [H, W, 3] unit vectors (0 outside the mask); the mean of unit
    vectors weighs each network's direction equally. ``spread`` [H, W] is ``member_spread``:
    where the members disagree (degrees). ``dark`` is any member's; notes are kept once each,
    in order; ``info`` holds each member's under "members".
    """
    if not results:
        raise ValueError("ensemble_normals needs at least one result")
    total = np.sum([r.normals.astype(np.float64) for r in results], axis=0)
    norm = np.linalg.norm(total, axis=-1, keepdims=True)
    # two unit vectors cancel only if opposite; outside the mask every member gives 0
    normals = np.where(norm > 1e-12, total / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
    dark = np.logical_or.reduce([r.dark for r in results])
    notes = list(dict.fromkeys(n for r in results for n in r.notes))
    return InferResult(normals, dark, {"members": [r.info for r in results]}, notes,
                       member_spread([r.normals for r in results]))


def member_spread(normals: list[np.ndarray]) -> np.ndarray:
    """The largest angle between any two of several [H, W, 3] normal maps, per pixel: [H, W]
    float32 degrees (two maps: the angle between them). 0 where a map is 0 (outside the mask).

    Where two networks trained apart disagree, their mean is less likely to be right: on psctl's
    synthetic test sets the ensemble's error grows with it (benchmarks/spread.py, docs/usage.md).
    """
    maps = [np.asarray(n, np.float64) for n in normals]
    out = np.zeros(maps[0].shape[:2], np.float64)
    for i in range(len(maps)):
        for j in range(i + 1, len(maps)):
            a, b = maps[i], maps[j]
            # atan2(|a x b|, a . b): accurate at small angles, where arccos of the dot is not
            ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))
            both = (np.abs(a).sum(-1) > 0) & (np.abs(b).sum(-1) > 0)
            np.maximum(out, np.where(both, ang, 0.0), out=out)
    return out.astype(np.float32)


def all_at_once_normals(model: "PSFCN", images: np.ndarray, lights: np.ndarray | None, mask: np.ndarray | None = None,
                        normalization: str = "none", train_images: int | None = None) -> np.ndarray:
    """The straightforward implementation (as the authors' test code): the whole frame padded
    to a multiple of 4, every image through the extractor, every feature map kept, max at the
    end. Memory grows with N. The oracle for tests and the baseline for benchmarks.

    images [N, H, W, 3], lights [N, 3] -> normals [H, W, 3] (zero outside the mask).
    """
    import torch

    from psctl.models.ps_fcn import normalize_observations

    images = np.asarray(images, np.float32)
    n, H, W = images.shape[:3]
    mask = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
    Hp, Wp = _ceil(H, STRIDE), _ceil(W, STRIDE)
    dtype = next(model.parameters()).dtype
    x = torch.zeros(n, 3, Hp, Wp, dtype=dtype)
    x[:, :, :H, :W] = torch.from_numpy(images * mask[None, ..., None]).permute(0, 3, 1, 2)
    x = normalize_observations(x, normalization, train_images)
    lt = None if lights is None or not model.uses_lights else torch.from_numpy(np.asarray(lights, np.float32)).to(dtype)
    model = model.to("cpu").eval()
    with torch.inference_mode():
        feats = [model.extract(x[k : k + 1], None if lt is None else lt[k : k + 1]) for k in range(n)]
        stacked = torch.cat(feats, 0)
        fused = stacked.amax(0, keepdim=True) if model.config["fuse"] == "max" else stacked.mean(0, keepdim=True)
        normals = model.regress(fused)[0].float().permute(1, 2, 0).numpy()[:H, :W]
    return np.where(mask[..., None], normals, 0.0).astype(np.float32)

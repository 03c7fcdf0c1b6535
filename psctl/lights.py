"""Light estimation for uncalibrated photometric stereo: LCNet over all images of a capture.

    psctl lights ballPNG     ->  ballPNG/psctl/light_directions.txt, light_intensities.txt, lights.png,
                                 lights_report.json

    >>> from psctl.lights import run_lights
    >>> report = run_lights("ballPNG")            # report["light_mae"] with ground-truth lights

The pipeline (psctl.models.lcnet has the network and the discretisation):

1. Crop and resize. The images are cropped to the mask's bounding box grown by ``margin``
   (15 px, as the authors' ``pmsData_crop``), multiplied by the mask and resized to LCNet's
   input side (128 x 128, bilinear, antialiased); the resized mask is the 4th channel. The
   images are used as captured: light_intensities.txt, if present, is ground truth to compare
   with, never applied (estimating the intensities is LCNet's job).
2. Global feature, pass 1. Images are read one at a time and go through the extractor in chunks;
   the global feature is a running element-wise max of the per-image features [256, 8, 8], so
   memory does not grow with the number of images. Per-image features (64 KB each) are kept up
   to ``cache_mb``.
3. Classification, pass 2. Each image's feature, concatenated with the global one, is
   classified (azimuth, elevation, intensity). Images whose features were not kept are read and
   extracted again (only captures of more than ~1000 images at the default cache).
4. Decoding: the soft-argmax (the default) or the argmax class centre (the paper, ``decode="argmax"``).
5. Symmetric views (``views``, 8 by default; 1 is the paper's single pass): steps 2-4 run on the
   images as captured and turned / mirrored about the view axis (the 8 symmetries of the square,
   ``psctl.symmetry``); each view's directions are turned back and the unit mean
   of the views is the estimate, the intensities their mean. Exact for an orthographic camera
   and isotropic materials; it costs ``views`` times the network work.
6. Refinement (``run_lights(refine=True)``, sdps; ``psctl.refine``): a normals network turns the lights into
   normals and ``psctl.refine.refine_lights`` refits each light by a robust fit of a diffuse model (a cosine
   that may fall to zero before the terminator) against them, gated by how well that fit
   explains the pixels. Then (``roll``, on by default) the lights are turned about the view axis
   by the roll that makes the normals from them most integrable (``psctl.refine.integrability_roll``).

The mask LCNet and the fit read is the mask file snapped to the object, or without one the
object found by brightness or shading (``psctl.masks``).

Outputs are in DiLiGenT's format: light_directions.txt (N x 3, unit, x right / y up / z toward
the camera) and light_intensities.txt (N x 3, the same value in R, G and B; only relative
intensities are meaningful). With ground truth in the folder, the report gives the mean angular
error of the directions (``light_mae``, degrees) and the scale-invariant relative intensity
error (``intensity_re``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.arrays import bounding_box
from psctl.errors import ProgressFactory, PsctlError, check_bool, check_path, check_progress, moved_names, naming
from psctl.hotpixels import clamp_hot_pixels, hot_pixel_notes
from psctl.masks import FOUND_FILE, NO_MASK_PREFIX, capture_object
from psctl.refine import lights_changed, refine_config

if TYPE_CHECKING:
    import torch

    from psctl.infer import Reader  # reader(start, box) yields images start.. as float32 [h, w, 3] cropped to box
    from psctl.io.capture import Capture, DecodeMemo
    from psctl.models.lcnet import LCNet
    from psctl.models.weights import Weights

DEFAULT_LIGHTS = {
    "device": "auto",  # auto | cpu | cuda
    "chunk": None,  # images per network batch: None = 8 on CPU, 64 on CUDA
    "margin": 15,  # pixels kept around the mask's bounding box (the authors' DiLiGenT crop)
    "cache_mb": 64,  # per-image features kept from pass 1 for pass 2 (64 KB each at 128 px)
    # a helper process decodes the images (cut to the crop) into a ring of shared memory of at
    # most this many MB while this one imports torch and loads LCNet (psctl.io.prefetch); 0 = off
    "prefetch_mb": 256,
    # soft-argmax: better than the paper's argmax (class centres) on held-out synthetic sets with
    # both release LCNets (7.53 vs 7.67 and 7.60 vs 7.99 degrees; docs/uncalibrated.md)
    "decode": "soft",  # soft | argmax
    # symmetric views averaged (1, 2, 4 or 8 of psctl.symmetry.SYMMETRIES): the images turned
    # and mirrored about the view axis, LCNet's estimates turned back and averaged. 8 was better
    # than 1 on held-out synthetic sets with the release LCNet (docs/uncalibrated.md)
    "views": 8,
    # pad the crop to a square before resizing (False: stretch it to a square, as the authors'
    # code does). Stretching won on the synthetic folder sets (6.41 vs 6.43 degrees over
    # syntest, syntest_dl, syntest_dl_dir; docs/uncalibrated.md)
    "square": False,
    # LCNet answers badly on captures much darker or brighter than its training exposures (mean
    # object radiance 0.02-0.5 times intensities in [0.2, 2]; syntest_dl scaled x0.03 or x3-x30:
    # mean light error 9.5-15 degrees against 4.6 as rendered, session 23). A capture whose mean
    # inside the mask (over all images, as read) is outside this band is scaled to the target for
    # LCNet; every capture measured so far lies inside (DiLiGenT dev split 0.018-0.075, the
    # synthetic test sets 0.014-0.43), so none of their numbers change; scaled syntest_dl with
    # it: 5.89 / 4.90 / 4.78 / 4.78 at x0.03 / 3 / 10 / 30 (docs/uncalibrated.md). None: off.
    "exposure_band": (0.01, 0.5),
    "exposure_target": 0.1,
    # where the guard's mean is taken: "mask" or "lit" (psctl.infer.lit_pixels, the bright part of
    # the frame; what runs without a mask use, so that a dark background does not halve it)
    "exposure_pixels": "mask",
}

OUTPUT_FILES = {"light_directions": "light_directions.txt", "light_intensities": "light_intensities.txt",
                "lights": "lights.png"}
SUBSET_FILE = "light_images.txt"  # with --images: the image each light file row belongs to
# the run's report (what --json prints: errors, notes, provenance), beside the light files it
# describes; named as psctl depth's depth_report.json, so never psctl normals' report.json
REPORT_FILE = "lights_report.json"
# psctl normals --method sdps: the lights its normals were estimated from, under names of their own
# so that they never replace psctl lights' files in the same folder (both default to PATH/psctl)
SDPS_FILES = {k: v.replace(".", "_estimated.", 1) for k, v in {**OUTPUT_FILES, "light_images": SUBSET_FILE}.items()}


@dataclass
class LightEstimate:
    directions: np.ndarray  # [N, 3] float32 unit vectors (x right, y up, z toward the camera)
    intensities: np.ndarray  # [N] float32, relative (LCNet's scale, in [0.2, 2.0] unless refined)
    logits: dict[str, np.ndarray]  # {"dir_x": [N, K_d], "dir_y": [N, K_d], "ints": [N, K_e]}, the first view's
    info: dict = field(default_factory=dict)  # device, box, size, chunk, passes, seconds, ...
    notes: list[str] = field(default_factory=list)


def lit_capture(capture: "Capture", est: LightEstimate) -> "Capture":
    """``capture`` with ``est``'s lights in place of its light files (the same intensity in R, G
    and B): what sdps' second stage reads (intensities_given False: the folder's file is not them)."""
    return replace(capture, lights=est.directions, intensities=np.repeat(est.intensities[:, None], 3, 1),
                   intensities_given=False)


# --- the network ------------------------------------------------------------------------------

def load_lcnet(weights: str | os.PathLike | None = None, flag: str = "--weights") -> tuple["LCNet", "Weights"]:
    """LCNet with installed weights (weights/lcnet.pt) or ``weights`` (psctl's file or the
    authors' LCNet_CVPR2019.pth.tar); returns (model, weights). ``flag`` names the option that
    passes a file, for the error message when nothing is installed."""
    from psctl.models.weights import installed_path, load_network, no_weights_error

    check_path(flag.lstrip("-"), weights, optional=True)
    if weights is None and installed_path("lcnet") is None:
        raise no_weights_error("lcnet", flag)
    model, _, w = load_network("lcnet", weights, device="cpu")
    return model, w


def pad_square(x: "torch.Tensor") -> "torch.Tensor":
    """Zero-pad [..., H, W] to [..., S, S], S = max(H, W), centred: resizing then keeps the
    object's aspect ratio (a stretched sphere no longer looks like a sphere to LCNet)."""
    import torch.nn.functional as F

    h, w = x.shape[-2:]
    s = max(h, w)
    return F.pad(x, ((s - w) // 2, s - w - (s - w) // 2, (s - h) // 2, s - h - (s - h) // 2))


def run_lcnet(model: "LCNet", reader: "Reader", n: int, mask: np.ndarray, config: dict | None = None,
              progress: "ProgressFactory | None" = None, label: str = "LCNet") -> LightEstimate:
    """Lights of ``n`` images from a stream, memory bounded in ``n``.

    Args:
        model: an LCNet (eval mode is set here).
        reader: see ``psctl.infer.Reader``; called once, twice when the features do not fit in
            cache_mb, and once more when the exposure guard's inputs do not (info["passes"]).
        n: number of images.
        mask: [H, W] bool object mask (the full image size).
        config: overrides of DEFAULT_LIGHTS.
    Returns:
        LightEstimate with directions [n, 3] and intensities [n].
    """
    import torch

    from psctl.infer import check_float32_scale, exposure_where, lit_mean, pick_device
    from psctl.models.lcnet import FEATURES, decode, resize_inputs
    from psctl.symmetry import SYMMETRIES, check_views, transform_images, untransform_dirs

    cfg = {**DEFAULT_LIGHTS, **(config or {})}
    t0 = time.perf_counter()
    if n < 1:
        raise PsctlError(None, "no images")
    check_decode(cfg["decode"], "decoding")
    where = exposure_where(cfg["exposure_pixels"])
    views = check_views(cfg["views"])
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise PsctlError(None, "mask is empty (no foreground pixel)")
    device = pick_device(cfg["device"])
    model = model.to(device).eval()
    dtype = next(model.parameters()).dtype
    size = int(model.config["size"])
    box = bounding_box(mask, int(cfg["margin"]))
    h, w = box[0].stop - box[0].start, box[1].stop - box[1].start
    crop_mask = mask[box].astype(np.float32)
    chunk = int(cfg["chunk"] or (64 if device.type == "cuda" else 8))
    feat_bytes = FEATURES * (-(-size // 16)) ** 2 * torch.finfo(dtype).bits // 8
    n_cache = max(0, int(cfg["cache_mb"] * 2**20) // (feat_bytes * views))
    # the exposure guard reads every image before pass 1; it keeps the network inputs (4 channels
    # at `size`) for pass 1 when they fit in cache_mb, else pass 1 reads them again
    keep_inputs = n * 4 * size * size * torch.finfo(dtype).bits // 8 <= cfg["cache_mb"] * 2**20
    guard = cfg["exposure_band"] is not None
    passes = int(guard) + int(not (guard and keep_inputs)) + int(n > n_cache)  # reads of the capture
    reads = n * int(guard) + n * int(not (guard and keep_inputs)) + max(0, n - n_cache)
    advance = (progress or (lambda d, t: (lambda k: None)))(label, reads)
    mask_t = torch.from_numpy(crop_mask)[None, None].to(device, dtype)

    peak = [0.0]  # the brightest pixel inside the mask read so far
    hot: dict[int, int] = {}  # image index -> values clamp_hot_pixels set
    level = [0.0, 0.0]  # sum and count of the values inside the mask (the exposure guard's mean)
    # no mask: each pixel's sum, so that the guard's mean is the lit pixels' (infer.lit_pixels),
    # not halved by a dark background (DiLiGenT's ball: 0.018 with its mask, 0.009 without)
    lit_rule = cfg["exposure_pixels"] == "lit" and cfg["exposure_band"] is not None
    pixel_sum = np.zeros((h, w), np.float64) if lit_rule else None

    def chunks(start: int) -> Iterator[torch.Tensor]:
        """Network inputs [c, 4, size, size] of images start.. in chunks."""
        pending: list[np.ndarray] = []
        k = start
        for img in reader(start, box):
            if img.ndim == 2:
                img = img[..., None]
            if img.shape[:2] != (h, w):
                raise PsctlError(None, f"image {k + 1}: size changed while reading")
            img = np.ascontiguousarray(img[..., :3], np.float32)
            if img.shape[-1] == 1:
                img = np.repeat(img, 3, -1)
            if not np.isfinite(img).all():
                raise PsctlError(None, f"image {k + 1} contains NaN or infinite values")
            img, count = clamp_hot_pixels(img * crop_mask[..., None], crop_mask)  # one pixel would move every light
            if count:
                hot[k] = count
            pending.append(img)
            peak[0] = max(peak[0], float(pending[-1].max()))
            level[0] += float(pending[-1].sum(dtype=np.float64))  # inside the mask (zero outside)
            level[1] += 3.0 * float(crop_mask.sum())
            if pixel_sum is not None:
                np.add(pixel_sum, pending[-1].sum(-1, dtype=np.float64), out=pixel_sum)
            advance(1)
            k += 1
            if len(pending) == chunk or k == n:
                x = torch.from_numpy(np.stack(pending)).permute(0, 3, 1, 2).to(device, dtype)
                m = mask_t.expand(len(pending), 1, h, w)
                if cfg["square"]:
                    x, m = pad_square(x), pad_square(m)
                x, m = resize_inputs(x, m, size)
                yield model.network_input(x, m)
                pending = []
        if k != n or pending:
            raise PsctlError(None, f"expected {n} images, got {k}")

    # exposure: the mean inside the mask over all images, as read (full resolution), before any
    # feature; the network inputs are kept for pass 1 when they fit in cache_mb, else read again
    factor, buffered, mean = 1.0, None, None
    band = cfg["exposure_band"]
    if band is not None:
        buffered = []
        with torch.inference_mode():
            for x in chunks(0):
                if keep_inputs:
                    buffered.append(x)
        buffered = buffered if keep_inputs else None
        mean = level[0] / max(level[1], 1.0)
        if pixel_sum is not None and mean > 0:
            mean = lit_mean(pixel_sum, n)
        pixel_sum = None  # the closure's too: later passes neither add to it nor keep it
        if mean > 0 and not band[0] <= mean <= band[1]:
            factor = check_float32_scale(float(cfg["exposure_target"]) / mean, mean, where)

    def scaled(xs: Iterator[torch.Tensor]) -> Iterator[torch.Tensor]:
        for x in xs:
            if factor != 1.0:
                x = torch.cat([x[:, :3] * factor, x[:, 3:]], 1)
            yield x

    fuse_max = model.config["fuse"] == "max"
    syms = SYMMETRIES[:views]
    with torch.inference_mode():
        fused: list[torch.Tensor | None] = [None] * views
        cache: list[list[torch.Tensor]] = [[] for _ in syms]
        kept = 0
        # pass 1: the global features (and the first features), one per view
        for x in scaled(buffered if buffered is not None else chunks(0)):
            take = min(len(x), n_cache - kept)
            for v, sym in enumerate(syms):
                f = model.extract(transform_images(x, sym))
                fm = f.amax(0, keepdim=True) if fuse_max else f.sum(0, keepdim=True)
                fused[v] = fm if fused[v] is None else (torch.maximum(fused[v], fm) if fuse_max else fused[v] + fm)
                if take > 0:
                    cache[v].append(f[:take].clone())
            kept += max(take, 0)
        if not peak[0] > 0:  # LCNet would still answer, with lights that mean nothing
            raise PsctlError(None, "all images are black inside the mask")
        if not fuse_max:
            fused = [f / n for f in fused]
        logits: list[dict[str, list[torch.Tensor]]] = [{"dir_x": [], "dir_y": [], "ints": []} for _ in syms]

        def classify(v: int, f: torch.Tensor) -> None:
            for i in range(0, len(f), chunk):
                out = model.classify(f[i:i + chunk], fused[v])
                for key in logits[v]:
                    logits[v][key].append(out[key].float().cpu())

        for v in range(views):  # pass 2: classify each image against its view's global feature
            for f in cache[v]:
                classify(v, f)
        cache.clear()
        buffered = None  # pass 1 is done with them
        if kept < n:
            for x in scaled(chunks(kept)):
                for v, sym in enumerate(syms):
                    classify(v, model.extract(transform_images(x, sym)))
    outs = [{k: torch.cat(val) for k, val in lv.items()} for lv in logits]
    decoded = [decode(o, model.config, cfg["decode"]) for o in outs]
    dirs = torch.nn.functional.normalize(torch.stack([untransform_dirs(d, sym) for (d, _), sym in zip(decoded, syms)]).mean(0),
                                         dim=-1)
    ints = torch.stack([i for _, i in decoded]).mean(0)
    out = outs[0]
    info = {"device": str(device), "box": [box[0].start, box[0].stop, box[1].start, box[1].stop],
            "size": size, "chunk": chunk, "passes": passes, "cached_features": kept, "decode": cfg["decode"], "views": views,
            "exposure": round(factor, 6), "seconds": round(time.perf_counter() - t0, 3)}
    if hot:
        info["hot_pixels"] = dict(sorted(hot.items()))
    notes = []
    if factor != 1.0:
        notes.append(f"lcnet: the images' mean {where}, {mean:.3g}, is {EXPOSURE_WORDS} "
                     f"({band[0]:g} to {band[1]:g}); it sees them scaled by {factor:.3g}")
    notes += [note for note in [few_lights_note(n)] if note]
    return LightEstimate(dirs.numpy().astype(np.float32), ints.numpy().astype(np.float32),
                         {k: v.numpy() for k, v in out.items()}, info, notes)


# LCNet compares a capture's images with one another (its global feature is a max over them) and
# learnt on 32 at a time: from few it is rougher. The DiLiGenT dev split, 6 random subsets of each
# object's images (estimate_lights' defaults, session 69): 14.97 degrees off on average from 1
# image, 9.69 from 2, 6.30 from 4, 4.87 from 8, 2.91 from all 96.
FEW_LIGHT_IMAGES = 8


def few_lights_note(n: int) -> str | None:
    """The note for LCNet given fewer than FEW_LIGHT_IMAGES images, else None."""
    if n >= FEW_LIGHT_IMAGES:
        return None
    return (f"lights: only {n} image{'s' * (n != 1)}: LCNet estimates each light by comparing the images with one "
            f"another, and from few it is rougher (the DiLiGenT dev split's objects, random subsets: 15.0 degrees "
            f"off on average from 1 image, 9.7 from 2, 6.3 from 4, 4.9 from 8, 2.9 from all 96)")


def check_decode(decode: str, name: str = "decode") -> str:
    """LCNet's decoding, "soft" or "argmax", or a one-line error naming the option ``name``."""
    decode = decode.lower() if isinstance(decode, str) else decode  # as --method, --encoding: ARGMAX too
    if decode not in ("argmax", "soft"):
        raise PsctlError(None, f"unknown {name} {decode!r}; choose argmax or soft")
    return decode

# the exposure guard's note, also found by these words (psctl.api warns with it)
EXPOSURE_WORDS = "outside the exposures LCNet was trained on"


def array_lights(images: np.ndarray, mask: np.ndarray | None = None, weights: str | os.PathLike | None = None,
                 config: dict | None = None, model: "LCNet | None" = None,
                 progress: "ProgressFactory | None" = None) -> LightEstimate:
    """Lights from in-memory images [N, H, W, 3] (or [N, H, W]), as captured (not divided by any
    intensity). ``model`` (an LCNet) replaces loading ``weights`` / the installed weights."""
    from psctl.arrays import as_images, as_mask, check_not_black

    images = as_images(images)  # integer arrays scaled as image files are; grey / RGBA to RGB
    n, H, W = images.shape[:3]
    mask = as_mask(mask, (H, W))
    check_not_black(images, mask)
    if mask is None:  # the whole frame; the exposure guard reads its lit part
        mask, config = np.ones((H, W), bool), {"exposure_pixels": "lit", **(config or {})}
    note = None
    if model is None:
        model, w = load_lcnet(weights)
        note = f"lcnet: weights {w.path}" + (" (the authors' checkpoint)" if w.official else "")
        if w.official:  # the guard's band describes psctl's training exposures, not the authors'
            config = {"exposure_band": None, **(config or {})}

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        for k in range(start, n):
            yield images[k][box]

    res = run_lcnet(model, reader, n, mask, config, progress)
    if note:
        res.notes.append(note)
    res.notes += hot_pixel_notes(res.info, [f"image {k + 1}" for k in range(n)])
    return res


def capture_lights(capture: "Capture", mask: np.ndarray, weights: str | os.PathLike | None = None,
                   config: dict | None = None, progress: "ProgressFactory | None" = None,
                   flag: str = "--weights", memo: "DecodeMemo | None" = None,
                   keep_box: tuple[slice, slice] | None = None) -> LightEstimate:
    """Lights of a capture folder, streaming its images from disk as captured (the folder's
    light_intensities.txt, if any, is not applied). ``memo`` (``DecodeMemo``): the decoded
    images are kept there for a later pass (sdps' second stage); ``keep_box``: what that pass
    reads of each image (``psctl.infer.first_read_box``), decoded here with LCNet's crop so that
    the memo serves it."""
    from psctl.io.capture import ImageCheck
    from psctl.io.prefetch import prefetch

    if capture.mask_path is None:  # the exposure guard reads the lit pixels
        config = {"exposure_pixels": "lit", **(config or {})}
    cfg = {**DEFAULT_LIGHTS, **(config or {})}
    mask = np.asarray(mask, bool)
    on = mask.any() and mask.shape == (capture.height, capture.width)
    box = bounding_box(mask, int(cfg["margin"])) if on else None
    # decoded once for both passes: the smallest box holding LCNet's crop and the later pass's
    read = box if box is None or keep_box is None or memo is None else (
        slice(min(box[0].start, keep_box[0].start), max(box[0].stop, keep_box[0].stop)),
        slice(min(box[1].start, keep_box[1].start), max(box[1].stop, keep_box[1].stop)))
    # started before LCNet's weights import torch: the decoding overlaps that import
    with prefetch(capture.image_paths, read, (capture.width, capture.height), cfg["prefetch_mb"]) as pf:
        model, w = load_lcnet(weights, flag)
        if w.official:  # the guard's band describes psctl's training exposures, not the authors'
            config = {"exposure_band": None, **(config or {})}
        raw = replace(capture, intensities=np.ones_like(capture.intensities))
        check = ImageCheck(replace(raw, intensities_given=False))  # black images, ...: notes (on images as captured)
        reader = check.reader(raw, mask, pf, memo)
        if read != box:
            reader = _cut_reader(reader, check.reader(raw, mask, pf, memo, _inner(box, read)), box, read)
        with naming(capture.path):  # all images black, ...
            res = run_lcnet(model, reader, raw.n_images, mask, config, progress, f"{capture.name}: reading + LCNet")
        res.info["prefetched"] = pf.served
    res.notes.append(f"lcnet: weights {w.path}" + (" (the authors' checkpoint)" if w.official else ""))
    res.notes += check.notes() + hot_pixel_notes(res.info, [p.name for p in capture.image_paths])
    return res


def _inner(box: tuple[slice, slice], outer: tuple[slice, slice]) -> tuple[slice, slice]:
    """``box`` (inside ``outer``) in the coordinates of an array cut to ``outer``."""
    return tuple(slice(b.start - o.start, b.stop - o.start) for o, b in zip(outer, box))


def _cut_reader(reader: "Reader", outer_reader: "Reader", box: tuple[slice, slice],
                outer: tuple[slice, slice]) -> "Reader":
    """A reader that, asked for ``box``, has ``outer_reader`` read ``outer`` (which holds
    ``box``; the images a later pass reads) and cuts each image to ``box``; any other box it
    leaves to ``reader``. ``outer_reader`` runs its checks on ``box``'s part, as ``reader``
    would on ``box``: the object's pixels for the notes, and the ambient image's check."""
    cut = _inner(box, outer)

    def read(start: int, asked: tuple[slice, slice]) -> Iterator[np.ndarray]:
        if asked != box:
            yield from reader(start, asked)
            return
        for img in outer_reader(start, outer):
            yield np.ascontiguousarray(img[cut])

    return read


# --- errors -----------------------------------------------------------------------------------

def intensity_error(est: np.ndarray, gt: np.ndarray) -> float:
    """Scale-invariant relative intensity error of estimates [N] (grey: LCNet's) or [N, 3] (RGB:
    a matte sphere's) against ground truth [N] or [N, 3] (RGB). As the authors' evaluation for a
    grey estimate: each ground-truth channel is first divided by its first row (a grey estimate
    cannot know the lights' common colour), then mean(|s e_i - e~_i| / e~_i) over images and
    channels, s by least squares. An RGB estimate against RGB truth: the same with one s per
    channel (each channel is known up to its own scale; scoring its grey mean instead counted the
    lights' true colours as errors: 0.037 for a calibration right to 0.0006, a QA helper's finding)."""
    from psctl.metrics import intensity_relative_error

    est = np.asarray(est, np.float64)
    n = est.shape[0] if est.ndim else 1
    gt = np.asarray(gt, np.float64).reshape(n, -1)
    est = est.reshape(n, -1)
    if est.shape[1] > 1 and est.shape[1] == gt.shape[1]:
        return float(np.mean([intensity_relative_error(est[:, c], gt[:, c]) for c in range(gt.shape[1])]))
    est = est.mean(1)
    gt = gt / gt[:1]
    return intensity_relative_error(np.repeat(est[:, None], gt.shape[1], 1), gt)


def light_errors(directions: np.ndarray, intensities: np.ndarray, gt_directions: np.ndarray | None = None,
                 gt_intensities: np.ndarray | None = None) -> dict:
    """{"light_mae": mean angle (degrees) or None, "intensity_re": float or None,
    "direction_errors": [N] degrees or None}."""
    from psctl.metrics import light_direction_error

    out: dict = {"light_mae": None, "intensity_re": None, "direction_errors": None}
    if gt_directions is not None:
        err = light_direction_error(directions, gt_directions)
        out["direction_errors"] = err
        out["light_mae"] = float(err.mean())
    if gt_intensities is not None:
        out["intensity_re"] = intensity_error(intensities, gt_intensities)
    return out


# --- files and pictures -----------------------------------------------------------------------

def image_list(cap: "Capture") -> str:
    """light_images.txt's text: each image's path from the capture folder, with forward slashes
    (a list written on Windows reads on Linux, and filenames.txt's reader takes it back), or in
    full where there is no relative path (an image listed on another drive)."""
    lines = []
    for p in cap.image_paths:
        try:
            lines.append(Path(os.path.relpath(p, cap.path)).as_posix())
        except ValueError:  # Windows: another drive
            lines.append(Path(os.path.abspath(p)).as_posix())
    return "".join(f"{n}\n" for n in lines)


def write_light_files(folder: str | os.PathLike, directions: np.ndarray, intensities: np.ndarray | None,
                      names: dict[str, str] | None = None) -> dict[str, Path]:
    """light_directions.txt (N x 3) and light_intensities.txt (N x 3; one value per image is
    repeated: grey) in DiLiGenT's format (``names``: other file names for the keys
    "light_directions" and "light_intensities"); ``intensities`` None: directions only."""
    from psctl.io.atomic import write_text_atomic

    names = names or OUTPUT_FILES
    folder = Path(folder)
    d = np.asarray(directions, np.float64)
    paths = {"light_directions": folder / names["light_directions"]}
    write_text_atomic(paths["light_directions"], "".join(f"{x:.8f} {y:.8f} {z:.8f}\n" for x, y, z in d))
    if intensities is not None:
        e = np.asarray(intensities, np.float64).reshape(len(d), -1)
        if e.shape[1] == 1:
            e = np.repeat(e, 3, 1)
        paths["light_intensities"] = folder / names["light_intensities"]
        write_text_atomic(paths["light_intensities"], "".join(f"{r:.6f} {g:.6f} {b:.6f}\n" for r, g, b in e))
    return paths


def _disk(canvas: np.ndarray, cy: float, cx: float, r: float, colour, ring: float | None = None) -> None:
    """A filled disk (or, with ``ring`` = line width, a circle) of radius r at (cy, cx)."""
    H, W = canvas.shape[:2]
    pad = r + (ring or 0) + 1
    y0, y1 = max(int(cy - pad), 0), min(int(cy + pad) + 1, H)
    x0, x1 = max(int(cx - pad), 0), min(int(cx + pad) + 1, W)
    if y1 <= y0 or x1 <= x0:
        return
    yy, xx = np.ogrid[y0:y1, x0:x1]
    d = np.sqrt((yy - cy) ** 2 + (xx - cx) ** 2)
    sel = np.abs(d - r) <= ring / 2 if ring else d <= r
    canvas[y0:y1, x0:x1][sel] = colour


def _dot(canvas: np.ndarray, cy: float, cx: float, colour) -> None:
    """An estimate's marker: a disk of radius 3.5 in ``colour`` with a light 1 px rim, which
    keeps jet's dark ends (the weakest and strongest lights) apart from the dark grey disk."""
    _disk(canvas, cy, cx, 4.5, 0.8)
    _disk(canvas, cy, cx, 3.5, colour)


def _segment(canvas: np.ndarray, p0: tuple[float, float], p1: tuple[float, float], colour) -> None:
    """A one-pixel line from p0 to p1 ((row, col) each)."""
    steps = int(max(abs(p1[0] - p0[0]), abs(p1[1] - p0[1]))) + 1
    t = np.linspace(0.0, 1.0, steps + 1)
    rows = np.round(p0[0] + t * (p1[0] - p0[0])).astype(int)
    cols = np.round(p0[1] + t * (p1[1] - p0[1])).astype(int)
    ok = (rows >= 0) & (rows < canvas.shape[0]) & (cols >= 0) & (cols < canvas.shape[1])
    canvas[rows[ok], cols[ok]] = colour


def lights_plot(directions: np.ndarray, intensities: np.ndarray | None, gt_directions: np.ndarray | None = None,
                title: str | None = None, radius: int = 220, ints_range: tuple[float, float] = (0.2, 2.0)) -> np.ndarray:
    """Estimated (and true) light directions on the unit disk: [H, W, 3] in [0, 1].

    Orthographic view of the hemisphere from the camera: a direction (x, y, z) is drawn at
    (x, y), x right, y up (axes labelled +X, +Y); grey circles at 30, 60 and 90 degrees from the
    view axis. Estimates are filled dots coloured by intensity divided by the intensities' mean
    (jet over ``ints_range``, colour bar on the right, labelled) with a light rim, or, with ``intensities`` None (directions only: a chrome
    sphere's), all orange with no bar; ground truth, when given, is a white ring joined to its
    estimate by a grey line. A legend under the disk says which is which.
    """
    from psctl.io.report import _stamp, colour_bar, jet, text_bitmap

    s = 2  # text scale
    top, pad, bar_w, right, bottom = 20 * s, 12, 10 * s, 44 * s, 14 * s  # top: the title, then the bar's name
    side = 2 * (radius + pad)
    legend = text_bitmap("ESTIMATE" if intensities is None else "ESTIMATE, COLOUR: INTENSITY / MEAN", s)
    true = text_bitmap("TRUE", s)
    legend_w = 4 * s + 12 + legend.shape[1] + 6 * s + 16 + true.shape[1]  # with or without its TRUE: one size
    title_w = 4 * s + (text_bitmap(title, s).shape[1] if title else 0)
    # as wide as the disk and its colour bar, the legend and the title, whichever is widest
    canvas = np.full((top + side + bottom, max(side + right, legend_w + 4 * s, title_w), 3), 0.12, np.float32)
    cy, cx = top + side / 2, side / 2
    _disk(canvas, cy, cx, radius, 0.18)
    for zenith in (30.0, 60.0, 90.0):
        _disk(canvas, cy, cx, radius * np.sin(np.radians(zenith)), 0.35, ring=1.0)
    _segment(canvas, (cy, cx - radius), (cy, cx + radius), 0.3)
    _segment(canvas, (cy - radius, cx), (cy + radius, cx), 0.3)
    grey = (0.6, 0.6, 0.6)

    def at(d: np.ndarray) -> tuple[float, float]:
        return cy - d[1] * radius, cx + d[0] * radius  # y up: row 0 is the top

    d = np.asarray(directions, np.float64).reshape(-1, 3)
    lo, hi = ints_range
    span = max(hi - lo, 1e-12)  # (a range of one value: one label, every dot in its colour)
    e = np.ones(len(d)) if intensities is None else np.asarray(intensities, np.float64).reshape(-1)
    if e.size and np.isfinite(e).all() and e.mean() > 0:
        e = e / e.mean()  # only relative intensities mean anything (LCNet's have no scale): colour them about 1
    dot = (1.0, 0.6, 0.2)  # the legend's
    colours = np.tile(dot, (len(d), 1)) if intensities is None else jet((e - lo) / span)  # clipped to the bar's ends
    g = None if gt_directions is None else np.asarray(gt_directions, np.float64).reshape(-1, 3)
    if gt_directions is not None:
        for k in range(len(d)):
            _segment(canvas, at(d[k]), at(g[k]), 0.6)
        for k in range(len(g)):
            _disk(canvas, *at(g[k]), 5.0, 1.0, ring=1.5)
    for k in range(len(d)):
        _dot(canvas, *at(d[k]), colours[k])
    # each ring's angle from the view axis, just outside the ring where the fewest markers are near
    # (lower left first), drawn last in a dark outline: over DiLiGenT's lights the label was
    # unreadable (a QA helper), and at a fixed place it hid a light (helper-162)
    marks = np.array([at(v) for v in (*d, *(() if g is None else g))], np.float64).reshape(-1, 2)

    def crowd(y: int, x: int, h: int, w: int) -> int:  # markers within 6 px of a label's box
        return int(((marks[:, 0] > y - 6) & (marks[:, 0] < y + h + 6) & (marks[:, 1] > x - 6)
                    & (marks[:, 1] < x + w + 6)).sum())

    def outlined(bm: np.ndarray, y: int, x: int) -> None:  # over the markers, readable on any of them
        for dy in (-s, 0, s):
            for dx in (-s, 0, s):
                _stamp(canvas, bm, y + dy, x + dx, (0.05, 0.05, 0.05))
        _stamp(canvas, bm, y, x, grey)

    # the axes' names at the rim, on the side of their axis with fewer markers (a light near the rim
    # on an axis hid "+Y" or "+X" when they were drawn under the markers at a fixed place)
    bm = text_bitmap("+Y", s)
    h, w = bm.shape
    y = int(cy - radius) + 2 * s
    x = min((int(cx) + 3 * s, int(cx) - 3 * s - w), key=lambda x: crowd(y, x, h, w))
    outlined(bm, y, x)
    bm = text_bitmap("+X", s)
    h, w = bm.shape
    x = int(cx + radius) - w - 2 * s
    y = min((int(cy) + 3 * s, int(cy) - 3 * s - h), key=lambda y: crowd(y, x, h, w))
    outlined(bm, y, x)
    for zenith in (30.0, 60.0):
        bm = text_bitmap(f"{zenith:.0f}°", s)
        h, w = bm.shape
        reach = radius * np.sin(np.radians(zenith)) + 0.5 * np.hypot(h, w) + 2  # the box's centre
        spots = []
        for a in np.radians(225.0 + np.array(sorted(range(-165, 195, 15), key=lambda v: (abs(v), -v)))):  # 0, 15, -15, ..
            y, x = int(round(cy - reach * np.sin(a) - h / 2)), int(round(cx + reach * np.cos(a) - w / 2))
            spots.append((crowd(y, x, h, w), len(spots), y, x))
        _, _, y, x = min(spots)
        outlined(bm, y, x)
    # colour bar: high intensities on top, its name above it
    ticks = [lo, *(v for v in (0.5, 1.0, 1.5) if lo < v < hi), hi]  # 1.0, the nominal intensity, among them
    labels = {(v - lo) / span: f"{v:.1f}" for v in ticks}
    upper, lower = max(labels), min(labels)  # the bar's ends
    labels[upper] = (">" if (e > hi).any() else "") + labels[upper]
    labels[lower] = ("<" if (e < lo).any() else "") + labels[lower]
    if intensities is not None:
        colour_bar(canvas, top + pad, side + 4 * s, side - 2 * pad, bar_w, labels, s)
        _stamp(canvas, text_bitmap("INT.", s), top + pad - 9 * s, side + 2 * s)
    # legend: a dot, then a ring with its line (when there is ground truth)
    y = top + side + 3 * s
    mid = y + 3.5 * s
    _dot(canvas, mid, 4 * s + 4, dot)
    x = 4 * s + 12
    _stamp(canvas, legend, y, x)
    x += legend.shape[1] + 6 * s
    if gt_directions is not None:
        _disk(canvas, mid, x + 6, 5.0, 1.0, ring=1.5)
        _stamp(canvas, true, y, x + 16)
    if title:
        _stamp(canvas, text_bitmap(title, s), 2 * s, 2 * s)
    return canvas


def write_lights_plot(path: str | os.PathLike, directions: np.ndarray, intensities: np.ndarray | None,
                      gt_directions: np.ndarray | None = None, light_mae: float | None = None,
                      name: str | None = None) -> None:
    """lights.png (8-bit RGB): ``name`` (the object's) and, when known, the mean direction error
    in the title."""
    from psctl.io.images import write_image

    title = "ESTIMATED LIGHTS" if light_mae is None else f"LIGHT DIRECTION MAE {light_mae:.2f}°"
    title = title if name is None else f"{name}: {title}"
    write_image(path, lights_plot(directions, intensities, gt_directions, title), "uint8")


# LCNet learnt from rigs around the view axis; with the lights to one side its estimates lean less
# than the lights do (a quarter rig's also come out nearer the axis) and the refinement does not undo
# that (a QA finding: 12 degrees, silently). On psctl's synthetic objects (benchmarks/one_sided.py,
# docs/uncalibrated.md, "One-sided rigs") the estimates' lean stayed <= 0.18 for rigs around the
# axis and was 0.35-0.84 for half, quarter and lopsided 10-light rigs
ONE_SIDED = 0.35
_SIDES = ("right", "upper right", "top", "upper left", "left", "lower left", "bottom", "lower right")


def one_sided(directions: np.ndarray) -> float:
    """How much the lights lean to one side: |mean of their image-plane parts| / mean of their
    lengths; 0 for a rig around the view axis, 1 for lights all in one direction. directions [N, 3]."""
    xy = np.asarray(directions, np.float64).reshape(-1, 3)[:, :2]
    size = float(np.linalg.norm(xy, axis=1).mean()) if len(xy) else 0.0
    return float(np.linalg.norm(xy.mean(0)) / size) if size > 1e-6 else 0.0


def one_sided_notes(directions: np.ndarray) -> list[str]:
    """A note when the estimated lights lie to one side of the view axis (``ONE_SIDED``)."""
    lean = one_sided(directions)
    if lean <= ONE_SIDED:
        return []
    mx, my = np.asarray(directions, np.float64).reshape(-1, 3)[:, :2].mean(0)
    side = _SIDES[int(np.round(np.degrees(np.arctan2(my, mx)) / 45.0)) % 8]
    return [f"lights: the estimates lie to one side of the view axis (the {side}; lean {lean:.2f}, where a rig "
            f"around the axis gives under 0.2): LCNet learnt from rigs around the axis, and on synthetic objects "
            f"lit from one side (half or a quarter of the rig) its directions came out 8.0-13.4 degrees off on "
            f"average, against 3.4-6.6 lit all around (docs/uncalibrated.md, 'One-sided rigs'); calibrate the "
            f"lights if you can (psctl calibrate)"]


# --- the command ------------------------------------------------------------------------------


def run_lights(path: str | os.PathLike, out: str | os.PathLike | None = None,
               weights: str | os.PathLike | None = None, device: str = "auto", decode: str = "soft",
               n_images: int | None = None, seed: int | None = None, write: bool = True,
               progress: "ProgressFactory | None" = None, views: int = DEFAULT_LIGHTS["views"],
               refine: bool = True, normals_weights: str | os.PathLike | None = None,
               falloff: str | None = None, roll: bool | None = None, encoding: str = "auto",
               light_distance: float | None = None, precision: str = "float32",
               arrays: dict | None = None, snap: bool = True) -> dict:
    """Estimate a capture folder's lights with LCNet, write them, return the report.

    ``weights``: LCNet's file (None: the installed one); ``device``: auto | cpu | cuda | cuda:N;
    ``decode``: how LCNet's classes become lights, "soft" (soft-argmax: the expected class index
    under the softmax, so an estimate can fall between bin centres) or "argmax" (the paper's bin
    centre; ``psctl.models.lcnet.decode``); ``views``: LCNet's answers averaged over
    1, 2, 4 or 8 symmetric views of the images (``psctl.symmetry``); ``n_images`` and ``seed``:
    a subset (``psctl.io.capture.select_images``); ``progress``: None or a factory (label,
    total) -> advance(k).

    ``encoding`` (auto | linear | srgb): how the images' values map to radiance
    (``psctl.io.capture.open_capture``; auto decodes files with an ICC profile through its tone curves,
    else JPEGs from sRGB, with a note).

    ``refine``: when a network that estimates normals from lights is installed (sdps' second
    stage, or ``normals_weights``), LCNet's lights are refined against its normals
    (``psctl.refine.refine_estimate``; off with refine=False or when none is installed, which a note says);
    ``falloff`` "shifted" or "lambertian" and ``roll`` (turn the refined lights by the roll of the
    normals they give, ``psctl.refine.roll_estimate``) override ``psctl.refine.DEFAULT_REFINE``'s. ``light_distance`` (pixels,
    with ``refine``): the lights are points that far from the mask's centroid (without a mask
    file, the found object's) along the estimated directions, and the refinement reads the images with their falloff divided out
    (``psctl.nearlight``; LCNet reads them as captured). ``precision`` (float32, bf16, fp16): the
    refinement's normals network's arithmetic (LCNet runs in float32), as ``psctl.run_normals``'.
    ``snap`` (True): LCNet and the light fit read a mask file snapped to the object
    (``psctl.masks.snap_mask``, noted when it leaves out over 2%, or when a mask kept as given looks drawn
    wider, ``psctl.masks.unsure_note``); False: as given (--no-snap).

    Returns the dict printed by ``psctl lights --json``: object, n_images, light_mae and
    intensity_re (None without ground truth), outputs, plus path, device, decode, views, light_distance,
    lights_refined ({quality, weight, ...} or None), lcnet_light_mae and lcnet_intensity_re
    (LCNet's own lights), precision, found_object (the object found without a mask file, else
    None), seconds, notes and provenance (``psctl.api.provenance``); docs/formats.md has each key. Outputs (when
    ``write``, all or none): light_directions.txt, light_intensities.txt, lights.png and
    lights_report.json (this report) in ``out`` (default ``PATH/psctl``), never in the capture
    folder itself; with an ``n_images`` subset also light_images.txt.
    ``arrays`` (a dict) receives what the light files hold: "directions" [N, 3] unit vectors (x
    right, y up, z toward the camera) and "intensities" [N, 3], one row per image (with
    ``n_images``, the chosen ones).
    """
    from psctl.io.atomic import check_output_dir, output_folder, staged_outputs
    from psctl.io.capture import (check_not_capture, capture_notes, load_mask, open_capture, select_images,
                                  selection_notes)

    t0, started = time.perf_counter(), time.time()  # started: for weights files replaced during the run
    for name, value in (("path", path), ("out", out), ("weights", weights), ("normals_weights", normals_weights)):
        check_path(name, value, optional=name != "path")
    if arrays is not None and not isinstance(arrays, dict):
        raise PsctlError(None, f"arrays must be a dict (it receives the light directions and intensities), not a "
                               f"{type(arrays).__name__}")
    fit = refine_config(falloff, roll)
    write, refine = check_bool("write", write), check_bool("refine", refine)  # "no" is truthy: never a yes
    snap = check_bool("snap", snap)
    progress = check_progress(progress)
    from psctl.symmetry import check_views

    check_views(views)  # options first: their errors name the option, not the capture folder
    decode = check_decode(decode, "--decode")
    from psctl.models import check_device_name, check_precision, precision_autocast

    check_device_name(device)  # a typo named as psctl normals names it, before the capture is read

    precision = check_precision(precision)
    from psctl.models.weights import installed_path
    from psctl.sdps import SDPS_SECOND

    # refined only with a normals network: asked for, but none installed, the refinement's options go unused
    refines = refine and (normals_weights is not None or any(installed_path(m) for m in SDPS_SECOND))
    second = None
    if refines:  # which network refines, decided once (a file given is checked here, before any work)
        from psctl.sdps import sdps_second_stage

        second = sdps_second_stage(normals_weights, flag="--normals-weights")[0]
    # the refinement's normals network; checked before any work (not where none will run)
    net_cfg = {"device": device, "autocast": precision_autocast(precision, device) if refines else None}
    cap = open_capture(path, encoding)
    n_all = cap.n_images
    picked = selection_notes(n_all, n_images, seed)  # never by the folder's lights: they are the answer
    cap = cap.subset(select_images(n_all, n_images, seed))
    picked += capture_notes(cap)
    subset = cap.n_images < n_all
    if subset:
        picked.append(f"images: the light files have {cap.n_images} rows, one per image listed in {SUBSET_FILE}")
    out_dir = output_folder(out, cap.path)
    if write:
        check_not_capture(out_dir, cap, (*OUTPUT_FILES.values(), FOUND_FILE, REPORT_FILE))  # its light files are inputs
        from psctl.io.atomic import check_inputs_kept

        check_inputs_kept(out_dir, [*OUTPUT_FILES.values(), SUBSET_FILE, FOUND_FILE, REPORT_FILE],
                          (("--weights", weights), ("--normals-weights", normals_weights)))
        check_output_dir(out_dir)
    mask = load_mask(cap)
    memo = None
    if refine or cap.mask_path is None:  # later passes take the images earlier ones decoded, where they fit
        from psctl.infer import DEFAULT_INFER
        from psctl.io.capture import DecodeMemo

        memo = DecodeMemo({**DEFAULT_INFER, **net_cfg}["cache_mb"] << 20)
    if light_distance is not None:
        from psctl.models.weights import installed_path
        from psctl.nearlight import check_light_distance
        from psctl.sdps import SDPS_SECOND

        check_light_distance(light_distance)  # the number now; where the lights sit, once the object is known
        if not refine:
            raise PsctlError(None, "--light-distance needs --refine: LCNet reads the images as captured, and only "
                                   "the refinement divides out the falloff")
        if normals_weights is None and not any(installed_path(m) for m in SDPS_SECOND):
            raise PsctlError(None, "--light-distance needs the light refinement, which needs a normals network "
                                   "(PS-FCN† / PS-FCN / PS-FCN+N): none is installed; name one with --normals-weights")
    from psctl.models.weights import installed_path, no_weights_error

    if weights is None and installed_path("lcnet") is None:  # before the read below, as the options' errors
        raise no_weights_error("lcnet", "--weights")
    # what LCNet and the light fit read: the mask, or the object found without one
    fit_mask, lc_cfg, found, snapped = capture_object(cap, mask, {"device": device, "decode": decode,
                                                                  "views": views}, progress, memo, snap=snap)
    picked += [] if found is None else [NO_MASK_PREFIX + n for n in found.notes]
    picked += [f"mask: {snapped}"] if snapped else []
    shown = found is not None and found.mask is not None  # read in the mask's place (and written for the user)
    near = None
    if light_distance is not None:  # the lights sit about the object's centre: the found one's without a mask
        from psctl.nearlight import near_lights, near_note

        # the centre of the user's mask (as psctl normals takes it), not of the snapped one
        near = near_lights(light_distance, fit_mask if found is not None else mask, cap.mask_path, found=shown)
        picked.append(near_note(near, "the refinement divides each image by its light's falloff (LCNet reads the "
                                      "images as captured)"))
    keep_box = None
    if refine:  # the refinement's passes take the images LCNet's decoded, where they fit
        from psctl.infer import first_read_box

        keep_box = first_read_box(cap, fit_mask, net_cfg)
    est = capture_lights(cap, fit_mask, weights, lc_cfg, progress, memo=memo, keep_box=keep_box)
    gt_ints = cap.intensities if cap.intensities_given else None
    lcnet_errors = light_errors(est.directions, est.intensities, cap.lights, gt_ints)
    if refines:
        # no normals written: the network too reads the found object only, its exposure the object's mean
        # (as a mask.png would make them; the lit pixels' rule of a capture without one split the object)
        cfg = {**net_cfg, "exposure_pixels": "found"} if shown else net_cfg
        est = _refine_capture(replace(cap, near=near), fit_mask, est, normals_weights, second, cfg, progress, fit,
                              memo)
    elif refine:
        est = replace(est, notes=[*est.notes, "lights: no normals network installed (PS-FCN† / PS-FCN / PS-FCN+N); "
                                              "LCNet's lights are not refined"])
    elif normals_weights is not None:
        est = replace(est, notes=[*est.notes, "lights: --normals-weights is unused without --refine"])
    est = replace(est, notes=[*est.notes, *one_sided_notes(est.directions)])
    from psctl.api import unused_note, unused_options

    why = "refine" if not refine else "no-network"
    unused = [unused_note(k, why) for k, _ in unused_options("sdps", refines, 1, 1, "float32", falloff, roll)]
    if not refines and precision != "float32":  # the refinement's network: LCNet alone runs in float32
        unused.append(unused_note("precision-refine", why))
    est = replace(est, notes=[*est.notes, *unused])
    if not refines:
        precision = "float32"  # LCNet's, the only network that ran
    errors = light_errors(est.directions, est.intensities, cap.lights, gt_ints)
    if arrays is not None:
        ints = np.array(est.intensities, np.float32).reshape(len(est.directions), -1)
        arrays.update(directions=np.array(est.directions, np.float32),
                      intensities=np.repeat(ints, 3, 1) if ints.shape[1] == 1 else ints)  # as the file: R G B
    report = {
        "object": cap.name,
        "path": os.path.abspath(cap.path),
        "n_images": cap.n_images,
        "light_mae": errors["light_mae"],
        "intensity_re": errors["intensity_re"],
        "outputs": {},
        "decode": est.info["decode"],
        "views": est.info["views"],
        "lights_refined": est.info.get("refine"),
        "lcnet_light_mae": lcnet_errors["light_mae"],
        "lcnet_intensity_re": lcnet_errors["intensity_re"],
        "device": est.info["device"],
        "precision": precision,
        "light_distance": None if near is None else near.distance,
        "found_object": None if found is None else found.info,
        "seconds": round(time.perf_counter() - t0, 3),
        "notes": picked + est.notes,
    }
    from psctl.api import provenance, provenance_notes, weights_used

    # LCNet's file, and the refinement's network where one ran (sdps' second stage, or --normals-weights)
    used = weights_used("sdps", normals_weights, weights, second) if refines else \
        {"lcnet": weights if weights is not None else installed_path("lcnet")}
    report["provenance"] = provenance(used, est.info["device"], started)
    report["notes"] += provenance_notes(report["provenance"])
    if subset:  # an --images subset: which images and the seed, as psctl normals reports them
        from psctl.io.capture import selection_report

        report["images_used"] = [os.path.relpath(p, cap.path) for p in cap.image_paths]
        report.update(selection_report(seed))  # never by the folder's lights
    if write:
        from psctl.io.atomic import own_outputs, read_outputs_list, replaced_notes, write_outputs_list
        from psctl.io.report import write_json

        report["outputs"] = {k: os.path.abspath(out_dir / v) for k, v in OUTPUT_FILES.items()}
        names = [*OUTPUT_FILES.values(), *([SUBSET_FILE] if subset else []), *([FOUND_FILE] if shown else []),
                 REPORT_FILE]
        # a same-named file of the user's (a mask_found.png psctl normals wrote there is psctl's: no word)
        ours = own_outputs(out_dir, "lights") + [n for n in read_outputs_list(out_dir, "normals") if n == FOUND_FILE]
        report["notes"] += replaced_notes(out_dir, names, "lights", ours)
        if subset:
            report["outputs"]["light_images"] = os.path.abspath(out_dir / SUBSET_FILE)
        elif (out_dir / SUBSET_FILE).is_file():
            report["notes"].append(f"outputs: removed {SUBSET_FILE}, left by an earlier psctl lights --images run "
                                   "(these light files have a row for every image)")
        if shown:
            report["outputs"]["mask_found"] = os.path.abspath(out_dir / FOUND_FILE)
            report["notes"].append(f"{NO_MASK_PREFIX}the object found is in {FOUND_FILE}: check it; copied into the "
                                   f"capture folder as mask.png, it is read as the mask")
        # an earlier run's found object goes (one this run's list will not name); a file of the user's stays
        earlier = FOUND_FILE in read_outputs_list(out_dir, "lights") and (out_dir / FOUND_FILE).is_file()
        if earlier and not shown:
            report["notes"].append(f"outputs: removed {FOUND_FILE}, left by an earlier psctl lights run that found the "
                                   f"object (this one {'read ' + cap.mask_path.name if found is None else 'found none'})")
        # an earlier subset's list goes, and an earlier found object
        with staged_outputs(out_dir, replaces=[SUBSET_FILE, *([FOUND_FILE] if earlier else [])]) as stage:
            write_outputs_list(stage, names, "lights")
            write_light_files(stage, est.directions, est.intensities)
            if subset:
                (stage / SUBSET_FILE).write_text(image_list(cap), encoding="utf-8")
            if shown:
                from psctl.io.images import write_image

                write_image(stage / FOUND_FILE, found.mask.astype(np.float32), "uint8", kind="data")
            write_lights_plot(stage / OUTPUT_FILES["lights"], est.directions, est.intensities, cap.lights,
                              errors["light_mae"], cap.name)
            report["outputs"]["report"] = os.path.abspath(out_dir / REPORT_FILE)
            report["seconds"] = round(time.perf_counter() - t0, 3)  # the file and the return agree
            write_json(stage / REPORT_FILE, report)
    return report


def _refine_capture(cap: "Capture", mask: np.ndarray, est: LightEstimate, weights: str | os.PathLike | None,
                    second: str, net_cfg: dict, progress: "ProgressFactory | None", config: dict | None = None,
                    memo: "DecodeMemo | None" = None) -> LightEstimate:
    """LCNet's lights refined against the normals that sdps' second stage gives from them (and
    turned by the roll of the normals from the refined lights when the config says so).
    ``memo``: images decoded by LCNet's pass. ``second``: the second stage's method, which
    run_lights chose once, before any work (``weights`` None: the installed network)."""
    from psctl.sdps import capture_source, second_stage

    source = capture_source(cap, mask, second, weights, net_cfg, progress, memo)
    return second_stage(source, est, True, config, normals=False)[0]


def render_lights(r: dict) -> None:
    """The human-readable summary of ``run_lights``'s report (Rich, stdout)."""
    from psctl.errors import console
    from psctl.io.summary import escape, print_notes, print_written

    con = console()
    print_notes(con, r.get("notes", []))
    line = f"[bold]{escape(r['object'])}[/]: LCNet ({r['decode']}), {r['n_images']} images, {r['seconds']:.2f} s"
    if r.get("lights_refined") and r["lights_refined"]["weight"] > 0:
        line += f", {r['lights_refined']['weight']:.0%} refined against the normals"  # as the note says
    if r["light_mae"] is not None:
        line += f"\n  light direction error [bold]{r['light_mae']:.2f}°[/] (mean)"
        if lights_changed(r.get("lights_refined")) and r.get("lcnet_light_mae") is not None:
            line += f" (LCNet alone {r['lcnet_light_mae']:.2f}°)"
    if r["intensity_re"] is not None:
        line += f", intensity relative error [bold]{r['intensity_re']:.3f}[/]"
    con.print(line, highlight=False, soft_wrap=True)
    print_written(con, r["outputs"])


# names that moved to psctl.masks and psctl.refine on 2026-12-01, still found here (with a warning)
__getattr__ = moved_names(__name__, "psctl.masks", "psctl.refine")

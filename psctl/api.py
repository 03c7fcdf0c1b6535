"""The Python API. The CLI is a thin layer over these functions.

    >>> import psctl
    >>> result = psctl.run_normals("examples/bumpy_sphere", method="l2", out="/tmp/sphere")
    >>> normals = psctl.estimate_normals(images, lights, mask, method="l2")   # arrays in, array out
"""

from __future__ import annotations

import contextlib
import os
import time
import sys
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

# ProgressFactory: progress(description, total) -> advance(n), how library code reports progress
# without depending on a UI (the CLI passes a Rich one; None is silent); defined in psctl.errors
from psctl.errors import (ProgressFactory, PsctlError, PsctlWarning, caller_level, check_bool, check_formats,  # noqa: F401
                          check_path, check_progress)
from psctl.io.atomic import OutputBatch, outputs_list, read_outputs_list, replaced_notes, write_outputs_list
from psctl.models import NETWORK_METHODS, check_device_name
from psctl.sdps import SDPS_SECOND, check_sdps_weights, sdps_second_stage  # noqa: F401 (sdps_second_stage: API)

if TYPE_CHECKING:
    from pathlib import Path

    from psctl.albedo import AlbedoResult
    from psctl.io.capture import Capture, DecodeMemo
    from psctl.lights import LightEstimate
    from psctl.masks import FoundObject
    from psctl.nearlight import NearLights

METHODS = ("auto", "l2", "ps-fcn", "ps-fcn-n", "ensemble", "ups-fcn", "sdps")
NETWORKS = ("ps-fcn", "ps-fcn-n", "ups-fcn")  # need weights: installed in weights/ or --weights FILE
LISTED_LIGHTS = ("l2", "ps-fcn", "ps-fcn-n", "ensemble")  # the methods that read light_directions.txt


def resolve_method(method: str, calibrated: bool, weights: str | os.PathLike | None = None,
                   lcnet: str | os.PathLike | None = None,
                   lights_file: str | os.PathLike | None = None) -> tuple[str, str | None]:
    """Map a user-facing method name to a concrete one; return (method, note for the user).

    auto: the method of ``weights`` when given, else (calibrated folders) ensemble when both
    ps-fcn and ps-fcn-n are installed, else whichever of them is, else l2. Without
    light_directions.txt: sdps (LCNet + PS-FCN†), else ups-fcn when only its weights are
    installed, else an error naming the missing weights. ``lcnet`` (a file) is sdps's LCNet.
    ensemble: both networks must be installed; ``weights`` is refused (it names one file).
    ``lights_file``: the folder's light_directions.txt, named when a method needs it and it is
    missing (None: arrays, whose lights are an argument).
    """
    if not isinstance(method, str):
        raise PsctlError(None, f"method must be one of {', '.join(METHODS)}, not {method!r}")
    check_path("weights", weights, optional=True)
    check_path("lcnet", lcnet, optional=True)
    method = method.lower()
    if method not in METHODS:
        raise PsctlError(None, f"unknown --method {method!r}; choose from {', '.join(METHODS)}")
    if lcnet is not None and method not in ("sdps", "auto"):
        raise PsctlError(lcnet, f"--lcnet is for --method sdps (or auto), not {method}")
    if method == "auto" and weights is not None:
        from psctl.models.weights import method_of

        method, note = method_of(weights)
        if method == "lcnet":
            raise PsctlError(weights, "holds LCNet weights (light estimation): use `psctl lights`, or pass them "
                                      "with --lcnet FILE to --method sdps")
        if method == "ps-fcn-dagger":  # the second stage of sdps
            note = check_sdps_weights(weights, lcnet)
            return "sdps", f"auto: sdps (PS-FCN† weights from {weights}); {note}"
        if NETWORK_METHODS[method]["lights"] and not calibrated:
            raise PsctlError(lights_file, ("missing: " if lights_file is not None else "") +
                             f"{weights} holds {method} weights, which need light directions; without them "
                             "--method sdps estimates the lights (with these weights as its second stage)")
        return method, note or f"auto: {method} (from {weights})"
    if method == "auto" and (not calibrated or lcnet is not None):
        from psctl.models.weights import installed_path

        # sdps runs when LCNet and any second stage are installed (PS-FCN†, else the calibrated
        # networks on LCNet's lights); UPS-FCN, single-stage and weaker, only when it cannot
        sdps_ready = installed_path("lcnet") is not None and (
            weights is not None or any(installed_path(m) is not None for m in SDPS_SECOND))
        if lcnet is None and installed_path("ups-fcn") is not None and not sdps_ready:
            return "ups-fcn", "auto: no light_directions.txt and the sdps weights are not installed: ups-fcn"
        note = check_sdps_weights(None, lcnet)
        # calibrated here only because --lcnet was given: the listed lights are not what chose sdps
        why = "--lcnet given, so sdps" if calibrated else "no light_directions.txt"
        return "sdps", f"auto: {why}; {note}"
    if method == "sdps":
        return "sdps", check_sdps_weights(weights, lcnet)
    if method == "ensemble":
        from psctl.infer import ENSEMBLE
        from psctl.models.weights import installed_path, weights_where

        if weights is not None:
            raise PsctlError(weights, "--weights names one network's file; ensemble uses the installed "
                                      f"{' and '.join(ENSEMBLE)} (use --method ps-fcn or --method ps-fcn-n with --weights)")
        missing = [m for m in ENSEMBLE if installed_path(m) is None]
        if missing:
            instead = next((m for m in ENSEMBLE if m not in missing), "l2")
            raise PsctlError(None, f"ensemble averages {' and '.join(ENSEMBLE)}, and no weights are installed for "
                                   f"{' and '.join(missing)} (looked in {weights_where()}); use --method {instead}")
    if method == "auto":
        from psctl.infer import ENSEMBLE
        from psctl.models.weights import installed_path, weights_where

        # the average of the two installed networks beat either alone on the synthetic test sets,
        # by which psctl chooses (benchmarks/ensemble.py's rule, session 34: the sum over seven
        # sets 29.60 vs PS-FCN 30.13 and PS-FCN+N 32.87; since session 55 28.97 vs 30.13 and 31.78); of the two alone PS-FCN comes first:
        # the release ps_fcn.pt beats ps_fcn_n.pt on them (syntest 4.94 vs 5.68, DiLiGenT-like
        # lights 4.15 vs 4.32, GPU stage 12; weights/README.md)
        have = [m for m in ENSEMBLE if installed_path(m) is not None]
        if len(have) == len(ENSEMBLE):
            return "ensemble", None
        if have:
            return have[0], None
        return "l2", f"auto: no trained network weights are installed in {weights_where()}, using l2 (least squares)"
    if weights is not None and method not in NETWORKS:
        raise PsctlError(weights, f"--weights is for the network methods ({', '.join(NETWORKS)}) and sdps (its normals "
                                  f"network), not {method}")
    if (method == "ensemble" or method in NETWORKS and NETWORK_METHODS[method]["lights"]) and not calibrated:
        if lights_file is not None:
            from psctl.io.capture import missing_lights_hint

            raise PsctlError(lights_file, f"missing: {method} needs calibrated light directions; without them "
                                          "--method sdps estimates the lights (as auto does), or ups-fcn"
                                          + missing_lights_hint(os.path.dirname(os.fspath(lights_file))))
        raise PsctlError(None, f"{method} needs light directions (lights=None); method='sdps' estimates them "
                               "(or ups-fcn)")
    return method, None


def _saturated(images) -> np.ndarray | None:
    """[N, H, W] bool: integer images' values at their type's top code in a channel that
    ``as_images`` keeps (saturated; the light fit leaves them out, as it does a capture
    folder's), or None for float images, which cannot tell (and for what ``as_images`` refuses)."""
    from psctl.arrays import plain

    try:
        raw = np.asarray(plain(images))
    except (TypeError, ValueError, RuntimeError):
        return None
    if raw.dtype.kind not in "iu" or raw.ndim < 3:
        return None
    if raw.ndim == 4:  # an alpha channel is no light's: grey + alpha reads grey, RGBA reads RGB
        raw = raw[..., :1] if raw.shape[-1] in (1, 2) else raw[..., :3]
    top = raw >= np.iinfo(raw.dtype).max
    return top.any(-1) if raw.ndim == 4 else top


def _warn_value_notes(notes: list[str], who: str, level: int) -> None:
    """The notes of values a network run changed (hot pixels clamped; LCNet's exposure guard's
    scale) as warnings at the caller's ``level`` (its public function's): a folder's report carries
    them, and array callers of LCNet got silence (helper-172)."""
    from psctl.hotpixels import HOT_PIXEL_WORDS
    from psctl.lights import EXPOSURE_WORDS

    for note in notes:
        if HOT_PIXEL_WORDS in note or EXPOSURE_WORDS in note:
            warnings.warn(f"{who}: {note}", PsctlWarning, stacklevel=level + 1)  # + this function's frame


def estimate_lights(images: np.ndarray, mask: np.ndarray | None = None, weights: str | os.PathLike | None = None,
                    decode: str = "soft", device: str = "auto", views: int = 8,
                    refine: bool = True, falloff: str | None = None,
                    roll: bool | None = None, precision: str = "float32",
                    snap: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Light directions and relative intensities from arrays (LCNet, uncalibrated).

    Args:
        images: [N, H, W, 3] (or [N, H, W] grey) linear images as captured, not divided by any
            light intensity; float on the scale psctl reads files at (integer value / (2^bits -
            1)), or uint8 / uint16 arrays, which are scaled so. LCNet depends on that scale; a
            capture far outside its training exposures is rescaled for it (the exposure guard,
            docs/uncalibrated.md). Only integer arrays show which values are saturated (at the
            top code), which the light fit leaves out as ``psctl lights`` does; float arrays keep
            them in (the cropped ball: light error 1.78 degrees against 1.66, helper-192).
        mask: [H, W] bool or numbers (above 0.5 is the object; None: LCNet and the light fit
            read the object found without it (by brightness, or by shading before a lit
            background: ``psctl.masks.find_object``), and a warning
            says so).
        weights: an LCNet weights file (default: the installed weights/lcnet.pt).
        decode: "soft" (soft-argmax over the classes, the default) or "argmax" (the paper's: bin centres).
        device: auto | cpu | cuda.
        views: symmetric views averaged, 1, 2, 4 or 8 (the default: the images turned and
            mirrored about the view axis, estimates turned back and averaged; 1 is the paper's
            single pass; docs/uncalibrated.md).
        refine: when a normals network is installed (PS-FCN†, PS-FCN or PS-FCN+N), refine
            LCNet's lights against the normals it gives from them (as ``psctl lights``;
            ``psctl.refine.refine_lights``); without one, LCNet's lights.
        falloff: the refinement's shading model, "shifted" or "lambertian" (None: the default,
            ``psctl.refine.DEFAULT_REFINE``; docs/uncalibrated.md, "Falloff").
        roll: turn the refined lights about the view axis by the roll that makes the normals they
            give most integrable (``psctl.refine.roll_estimate``; None: the default,
            ``DEFAULT_REFINE["roll"]``; docs/uncalibrated.md, "Roll from integrability").
        precision: the refinement's normals network: "float32" (the default), "bf16" or "fp16"
            (as ``estimate_normals``); LCNet runs in float32.
        snap: LCNet and the light fit read ``mask`` snapped to the object (``psctl.masks.snap_mask``:
            a mask drawn wider than the object puts LCNet's lights far off), with a warning when
            it leaves out over 2% of it, or when it keeps a mask as given that looks drawn wider
            before a background that is not one plane (``psctl.masks.unsure_note``); False: the mask as given (an exact mask whose object
            has a face that shades as the background does; docs/uncalibrated.md).
    Returns:
        directions [N, 3] float32 unit vectors (x right, y up, z toward the camera) and
        intensities [N] float32 (relative; LCNet's scale, in [0.2, 2.0] before refinement).
    """
    from psctl.arrays import as_images, as_mask
    from psctl.lights import array_lights, check_decode, few_lights_note
    from psctl.masks import array_shading, array_snap, find_object
    from psctl.refine import refine_config
    from psctl.models.weights import installed_path
    from psctl.sdps import array_source, second_stage

    from psctl.models import check_precision, precision_autocast

    from psctl.symmetry import check_views

    fit = refine_config(falloff, roll)
    refine, snap = check_bool("refine", refine), check_bool("snap", snap)
    check_precision(precision)  # a bad name is an error with refine=False too
    decode = check_decode(decode)  # before the weights load and the mask snap (helper-172: 1.6 s, then the error)
    check_views(views)
    check_device_name(device)
    refines = refine and any(installed_path(m) is not None for m in SDPS_SECOND)
    # the refinement's normals network; checked before any work (not where none will run)
    net_cfg = {"device": device, "autocast": precision_autocast(precision, device) if refines else None}
    saturated = _saturated(images)
    images = as_images(images)
    mask = as_mask(mask, images.shape[1:3])
    found = None if mask is not None else find_object(*array_shading(images))
    fit_mask, snapped = (found.mask, None) if found is not None else array_snap(images, mask) if snap else (mask, None)
    if snapped:
        warnings.warn(f"estimate_lights: mask: {snapped}", PsctlWarning, stacklevel=caller_level())
    used = {} if found is None or found.mask is None else {"exposure_pixels": "found"}  # the notes' words
    net_cfg.update(used)
    est = array_lights(images, fit_mask, weights, {"device": device, "decode": decode, "views": views, **used})
    _warn_value_notes(est.notes, "estimate_lights", caller_level())
    few = few_lights_note(len(images))
    if few:  # (a folder's report notes it)
        warnings.warn(f"estimate_lights: {few}", PsctlWarning, stacklevel=caller_level())
    if found is not None:  # as a folder without mask.png is noted (a QA helper: 1.75 -> 19.78 degrees, silently)
        _warn_found(found, "estimate_lights", caller_level())
    # as run_lights' notes: a warning, not silence (the refinement's options, and its network's precision)
    given = {"falloff": falloff, "roll": roll, "precision": precision}
    unused = [k for k, _ in unused_options("sdps", refines, 1, 1, "float32", falloff, roll)]
    unused += ["precision"] if not refines and precision != "float32" else []
    if unused:
        level = caller_level()
        why = "the refinement's, and refine=False" if not refine else \
            "the refinement's, and no normals network is installed to refine with: PS-FCN†, PS-FCN or PS-FCN+N"
        warnings.warn(f"estimate_lights: {', '.join(f'{k}={given[k]!r}' for k in unused)} unused ({why})",
                      PsctlWarning, stacklevel=level)
    if refines:
        # no normals returned: the network too reads the found object only (as a mask would make it)
        source = array_source(images, fit_mask, sdps_second_stage(None)[0], None, net_cfg, saturated)
        est = second_stage(source, est, True, fit, normals=False)[0]
    return est.directions, est.intensities


def estimate_normals(images: np.ndarray, lights: np.ndarray | None, mask: np.ndarray | None = None,
                     method: str = "l2", weights: str | os.PathLike | None = None,
                     device: str = "auto", lcnet: str | os.PathLike | None = None, views: int = 1,
                     refine: bool = True, falloff: str | None = None, roll: bool | None = None,
                     light_distance: float | None = None, downsample: int = 1,
                     precision: str = "float32", snap: bool = True) -> np.ndarray:
    """Normals from arrays.

    Args:
        images: [N, H, W, 3] (or [N, H, W] grey) linear images, already divided by light
            intensities (sdps: as captured; it estimates the intensities); float on the scale
            psctl reads files at (integer value / (2^bits - 1)), or uint8 / uint16 arrays, which
            are scaled so (``psctl.arrays.as_images``).
        lights: [N, 3] light directions, x right / y up / z toward the camera, normalised here
            (None for ups-fcn and sdps, which do not use them).
        mask: [H, W] bool, or numbers (above 0.5 is the object); normals outside are 0. None:
            l2 the whole image (a pixel dark in every image, as a black background's, gets
            (0, 0, 1): facing the camera); the network methods read the object ``psctl.masks.find_object``
            finds by brightness before a dark background (``FoundObject.normals_mask``) and give
            normals on it and ``psctl.infer.FOUND_GROW`` pixels around it (0 beyond), else the
            whole image (warnings say which); sdps' LCNet and light fit read any object found.
        method: "l2", "ps-fcn", "ps-fcn-n", "ensemble" (the unit mean of PS-FCN's and PS-FCN+N's
            normals), "ups-fcn", "sdps" or "auto".
        weights: a weights file for the network methods (default: the installed ones; for sdps
            the PS-FCN† file).
        device: auto | cpu | cuda, for the network methods.
        lcnet: sdps: the LCNet weights file (default: the installed one).
        views: network methods: average 1, 2, 4 or 8 symmetric views of the capture (turned and
            mirrored about the view axis; ``views`` times the work; docs/models.md).
        refine: sdps: refine LCNet's lights against the first normals and run the second stage
            again (``psctl.refine.refine_lights``; docs/uncalibrated.md, "Light refinement").
        falloff: sdps: the refinement's shading model, "shifted" or "lambertian" (None: the
            default, ``psctl.refine.DEFAULT_REFINE``).
        roll: sdps: turn the refined lights and the normals about the view axis by the normals'
            roll (``psctl.refine.roll_estimate``; None: the default, ``DEFAULT_REFINE["roll"]``).
        light_distance: l2, ps-fcn, ps-fcn-n, ensemble: the lights are points this many pixels
            from the mask's centroid (mask=None: the networks' object found, else the frame's) along ``lights``; each image is divided by its light's
            falloff first (``psctl.nearlight``, docs/near-lights.md).
        downsample: network methods: run the network on the capture shrunk by this whole
            factor (each k x k block's mean over the mask), its normals interpolated back to
            full size (``psctl.infer.run_downsampled``): about 1/k^2 of the network's work, at a
            cost in accuracy wherever the surface has detail (docs/models.md, "Downsampling");
            1: full size.
        precision: network methods: "float32" (the default; on a GPU PyTorch runs its convolutions
            as TF32 where the GPU has it), "bf16" (an Ampere or newer GPU, or a CPU with native bf16: 1.6x faster end to end on a
            2-core AVX512-BF16 CPU, normals about 0.1 degrees from float32's on average; docs/models.md,
            "Precision") or "fp16" (CUDA).
        snap: sdps: its LCNet and light fit read ``mask`` snapped to the object (as
            ``estimate_lights``); False: as given. The other methods read the mask as given.
    Returns:
        [H, W, 3] float32 unit normals, x right / y up / z toward the camera (row 0 the top), 0
        outside the mask (mask=None: see ``mask``).

    Images may also be torch tensors or lists of [H, W, 3] images; [N, H, W, 1] is grey and an
    alpha channel is dropped (``psctl.arrays.as_images``). Bad input raises ``psctl.PsctlError``
    (a ValueError) naming the argument; what a folder's report would note is a ``PsctlWarning``.
    """
    from psctl.refine import refine_config

    from psctl.arrays import as_images, as_lights, as_mask, check_not_black, lights_behind, n_rows
    from psctl.models import check_downsample, check_precision, precision_autocast
    from psctl.symmetry import check_views

    fit = refine_config(falloff, roll)  # a bad value stops before any work, whatever the method
    refine, snap = check_bool("refine", refine), check_bool("snap", snap)
    check_device_name(device)  # typos are errors for l2 too, which uses neither
    precision = check_precision(precision)
    views = check_views(views)
    downsample = check_downsample(downsample)
    net_cfg = {"device": device, "views": views, "downsample": downsample}
    raw_images = images  # (for the saturated map: sdps' light fit leaves those pixels out)
    images = as_images(images, n_rows(lights))
    mask = as_mask(mask, images.shape[1:3])
    lights = as_lights(lights, images.shape[0])
    check_not_black(images, mask)
    method, _ = resolve_method(method, calibrated=lights is not None, weights=weights, lcnet=lcnet)
    # after method resolves: auto and 'SDPS' are sdps without lights too (an audit found them reading the
    # saturated pixels that method='sdps' left out)
    saturated = _saturated(raw_images) if method == "sdps" else None
    if method != "l2":
        net_cfg["autocast"] = precision_autocast(precision, device)  # bf16 this CPU would emulate: before any work
    if lights is not None and method not in LISTED_LIGHTS:  # they would be dropped without a word
        raise PsctlError(None, f"lights: {method} does not use given light directions ("
                               + ("it estimates them" if method == "sdps" else "it works without them")
                               + "); pass lights=None, or use l2, ps-fcn, ps-fcn-n or ensemble")
    if light_distance is not None and method not in LISTED_LIGHTS:
        raise PsctlError(None, f"light_distance: {method} on arrays does not read listed light directions, which "
                               f"the falloff follows; use l2, ps-fcn, ps-fcn-n or ensemble (or psctl.run_normals "
                               f"on a folder)")
    level = caller_level()
    found = None  # mask=None: the object the networks (sdps: LCNet and the light fit too) read
    if mask is None and method != "l2":
        from psctl.masks import array_shading, find_object

        found = find_object(*array_shading(images), reader="normals" if method != "sdps" else "sdps")
        _warn_found(found, method, level)
    read = _networks_read(found, mask)
    if light_distance is not None:
        from psctl.nearlight import near_lights

        h, w = images.shape[1:3]
        near = near_lights(light_distance, np.ones((h, w), bool) if read is None else read, found=read is not mask)
        rows, cols = np.arange(h), np.arange(w)
        images = np.stack([img * near.correction(lt, rows, cols)[..., None] for img, lt in zip(images, lights)])
    if lights is None and method in ("sdps", "ups-fcn") and len(images) < 3:  # as run_normals' note
        warnings.warn(few_images_note(method, len(images)), PsctlWarning, stacklevel=level)
    behind = None if lights is None else lights_behind(lights, lambda idx: ", ".join(f"lights[{i}]" for i in idx))
    if behind:  # as a folder's light file gets a note (an audit: arrays got none)
        warnings.warn(f"lights: {behind}", PsctlWarning, stacklevel=level)
    net_cfg.update(_found_config(found))
    if found is not None and found.normals_mask is not None:
        warnings.warn(f"{method}: mask=None: {_found_file_note(False)}", PsctlWarning, stacklevel=level)
    # options the method does not use: run_normals notes them; here, a warning, not silence
    unused = unused_options(method, refine, views, downsample, precision, falloff, roll, snap)
    if unused:
        given = {"views": views, "downsample": downsample, "precision": precision, "refine": refine,
                 "falloff": falloff, "roll": roll, "snap": snap}
        unused.sort(key=lambda kw: list(given).index(kw[0]))
        why = list(dict.fromkeys(UNUSED_WHY[w] for _, w in unused))
        warnings.warn(f"{method}: {', '.join(f'{k}={given[k]!r}' for k, _ in unused)} unused ({'; '.join(why)})",
                      PsctlWarning, stacklevel=level)
    if method == "sdps":
        from psctl.lights import array_lights, few_lights_note
        from psctl.masks import array_snap
        from psctl.sdps import array_source, sdps_lcnet_config, second_stage

        second = sdps_second_stage(weights)[0]
        # LCNet and the light fit: the object found, or the mask snapped to the object (snap_mask)
        fit_mask, snapped = (found.mask, None) if found is not None else array_snap(images, mask) if snap \
            else (mask, None)
        for note in (f"mask: {snapped}" if snapped else None, few_lights_note(len(images))):
            if note:
                warnings.warn(f"sdps: {note}", PsctlWarning, stacklevel=level)
        est = array_lights(images, fit_mask, lcnet, sdps_lcnet_config(second, weights, device))
        _warn_value_notes(est.notes, "sdps", level)
        source = array_source(images, read, second, weights, net_cfg, saturated, fit_mask)
        return second_stage(source, est, refine, fit)[1].normals
    if method in NETWORKS or method == "ensemble":
        from psctl.classic import lights_problem
        from psctl.infer import array_normals

        res = array_normals(images, lights, read, method, weights, net_cfg)
        if lights is not None and lights_problem(lights):  # no report here: a warning carries the note
            warnings.warn(undetermined_note(method, lights), PsctlWarning, stacklevel=level)
        _warn_value_notes(res.notes, method, level)  # values changed: a warning, as l2's below
        return res.normals
    if lights is None:
        raise PsctlError(None, f"{method} needs light directions")
    from psctl.classic import l2_normals
    from psctl.hotpixels import clamp_hot_pixels, hot_pixel_notes

    # as a folder's l2 and the networks: an isolated hot value set to its neighbours' level (a QA
    # helper's finding: on arrays it turned its pixel 42 degrees, where the folder's run gave 0.01)
    hot: dict[int, int] = {}

    def clamped() -> Iterator[np.ndarray]:
        for k, img in enumerate(images):  # masked first, as a folder's
            img, count = clamp_hot_pixels(img if mask is None else img * mask[..., None], mask)
            if count:
                hot[k] = count
            yield img

    normals = l2_normals(clamped(), lights, mask).normals
    for note in hot_pixel_notes({"hot_pixels": hot}, [f"image {k + 1}" for k in range(len(images))]):
        warnings.warn(f"l2: {note}", PsctlWarning, stacklevel=level)
    return normals


def ups_fcn_albedo_message(asked: str, weights: str | os.PathLike | None, calibrated: bool) -> str:
    """Why --albedo cannot run where ``asked`` (the --method given) resolved to ups-fcn, which
    estimates no lights, on a folder with (``calibrated``) or without light_directions.txt, and
    what would give it lights."""
    if str(asked).lower() == "ups-fcn":
        return "--albedo: ups-fcn estimates no lights, which the albedo needs; use " + (
            "l2, ps-fcn, ps-fcn-n or ensemble (the folder lists its lights)" if calibrated else
            "sdps (LCNet's lights) or a folder with light_directions.txt")
    if weights is not None:
        return "holds UPS-FCN weights, which estimate no lights, and --albedo needs them: give another --weights " \
               "file, or none (then auto chooses for each folder)"
    from psctl.models.weights import installed_path, weights_where

    need = f"LCNet's weights, lcnet.pt, in {weights_where()} (or --lcnet FILE)" if installed_path("lcnet") is None \
        else f"a second stage (PS-FCN†, PS-FCN or PS-FCN+N weights) in {weights_where()}"
    return (f"--albedo needs lights, and without light_directions.txt --method {asked} chose ups-fcn, which "
            f"estimates none: sdps (estimated lights) needs {need}; or add light_directions.txt")


def undetermined_note(method: str, lights: np.ndarray) -> str:
    """The note for a network given fewer than 3 images or (nearly) coplanar lights."""
    what = f"only {len(lights)} image(s)" if len(lights) < 3 else "the light directions are (nearly) coplanar"
    return (f"lights: {what}, which leaves the normals undetermined (l2 refuses them); {method} answers "
            "from what it learnt: expect large errors")


def few_images_note(method: str, n_images: int) -> str:
    """The note for a method without listed lights (sdps, ups-fcn) given fewer than 3 images."""
    return (f"images: only {n_images}, which leaves the normals undetermined; {method} answers from what it "
            "learnt: expect large errors")


UNUSED_WHY = {"l2": "l2 solves each pixel alone, at full size, in float64", "sdps": "only sdps refines lights",
              "refine": "sdps refines lights only with refine=True",
              "snap": "only sdps snaps the mask, for LCNet and its light fit"}


def unused_options(method: str, refine: bool, views: int, downsample: int, precision: str,
                   falloff: str | None, roll: bool | None, snap: bool = True) -> list[tuple[str, str]]:
    """The options ``method`` ignores, as (option, why), why a key of ``UNUSED_WHY``: "l2" (one
    pass at full size in float64), "sdps" (only sdps refines lights), "refine" (sdps without
    refinement). One table for run_normals' notes (``unused_note``) and estimate_normals' warning,
    which word it each their own way. ``refine`` False counts as asked for (its default is True)."""
    out = [(k, "sdps" if method != "sdps" else "refine") for k, v in (("falloff", falloff), ("roll", roll))
           if v is not None and (method != "sdps" or not refine)]
    if not refine and method != "sdps":
        out.append(("refine", "sdps"))
    if not snap and method != "sdps":  # --no-snap, like --no-refine, counts as asked for
        out.append(("snap", "snap"))
    if method == "l2":
        out += [(k, "l2") for k, off in (("views", views > 1), ("downsample", downsample > 1),
                                          ("precision", precision != "float32")) if off]
    return out


def unused_note(option: str, why: str, value: object = None) -> str:
    """A note for the command line (``psctl normals``, ``psctl lights``) on an option the method
    ignores (``unused_options``); ``value`` is the --precision asked for. ``psctl lights`` adds
    why "no-network" (--refine, but no normals network installed to refine with) and the option
    "precision-refine" (the refinement network's --precision)."""
    if option in ("falloff", "roll", "refine", "precision-refine"):
        flag = {"falloff": "--falloff", "roll": "--roll/--no-roll", "refine": "--no-refine",
                "precision-refine": "--precision"}[option]
        return f"lights: {flag} is unused " + {"refine": "without --refine",
                                               "no-network": "(no normals network is installed to refine with)",
                                               }.get(why, "(only sdps refines lights)")
    if option == "snap":
        return "mask: --no-snap is unused (only sdps snaps the mask, for LCNet and its light fit)"
    return {"views": "views: l2 gives the same normals in every view; one pass",
            "downsample": "downsample: l2 solves each pixel alone, at full size; unused",
            "precision": f"precision: l2 solves in float64; --precision {value} unused"}[option]


def run_normals(path: str | os.PathLike, method: str = "auto", out: str | os.PathLike | None = None,
                formats: tuple[str, ...] | list[str] = ("png16", "exr"), n_images: int | None = None,
                seed: int | None = None, write: bool = True,
                progress: ProgressFactory | None = None, weights: str | os.PathLike | None = None,
                device: str = "auto", lcnet: str | os.PathLike | None = None, views: int = 1,
                refine: bool = True, falloff: str | None = None, roll: bool | None = None,
                batch: "OutputBatch | None" = None, encoding: str = "auto",
                light_distance: float | None = None, arrays: dict | None = None, downsample: int = 1,
                precision: str = "float32", albedo: bool = False, snap: bool = True,
                reuse: dict | None = None) -> dict:
    """Run a method on a capture folder, write its outputs, return the report.

    Returns the dict printed by ``psctl normals --json``: object, path, method, calibrated,
    n_images, height, width, views, downsample, precision, light_distance, seconds, outputs, mae, median, within,
    mae_missing_as_90 (the MAE as the authors' code scores: mask pixels without ground truth at 90
    degrees), n_mask_pixels, n_evaluated_pixels, n_dark, albedo ({png_scale, median, n_undetermined} with
    ``albedo``, else None), written ({file: [bytes, mtime ns]} of the files written), notes and
    provenance (``psctl.api.provenance``), with an ``n_images`` subset also images_used, selection
    and seed (docs/formats.md has each key).
    Outputs (when ``write``): ``normal.png`` (16-bit), ``normal.exr`` and others per
    ``formats``, ``report.json``, and with ground truth ``error.png``. Default folder:
    ``PATH/psctl``. With the ensemble also ``spread.png``, the angle between its members'
    normals per pixel (``psctl.infer.member_spread``), and the report's "spread" (``spread_stats``).
    Either all files appear or none. ``weights`` (a file) and ``device`` (auto |
    cpu | cuda) are for the network methods; ``lcnet`` (a file) for sdps, whose report also has
    light_mae and intensity_re (None without ground-truth lights). ``views`` (1, 2, 4 or 8): the
    network methods average that many symmetric views of the capture (psctl.infer.run_views;
    ``views`` times the work). ``downsample`` (a whole number, 1: off): the network methods run on
    the capture shrunk by that factor, their normals interpolated back to full size
    (``psctl.infer.run_downsampled``). ``precision`` (the network methods; sdps: its second stage):
    "float32" (the default), "bf16" (an Ampere or newer GPU, or a CPU with native bf16) or "fp16"
    (CUDA), as ``psctl.estimate_normals``. ``refine`` (sdps): LCNet's lights are refined against the first
    normals and the second stage runs again (``psctl.refine.refine_lights``); the report's
    light_mae is then the refined lights' and lcnet_light_mae LCNet's own; ``falloff``
    ("shifted" or "lambertian", None: the default) is the refinement's shading model; ``roll``
    (None: the default) turns the refined lights and the normals about the view axis by the
    normals' roll (``psctl.refine.roll_estimate``). ``batch`` (``psctl.io.atomic.OutputBatch``):
    stage the files there, to appear with the other runs of the batch (``psctl eval --out``).
    The out folder holds one run's outputs: the files an earlier run of psctl normals wrote there
    (its list, OUTPUTS_LIST) that this run does not write (another ``formats``, no ground truth)
    are removed, and a note says so; no other file is. ``out`` may not hold a capture.
    ``encoding`` (auto | linear | srgb): how the images' values map to radiance
    (``psctl.io.capture.open_capture``; auto decodes files with an ICC profile through its tone curves,
    else JPEGs from sRGB, with a note).
    ``light_distance`` (pixels; l2, ps-fcn, ps-fcn-n, ensemble, sdps): the lights are points that far from
    the mask's centroid along the listed directions (sdps: LCNet's, refined or not, about the
    centroid of the object LCNet reads, found without a mask file, ``find_object``); each image is
    divided by its light's falloff (``psctl.nearlight``, docs/near-lights.md). sdps' LCNet reads
    the images as captured. Without a mask file the network methods (all but l2) read the object
    ``psctl.masks.find_object`` finds by brightness before a dark background and give normals
    on it and ``psctl.infer.FOUND_GROW`` pixels around it, else the whole frame (docs/models.md,
    "Without a mask"); it is written as ``mask_found.png`` and
    is the report's ``found_object``. ``arrays`` (a dict) receives the arrays behind the outputs: "normals"
    [H, W, 3], "mask" [H, W] (where normals are given), "error" [H, W] degrees (None without ground
    truth; 0 outside the pixels scored, NaN on mask pixels whose ground truth is zero or NaN, which
    the metrics leave out; without a mask file, a ground-truth pixel beyond the object found has no
    normal and scores 90), "scored" [H, W] (the pixels the error map covers: the mask, and there
    those ground-truth pixels), "found" [H, W] (the object found that the networks read, without the
    pixels around it; None with a mask file or where they read the whole frame), "spread"
    [H, W] degrees (None but for the ensemble) and "albedo" [H, W, 3] (None without ``albedo``).
    ``albedo``: also the albedo map from the normals, the lights (sdps: as estimated) and the
    images (``psctl.albedo``: per channel, the median of image / (n . l) over the images that
    light each pixel well; one more pass over the images), in each of ``formats``
    (``albedo.png``: an sRGB picture scaled to the report's ``albedo.png_scale``; ``albedo.exr``
    and ``albedo.npy``: linear values), and the report's "albedo" (None without it).
    ``snap`` (sdps; True): its LCNet and light fit read a mask file snapped to the object
    (``psctl.masks.snap_mask``); False: as given (--no-snap). The other methods read it as given.
    ``reuse`` (a dict kept across runs: each network's normals on each capture, held in memory):
    ps-fcn, ps-fcn-n and the ensemble's members take a network's normals from an earlier run on
    the same images (the same files, sizes and times), mask, lights, options and weights file
    instead of computing them again, with a note; each kept result is taken once, then let go
    (``psctl.infer.capture_normals``; psctl eval's comparisons pass a ``psctl.infer.KeptNormals``,
    which keeps no more than its budget).
    """
    from dataclasses import replace

    from psctl.classic import lights_problem
    from psctl.models import check_downsample, check_precision, precision_autocast
    from psctl.lights import SDPS_FILES
    from psctl.masks import FOUND_FILE, NO_MASK_PREFIX
    from psctl.refine import refine_config
    from psctl.symmetry import check_views
    from psctl.io.atomic import output_folder, staged_outputs
    from psctl.arrays import bounding_box
    from psctl.io.capture import (capture_notes, check_ground_truth_inside, ground_truth_error, load_ground_truth,
                                  load_mask, open_capture, select_images, selection_notes)
    from psctl.io.normals import ALBEDO_FORMATS, FORMATS, parse_formats, write_albedo_map, write_normal_map
    from psctl.io.report import write_error_map, write_json, write_spread_map

    t0, started = time.perf_counter(), time.time()  # started: for weights files replaced during the run
    for name, value in (("path", path), ("out", out), ("weights", weights), ("lcnet", lcnet)):
        check_path(name, value, optional=name != "path")  # before minutes of work, as every check here
    formats = parse_formats(check_formats(formats))
    if arrays is not None and not isinstance(arrays, dict):
        raise PsctlError(None, f"arrays must be a dict (it receives the arrays behind the outputs), not a "
                               f"{type(arrays).__name__}")
    progress = check_progress(progress)
    if batch is not None and not hasattr(batch, "stage"):  # psctl eval's own argument, public all the same
        raise PsctlError(None, f"batch must be a psctl.io.atomic.OutputBatch or None, not {type(batch).__name__}")
    fit = refine_config(falloff, roll)
    write, refine = check_bool("write", write), check_bool("refine", refine)  # "no" is truthy: never a yes
    snap = check_bool("snap", snap)
    want_albedo = check_bool("albedo", albedo)
    check_device_name(device)  # a typo is an error for l2 too, which does not use it
    precision = check_precision(precision)
    cap = open_capture(path, encoding)
    asked = method
    method, note = resolve_method(method, cap.calibrated, weights, lcnet, cap.path / "light_directions.txt")
    if want_albedo and method == "ups-fcn":
        raise PsctlError(weights, ups_fcn_albedo_message(asked, weights, cap.calibrated))
    if light_distance is not None and method not in (*LISTED_LIGHTS, "sdps"):
        raise PsctlError(None, f"--light-distance: {method} uses no light directions, which the falloff follows; "
                               f"use l2, ps-fcn, ps-fcn-n, ensemble or sdps")
    from psctl.nearlight import check_light_distance

    check_light_distance(light_distance)  # the number now; sdps finds where the lights sit with the object
    # an --images subset is spread over the light directions only where the method reads them
    by_lights = cap.calibrated and method in LISTED_LIGHTS
    picked = selection_notes(cap.n_images, n_images, seed, by_lights)
    n_all = cap.n_images
    cap = cap.subset(select_images(cap.n_images, n_images, seed, cap.lights if by_lights else None))
    notes = ([note] if note else []) + picked + capture_notes(cap)
    views, downsample = check_views(views), check_downsample(downsample)
    notes += [unused_note(k, why, precision) for k, why in
              unused_options(method, refine, views, downsample, precision, falloff, roll, snap)]
    if method == "l2" and check_device_name(device).startswith("cuda"):
        notes.append(f"device: l2 solves with NumPy on the CPU; --device {device} unused")
    if method == "l2":  # what l2 does whatever was asked (the notes above say so)
        views, downsample, precision = 1, 1, "float32"
    # bf16 this CPU would emulate: refused here, before any work
    net_cfg = {"device": device, "views": views, "downsample": downsample,
               "autocast": precision_autocast(precision, device)}
    if method == "l2":
        if not cap.calibrated:
            from psctl.io.capture import missing_lights_hint

            raise PsctlError(cap.path / "light_directions.txt", "missing: l2 needs calibrated light directions"
                                                                + missing_lights_hint(cap.path))
        problem = lights_problem(cap.lights)  # before any image is read
        if problem:
            raise PsctlError(cap.path if cap.n_images < 3 else cap.path / "light_directions.txt", f"l2: {problem}")
    elif method in LISTED_LIGHTS and cap.calibrated and lights_problem(cap.lights):  # a network answers anyway
        notes.append(undetermined_note(method, cap.lights))
    elif method in ("sdps", "ups-fcn") and cap.n_images < 3:  # no listed lights, the same shortage
        notes.append(few_images_note(method, cap.n_images))
    out_dir = output_folder(out, cap.path)
    names, light_files, stale, out_notes = _normals_outputs(method, cap, n_all, formats, want_albedo, write, out_dir,
                                                            weights, lcnet)
    notes += out_notes

    mask = load_mask(cap)
    try:
        gt = load_ground_truth(cap)
        if gt is not None:
            check_ground_truth_inside(gt, mask, cap.gt_path)  # before the work
    except PsctlError as e:  # a user without a good ground truth still wants the normals: say how
        raise ground_truth_error(e) from None
    memo = None  # the albedo's pass takes the images this one decodes, where they fit
    if want_albedo:
        from psctl.albedo import DEFAULT_ALBEDO
        from psctl.io.capture import DecodeMemo

        memo = DecodeMemo(DEFAULT_ALBEDO["memo_mb"] << 20)
    found = None  # without a mask file, the object the networks read (sdps: _sdps_normals finds it)
    if cap.mask_path is None and method in (*NETWORKS, "ensemble"):
        from psctl.infer import DEFAULT_INFER
        from psctl.io.capture import DecodeMemo
        from psctl.masks import capture_object

        if memo is None:  # the networks' pass takes the images the search decoded, where they fit
            memo = DecodeMemo(DEFAULT_INFER["cache_mb"] << 20)
        # (the search reads ahead as the networks' pass would)
        found = capture_object(cap, mask, {"prefetch_mb": DEFAULT_INFER["prefetch_mb"]}, progress, memo,
                               reader="normals")[2]
    read = _networks_read(found, mask)
    box = bounding_box(mask)
    near = None
    if light_distance is not None and method != "sdps":  # sdps: about the object LCNet reads (_sdps_normals)
        from psctl.nearlight import near_lights, near_note

        near = near_lights(light_distance, read, cap.mask_path, found=read is not mask)
        notes.append(near_note(near, "each image divided by its light's falloff; directions as listed"))
        cap = replace(cap, near=near)

    # --- solve -------------------------------------------------------------------------------
    light_stats = None
    spread = None  # the ensemble's members' disagreement, [H, W] degrees
    if method == "sdps":
        sd = _sdps_normals(cap, mask, light_distance, weights, lcnet, device, net_cfg, refine, fit, progress, memo,
                           snap)
        est, normals, dark, light_stats, near = sd.lights, sd.normals, sd.dark, sd.light_stats, sd.near
        from psctl.lights import one_sided_notes

        notes += sd.notes + one_sided_notes(est.directions)
        found, mask = sd.found, sd.mask
    elif method in NETWORKS or method == "ensemble":
        from psctl.infer import ENSEMBLE, capture_normals

        cfg = {**net_cfg, **_found_config(found)}
        net = capture_normals(cap, read, method, weights, cfg, progress, memo, reuse)
        normals, dark, spread = net.normals, net.dark, net.spread
        notes += ([] if found is None else [NO_MASK_PREFIX + n for n in found.notes]) + net.notes + (
            ["ensemble: the unit mean of the normals of " + " and ".join(ENSEMBLE)] if method == "ensemble" else [])
        mask = _normals_domain(read, cfg)
    else:
        normals, dark, l2_notes = _l2_normals(cap, mask, box, progress, memo)
        notes += l2_notes
    if not np.isfinite(normals).all():  # a bug, never a user error: fail loudly
        raise RuntimeError("internal error: non-finite normals")
    found_mask = None if found is None else found.mask
    if FOUND_FILE in names:  # no mask file: the object found is written, or none was (_normals_outputs)
        if found_mask is None:
            names.remove(FOUND_FILE)  # (before the note: stale() then counts an earlier one)
        notes += _found_file_notes(found_mask is not None, stale, out_dir) if write else []
    if found is not None and found.normals_mask is not None:
        notes.append(NO_MASK_PREFIX + _found_file_note(write))
    elif found_mask is not None and write:  # sdps: the object LCNet and the light fit read
        notes.append(f"{NO_MASK_PREFIX}the object found for LCNet and the light fit is in {FOUND_FILE}: check it; "
                     f"copied into the capture folder as mask.png, it is read as the mask")
    box = bounding_box(mask)
    if method in LISTED_LIGHTS:  # the light file's methods
        notes += mirror_notes(normals[box], mask[box])  # the box: the rest of the frame is background

    alb = albedo_stats = None
    if want_albedo:
        from psctl.lights import lit_capture

        lit = cap if method != "sdps" else lit_capture(replace(cap, near=near), est)  # the lights the normals used
        # the object found, not the ring around it (background there: no albedo to speak of)
        on = _networks_read(found, mask)
        alb, albedo_stats, alb_notes = _capture_albedo(lit, method, normals, dark, on, progress, memo)
        notes += alb_notes

    # --- evaluate ------------------------------------------------------------------------------
    scored = mask
    if found is not None and found.normals_mask is not None and gt is not None:
        # the object found may miss pixels the ground truth has: scored too, at 90 degrees (no
        # normal), else a search that found less would score better
        truth = np.isfinite(gt).all(-1) & (np.linalg.norm(np.nan_to_num(gt), axis=-1) > 0.5)
        scored = mask | truth
        missed = int((truth & ~mask).sum())
        if missed:
            from psctl.infer import FOUND_GROW

            notes.append(f"scoring: {missed} pixels with a ground-truth normal lie beyond the object found and the "
                         f"{FOUND_GROW} pixels around it: they have no normal and count at 90 degrees")
    error, stats, valid, eval_notes = _evaluate(normals, gt, scored, cap.gt_path, mask_file=cap.mask_path is not None)
    n_eval = 0 if valid is None else int(valid.sum())
    notes += eval_notes

    seconds = time.perf_counter() - t0
    report = {
        "object": cap.name,
        "path": os.path.abspath(cap.path),  # report.json is read from elsewhere
        "method": method,
        "calibrated": cap.calibrated,
        "n_images": cap.n_images,
        "height": cap.height,
        "width": cap.width,
        "seconds": round(seconds, 3),
        "outputs": {},
        "written": {},  # filled as the files are written
        **stats,
        "n_mask_pixels": int(mask.sum()),
        "n_evaluated_pixels": n_eval,
        "n_dark": int(dark.sum()),
        "views": views,
        "downsample": downsample,
        "precision": precision,
        "light_distance": None if near is None else near.distance,
        "notes": notes,
    }
    if spread is not None:
        report["spread"] = spread_stats(spread, mask, error, valid)
    report["albedo"] = albedo_stats
    if cap.n_images < n_all:  # an --images subset: which images, so that the run can be repeated
        from psctl.io.capture import selection_report

        report["images_used"] = [os.path.relpath(p, cap.path) for p in cap.image_paths]
        report.update(selection_report(seed, by_lights))
    if method != "l2":
        from psctl.infer import pick_device

        dev = str(pick_device(device))
    report["provenance"] = provenance(weights_used(method, weights, lcnet, sd.second if method == "sdps" else None),
                                      None if method == "l2" else dev, started)
    notes += provenance_notes(report["provenance"])  # report["notes"] is this list
    if light_stats is not None:
        report["second_stage"] = sd.second  # the network that turned LCNet's lights into normals
        report["lcnet_decode"] = sd.lcnet_config["decode"]
        report["lcnet_views"] = sd.lcnet_config["views"]
        report["light_mae"] = light_stats["light_mae"]
        report["intensity_re"] = light_stats["intensity_re"]
        report["lcnet_light_mae"] = sd.lcnet_stats["light_mae"]  # before refinement
        report["lcnet_intensity_re"] = sd.lcnet_stats["intensity_re"]
        report["lights_refined"] = est.info.get("refine")  # {quality, weight, ...} or None
    if method != "l2":  # the networks' object without a mask file (None with one)
        report["found_object"] = None if found is None else found.info

    if arrays is not None:
        arrays.update(normals=normals, mask=mask, error=error, spread=spread, albedo=None if alb is None else alb.albedo,
                      scored=scored, found=None if found is None else found.normals_mask)

    # --- write ---------------------------------------------------------------------------------
    if write:
        report["outputs"] = {_output_key(n): os.path.abspath(out_dir / n) for n in names}
        staging = staged_outputs(out_dir, stale) if batch is None else \
            contextlib.nullcontext(batch.stage(out_dir, stale).path)
        with staging as stage:
            write_outputs_list(stage, names, "normals")
            for f in formats:
                write_normal_map(stage / FORMATS[f], normals, mask, f)
                if alb is not None:
                    write_albedo_map(stage / ALBEDO_FORMATS[f], alb.albedo, mask, f, albedo_stats["png_scale"])
            label = f"{report['object']}  {report['method']}"  # which run: pictures get compared side by side
            if error is not None:
                write_error_map(stage / "error.png", error, scored, stats["mae"], stats["median"], label=label)
            if spread is not None:
                write_spread_map(stage / "spread.png", spread, mask, report["spread"]["mean"], report["spread"]["p90"],
                                 label=label)
            if found_mask is not None:
                from psctl.io.images import write_image

                write_image(stage / FOUND_FILE, found_mask.astype(np.float32), "uint8", kind="data")
            if light_files:
                from psctl.lights import image_list, write_light_files, write_lights_plot

                write_light_files(stage, est.directions, est.intensities, SDPS_FILES)
                write_lights_plot(stage / SDPS_FILES["lights"], est.directions, est.intensities, cap.lights,
                                  light_stats["light_mae"], cap.name)
                if SDPS_FILES["light_images"] in light_files:  # one row per image used, in this order
                    (stage / SDPS_FILES["light_images"]).write_text(image_list(cap), encoding="utf-8")
            # each file as written (bytes, modification time in ns: kept by the rename), so that a
            # later command can tell this run's files from ones replaced since (psctl depth's colours)
            report["written"] = {n: [st.st_size, st.st_mtime_ns] for n in names if n != "report.json"
                                 for st in [os.stat(stage / n)]}
            report["seconds"] = round(time.perf_counter() - t0, 3)  # report.json and the return agree
            write_json(stage / "report.json", report)
    return report


def _normals_outputs(method: str, cap: "Capture", n_all: int, formats: list[str], want_albedo: bool, write: bool,
                     out_dir: "Path", weights: str | os.PathLike | None,
                     lcnet: str | os.PathLike | None) -> tuple[list[str], list[str], Callable[[], list[str]], list[str]]:
    """The files a psctl normals run writes into ``out_dir``: (names, light_files: sdps' among
    them, stale: () -> an earlier run's files there that this one removes, notes). With ``write``,
    ``out_dir`` is checked here, before any work: no capture's inputs, no file the run reads,
    no folder in the way of an output."""
    from psctl.io.atomic import check_inputs_kept, check_output_dir
    from psctl.io.capture import check_not_capture
    from psctl.io.normals import ALBEDO_FORMATS, FORMATS
    from psctl.lights import SDPS_FILES
    from psctl.masks import FOUND_FILE

    notes: list[str] = []
    # report.json always: without ground truth it still records the method, notes and timings
    # sdps: the lights its normals came from (with an --images subset, the images they belong to)
    light_files = [] if method != "sdps" else \
        [SDPS_FILES[k] for k in ("light_directions", "light_intensities", "lights")] + \
        ([SDPS_FILES["light_images"]] if cap.n_images < n_all else [])
    if write and SDPS_FILES["light_images"] in light_files:
        notes.append(f"images: the estimated light files have {cap.n_images} rows, one per image listed in "
                     f"{SDPS_FILES['light_images']}")
    names = [FORMATS[f] for f in formats] + ([ALBEDO_FORMATS[f] for f in formats] if want_albedo else []) + \
        (["error.png"] if cap.gt_path else []) + \
        (["spread.png"] if method == "ensemble" else []) + light_files + \
        ([FOUND_FILE] if method != "l2" and cap.mask_path is None else []) + ["report.json"]  # (if one is found)
    # every file psctl normals may write
    all_names = (*FORMATS.values(), *ALBEDO_FORMATS.values(), "error.png", "spread.png", *SDPS_FILES.values(),
                 FOUND_FILE, "report.json")
    given = {os.path.realpath(p) for p in (weights, lcnet, *cap.input_paths) if p is not None}

    def stale(listed: list[str] | None = None) -> list[str]:
        # psctl's own files from an earlier run there (its list says which) that this run does not
        # write; never the files this run reads (an image listed by its path in an output folder).
        # Asked again at the commit, under the folder's lock: a run that wrote there meanwhile
        # has its own list by then (two runs into one folder at once, an interruption audit)
        listed = read_outputs_list(out_dir, "normals") if listed is None else listed
        return sorted(n for n in listed if n in all_names and n not in names and (out_dir / n).is_file()
                      and os.path.realpath(out_dir / n) not in given)

    if write:
        check_not_capture(out_dir, cap, names)  # normal.png there would be read as ground truth next time
        check_inputs_kept(out_dir, names, (("--weights", weights), ("--lcnet", lcnet)))
        check_output_dir(out_dir)
        listed = read_outputs_list(out_dir, "normals")  # read once here: for the note on removals and the one below
        # mask_found.png: where this run may write one, whether it does is known only after the
        # search (_found_file_notes); otherwise an earlier one goes now and is named here
        removed = [n for n in stale(listed) if n != FOUND_FILE or FOUND_FILE not in names]
        if removed:
            notes.append(f"outputs: removed {', '.join(removed)}, left in {out_dir} by an earlier psctl run "
                         "(a folder holds one run's outputs)")
        for n in names:  # a folder in the way would fail the run only after its work
            if os.path.lexists(out_dir / n) and not ((out_dir / n).is_file() or (out_dir / n).is_symlink()):
                raise PsctlError(out_dir / n, "is in the way of an output file (it is not a file); move it away "
                                              "or choose another --out")
        # not psctl's (or from a psctl without the list); the found object's file: after the search
        notes += replaced_notes(out_dir, [n for n in names if n != FOUND_FILE], "normals", listed)
        notes += _depth_left_notes(out_dir, names + removed)
    return names, light_files, stale, notes


def _depth_left_notes(out_dir: "Path", replaced: list[str]) -> list[str]:
    """A note when psctl depth's outputs in ``out_dir`` (both commands default to PATH/psctl) were
    integrated from a normal map this run replaces or removes: they stay, and would read as the
    surface of the new normals (a helper's finding: an l2 mesh beside ps-fcn-n's normals)."""
    from psctl.io.atomic import read_report

    depth = [n for n in read_outputs_list(out_dir, "depth") if (out_dir / n).is_file()]
    source = (read_report(out_dir / "depth_report.json") or {}).get("normals") if depth else None
    if not isinstance(source, str) or "\0" in source:  # (realpath raises on a NUL byte)
        return []
    hit = [n for n in replaced if os.path.realpath(out_dir / n) == os.path.realpath(source)]
    return [f"outputs: {', '.join(depth)} in {out_dir} stay, integrated by psctl depth from the earlier {hit[0]}: "
            f"run psctl depth again for these normals' surface"] if hit else []


def _found_file_notes(written: bool, stale: Callable[[], list[str]], out_dir: "Path") -> list[str]:
    """The notes on mask_found.png that _normals_outputs leaves to after the object search:
    replacing a user's own file of that name (``written``), or removing an earlier run's."""
    from psctl.io.atomic import replaced_notes
    from psctl.masks import FOUND_FILE

    if written:  # one psctl lights wrote there is psctl's too (the same search): replaced without a word
        listed = read_outputs_list(out_dir, "normals") + read_outputs_list(out_dir, "lights")
        return [n for n in replaced_notes(out_dir, [FOUND_FILE], "normals", listed) if FOUND_FILE in n]
    if FOUND_FILE in stale():
        return [f"outputs: removed {FOUND_FILE}, left in {out_dir} by an earlier psctl run (this one read no object "
                f"found: none was, or the networks read the whole frame)"]
    return []


def _l2_normals(cap: "Capture", mask: np.ndarray, box: tuple, progress: ProgressFactory,
                memo: "DecodeMemo | None") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """l2 on a capture folder, streamed image by image: (normals [H, W, 3], dark [H, W], notes)."""
    from psctl.classic import L2Accumulator
    from psctl.hotpixels import clamp_hot_pixels, hot_pixel_notes
    from psctl.io.capture import ImageCheck, iter_images

    acc = L2Accumulator(mask[box])
    advance = progress(f"{cap.name}: reading + l2", cap.n_images)
    check = ImageCheck(cap)  # black images, negative values: notes
    hot: dict[int, int] = {}
    for k, img in enumerate(iter_images(cap, box, clipped=check.clipped_reader(mask, box), memo=memo,
                                        ceiling=check.ceiling_reader(mask, box))):
        check.see(k, img[mask[box]])
        # as the networks do: a hot value gives its own pixel a normal toward that image's light (66
        # degrees off in test_l2's sphere) and an albedo thousands of times the rest
        inside = mask[box]
        img, count = clamp_hot_pixels(img * inside[..., None], inside)  # masked first, as the networks'
        if count:
            hot[k] = count
        acc.add(img, cap.lights[k])
        advance(1)
    res = acc.solve()
    if res.dark[mask[box]].all():  # as the network methods: nothing to estimate from
        raise PsctlError(cap.path, "all images are black inside the mask")
    normals = np.zeros((cap.height, cap.width, 3), np.float32)
    normals[box] = res.normals
    dark = np.zeros(mask.shape, bool)
    dark[box] = res.dark
    return normals, dark, check.notes() + hot_pixel_notes({"hot_pixels": hot}, [p.name for p in cap.image_paths])


@dataclass
class _SdpsRun:
    """What sdps gave a capture folder: the report's parts beside the normals."""
    lights: "LightEstimate"  # as the second stage last used them (refined or not)
    normals: np.ndarray  # [H, W, 3]
    dark: np.ndarray  # [H, W] bool
    notes: list[str]
    second: str  # the second stage's method
    lcnet_config: dict  # how LCNet ran (decode, views)
    lcnet_stats: dict  # LCNet's own lights against the folder's: light_mae, intensity_re (None without)
    light_stats: dict  # the lights the normals came from, likewise
    found: "FoundObject | None"  # without mask.png, the object LCNet, the light fit and the networks read (None: a mask file)
    near: "NearLights | None"  # the lights' distance and centre (the object LCNet reads)
    mask: np.ndarray  # [H, W] bool, where the normals are given (_normals_domain)


def _warn_found(found: "FoundObject", who: str, level: int) -> None:
    """mask=None on arrays: what ``psctl.masks.find_object`` found for LCNet and the light fit,
    warned as ``who``'s (a folder's report notes it)."""
    for note in found.notes:
        warnings.warn(f"{who}: mask=None: {note}", PsctlWarning, stacklevel=level + 1)


def _sdps_normals(cap: "Capture", mask: np.ndarray, light_distance: float | None,
                  weights: str | os.PathLike | None, lcnet: str | os.PathLike | None, device: str, net_cfg: dict,
                  refine: bool, fit: dict, progress: ProgressFactory, memo: "DecodeMemo | None",
                  snap: bool = True) -> _SdpsRun:
    """sdps on a capture folder: LCNet's lights, the second stage, the refinement (``refine``,
    ``fit``); ``light_distance``: the lights' distance from the centre of the object LCNet reads
    (the mask, or the one found without it), whose falloff the second stage divides out."""
    from dataclasses import replace

    from psctl.infer import DEFAULT_INFER, first_read_box
    from psctl.io.capture import DecodeMemo
    from psctl.lights import capture_lights, light_errors
    from psctl.masks import NO_MASK_PREFIX, capture_object
    from psctl.refine import lights_changed
    from psctl.nearlight import near_lights, near_note
    from psctl.sdps import capture_source, sdps_lcnet_config, second_stage

    second = sdps_second_stage(weights)[0]
    lc_cfg = sdps_lcnet_config(second, weights, device)
    if memo is None:  # every pass takes the images LCNet's decoded, where they fit
        memo = DecodeMemo({**DEFAULT_INFER, **net_cfg}["cache_mb"] << 20)
    # LCNet, the light fit and the second stage read the object (found without a mask file)
    fit_mask, lc_cfg, found, snapped = capture_object(cap, mask, lc_cfg, progress, memo, reader="sdps", snap=snap)
    net_cfg = {**net_cfg, **_found_config(found)}
    found_notes = [] if found is None else [NO_MASK_PREFIX + n for n in found.notes]
    found_notes += [f"mask: {snapped}"] if snapped else []
    # the centre of the user's mask (as the calibrated methods take it), not of the snapped one
    near = near_lights(light_distance, fit_mask if found is not None else mask, cap.mask_path,
                       found=found is not None and found.mask is not None)
    if near is not None:
        found_notes.append(near_note(near, "each image divided by its light's falloff; directions as estimated "
                                           "(LCNet reads the images as captured)"))
    read = _networks_read(found, mask)  # the second stage's
    est = capture_lights(cap, fit_mask, lcnet, lc_cfg, progress, flag="--lcnet", memo=memo,
                         keep_box=first_read_box(cap, read, net_cfg))
    gt_ints = cap.intensities if cap.intensities_given else None
    lcnet_stats = light_errors(est.directions, est.intensities, cap.lights, gt_ints)
    source = capture_source(replace(cap, near=near), read, second, weights, net_cfg, progress, memo, fit_mask)
    est, net = second_stage(source, est, refine, fit)
    notes = found_notes + list(dict.fromkeys(est.notes + net.notes))  # both stages may name a black image
    light_stats = light_errors(est.directions, est.intensities, cap.lights, gt_ints)
    if light_stats["light_mae"] is not None:
        refined = refine and lights_changed(est.info["refine"])
        notes.append(f"lights: direction error {light_stats['light_mae']:.2f}° (mean)" + (
            "" if light_stats["intensity_re"] is None else
            f", intensity relative error {light_stats['intensity_re']:.3f}") + (
            f"; LCNet alone {lcnet_stats['light_mae']:.2f}°" if refined else ""))
    return _SdpsRun(est, net.normals, net.dark, notes, second, lc_cfg, lcnet_stats, light_stats,
                    found, near, _normals_domain(read, net_cfg))


def _networks_read(found: "FoundObject | None", mask: np.ndarray | None) -> np.ndarray | None:
    """What the normals networks read: the object found without a mask file where they may read it
    (``FoundObject.normals_mask``), else ``mask`` (a mask file's, the whole frame, or None)."""
    return mask if found is None or found.normals_mask is None else found.normals_mask


def _found_config(found: "FoundObject | None") -> dict:
    """The networks' settings for the object found without a mask (``psctl.masks.find_object``):
    its mean for PS-FCN's exposure, as a mask's, and normals FOUND_GROW pixels beyond it; {} with
    a mask, or where none was found (the whole frame)."""
    from psctl.infer import FOUND_GROW

    return {} if found is None or found.normals_mask is None else {"exposure_pixels": "found", "grow": FOUND_GROW}


def _normals_domain(read: np.ndarray, config: dict) -> np.ndarray:
    """Where the networks give normals: the mask they read (``read``) grown by the config's
    ``grow`` (FOUND_GROW for the object found without a mask file, else 0 unless set)."""
    from psctl.infer import DEFAULT_INFER, check_grow, grow_mask

    return grow_mask(read, check_grow({**DEFAULT_INFER, **config}["grow"]))


def _found_file_note(write: bool) -> str:
    """What the normals of a capture without a mask file cover, and where the object found is."""
    from psctl.infer import FOUND_GROW
    from psctl.masks import FOUND_FILE

    return (f"the normals cover the object found and {FOUND_GROW} pixels around it (its dark rim, "
            f"which the search can miss; the networks answer there from the object beside it)" +
            (f"; the object is in {FOUND_FILE}: check it; copied into the capture folder as mask.png, it is read "
             f"as the mask (the normals then cover it alone)" if write else ""))


def _capture_albedo(lit: "Capture", method: str, normals: np.ndarray, dark: np.ndarray, mask: np.ndarray,
                    progress: ProgressFactory, memo: "DecodeMemo | None") -> tuple["AlbedoResult", dict, list[str]]:
    """The albedo of a capture whose lights (``lit``) the normals came from: (the albedo, the
    report's "albedo" {png_scale, median, n_undetermined}, notes)."""
    from psctl.albedo import albedo_png_scale, capture_albedo

    alb = capture_albedo(lit, np.where(dark[..., None], 0.0, normals), mask, progress=progress,
                         memo=memo)  # dark pixels: no normal
    undetermined = int(alb.undetermined.sum())
    determined = mask & ~alb.undetermined
    stats = {"png_scale": albedo_png_scale(alb.albedo, determined),
             "median": [float(v) for v in np.median(alb.albedo[determined], axis=0)] if determined.any() else None,
             "n_undetermined": undetermined}
    notes = []
    if undetermined:
        notes.append(f"albedo: {undetermined} of {int(mask.sum())} object pixels undetermined (no normal, no "
                     f"light in front of their normal, or black in every image that counts, docs/formats.md): "
                     f"0 in the albedo maps")
    if method == "sdps":
        notes.append("albedo: on the scale of the estimated intensities, one per image: known up to one "
                     "factor per channel (the lights' colour, which sdps does not estimate)")
    return alb, stats, notes


def _evaluate(normals: np.ndarray, gt: np.ndarray | None, mask: np.ndarray,
              gt_path: "Path | None", mask_file: bool = True) -> tuple[np.ndarray | None, dict, np.ndarray | None, list[str]]:
    """Normals [H, W, 3] against the ground truth (None: not scored): (the error map [H, W]
    degrees, 0 outside the mask and NaN where the ground truth has no normal; the summary
    (mae, median, within); the scored pixels [H, W]; notes). Without ground truth: None, the
    summary's keys with None, None, no notes. ``mask_file`` False: ``mask`` is no mask of the
    user's (the whole frame, or the pixels given a normal and the ground truth's where the object
    found was read): the authors' count over a mask has none to go by, so mae_missing_as_90 is
    None and no note is given (it counted the background at 90 degrees: examples/bumpy_sphere
    without its mask gave 16.55 beside an MAE of 1.38, and 34.66 with l2 on the whole frame)."""
    from psctl.io.capture import check_ground_truth_inside
    from psctl.metrics import angular_error, summarize

    if gt is None:
        return None, {"mae": None, "median": None, "within": {"11.25": None, "22.5": None, "30": None},
                      "mae_missing_as_90": None}, None, []
    check_ground_truth_inside(gt, mask, gt_path)
    valid = mask & (np.linalg.norm(gt, axis=-1) > 0.5)
    error = np.zeros(mask.shape, np.float32)
    error[mask & ~valid] = np.nan  # no ground truth there: the maps show it apart from 0 degrees
    error[valid] = angular_error(normals, gt, valid)
    stats = summarize(error[valid])
    # the authors' evaluation code scores every mask pixel, a zero ground truth at 90 degrees (its
    # dot product is 0): their published numbers hold those pixels, so the report gives both (a
    # NaN or short ground truth, which their code would turn into NaN or an angle, counts 90 here)
    n_missing, n_mask = int((mask & ~valid).sum()), int(mask.sum())
    stats["mae_missing_as_90"] = (stats["mae"] * (n_mask - n_missing) + 90.0 * n_missing) / n_mask \
        if mask_file else None
    notes = convention_notes(normals, gt, valid, stats["mae"], gt_path.name)
    if n_missing and mask_file:
        notes.append(f"scoring: {n_missing} of {n_mask} mask pixels have no ground-truth normal in {gt_path.name} "
                     f"(zero or NaN) and are not scored; at 90 degrees each, as the authors' evaluation code counts "
                     f"a zero normal, the MAE would be {stats['mae_missing_as_90']:.2f} (mae_missing_as_90)")
    return error, stats, valid, notes


OUTPUTS_LIST = outputs_list("normals")  # in an output folder: the files psctl normals wrote there last


def provenance(weights_used: dict[str, "str | os.PathLike | None"], device: str | None = None,
               started: float | None = None) -> dict:
    """What produced a result, for its report: psctl's, Python's, NumPy's and torch's versions
    (torch: None where it is not loaded), the device the networks ran on, and each weights file
    used by its role (``{"ps-fcn": PATH, ...}``) with its sha256, so that a report from before
    the weights were replaced still names the file that made it. The digest is taken now, at the
    report; ``started`` (``time.time()`` when the run began): a file modified since then gets
    ``"modified_during_run": true``, as its digest may not be what the run read."""
    import platform

    import psctl
    from psctl.models.weights import file_sha256

    def entry(p: "str | os.PathLike") -> dict:
        e = {"path": os.path.abspath(p), "sha256": file_sha256(p)}
        # after the start, and not in the future (a file dated ahead, clock skew: not a change)
        if started is not None and started < os.stat(p).st_mtime <= time.time():
            e["modified_during_run"] = True
        return e

    torch = sys.modules.get("torch")
    return {"psctl": psctl.__version__, "python": platform.python_version(), "numpy": np.__version__,
            "torch": None if torch is None else torch.__version__, "device": device,
            "weights": {role: entry(p) for role, p in weights_used.items() if p is not None}}


def provenance_notes(prov: dict) -> list[str]:
    """A note for each weights file of ``provenance`` modified while the run went on."""
    return [f"weights: {w['path']} was modified during the run; the report's sha256 is of the file as it is now, "
            f"which may not be what the run read" for w in prov["weights"].values() if w.get("modified_during_run")]


def weights_used(method: str, weights: "str | os.PathLike | None", lcnet: "str | os.PathLike | None" = None,
                 second: str | None = None) -> dict[str, "str | os.PathLike | None"]:
    """The weights files a resolved ``method`` reads, by role (``second``: sdps' second stage)."""
    from psctl.infer import ENSEMBLE
    from psctl.models.weights import installed_path

    if method == "ensemble":
        return {m: installed_path(m) for m in ENSEMBLE}
    if method == "sdps":
        stage = {m: installed_path(m) for m in ENSEMBLE} if second == "ensemble" else \
            {second: weights if weights is not None else installed_path(second)}
        return {"lcnet": lcnet if lcnet is not None else installed_path("lcnet"), **stage}
    if method == "l2":
        return {}
    return {method: weights if weights is not None else installed_path(method)}


def spread_stats(spread: np.ndarray, mask: np.ndarray, error: np.ndarray | None = None,
                 valid: np.ndarray | None = None) -> dict:
    """The report's "spread": mean, median and 90th percentile of ``spread`` [H, W] (degrees)
    over ``mask``; with ``error`` [H, W] (degrees) and ``valid`` [H, W] (the pixels scored
    against ground truth), the mean error of the scored pixels whose spread is above that
    percentile (``mae_top10``; where ties leave none above it, those at it) and of the others
    (``mae_rest``); None without them, or for a group with no scored pixel (a mask of a few
    pixels). An empty mask gives None throughout."""
    s = spread[mask].astype(np.float64)
    out = {"mean": None, "median": None, "p90": None, "mae_top10": None, "mae_rest": None}
    if not s.size:
        return out
    p90 = float(np.percentile(s, 90))
    out.update(mean=float(s.mean()), median=float(np.median(s)), p90=p90)
    if error is not None and valid is not None:
        e, v = error[mask].astype(np.float64), np.asarray(valid, bool)[mask]
        top = s > p90
        if not top.any():  # ties at the top (a flat spread): the pixels at the percentile
            top = s >= p90
        for key, sel in (("mae_top10", top & v), ("mae_rest", ~top & v)):
            out[key] = float(e[sel].mean()) if sel.any() else None
    return out


def mirror_notes(normals: np.ndarray, mask: np.ndarray) -> list[str]:
    """A note when the normals' mirror image is far more integrable than they are
    (``psctl.refine.mirror_ratio`` below MIRROR_NOTE): the light directions probably have an axis
    flipped."""
    from psctl.refine import MIRROR_NOTE, mirror_ratio

    r = mirror_ratio(normals, mask)
    if r is None or r >= MIRROR_NOTE:
        return []
    return [f"lights: these normals are {1 / r:.1f} times less integrable than their mirror image; is an axis of "
            "light_directions.txt flipped? psctl wants x right, y up (not down, as image rows), z toward the camera"]


def convention_notes(normals: np.ndarray, gt: np.ndarray, valid: np.ndarray, mae: float, gt_name: str) -> list[str]:
    """A note when the error says more about axes than about the method: ground truth whose normals
    point away from the camera, or normals that match the ground truth far better with x or y
    flipped (the light file or the ground truth uses another axis; psctl: x right, y up, z toward
    the camera)."""
    from psctl.metrics import angular_error

    notes = []
    if float(gt[valid][:, 2].mean()) < 0:
        notes.append(f"ground truth: {gt_name}'s normals point away from the camera on average (mean nz < 0); "
                     "psctl's z is toward the camera")
    # a good method's error says nothing about axes, nor a handful of pixels (a one-pixel mask)
    if mae > 10 and int(np.count_nonzero(valid)) >= 50:
        for axis, name in ((0, "x"), (1, "y")):
            flipped = gt.copy()
            flipped[..., axis] *= -1
            e = float(angular_error(normals, flipped, valid).mean())
            if e < mae / 2:
                notes.append(f"ground truth: these normals match {gt_name} with {name} flipped far better ({e:.1f} vs "
                             f"{mae:.1f} degrees): does the light file or the ground truth use {name} "
                             f"{'left' if axis == 0 else 'down'}? psctl wants x right, y up")
    return notes


def _output_key(filename: str) -> str:
    """normal.png -> normal_png, normal_8bit.png -> normal_8bit_png (the normal maps: one key per
    format); error.png -> error, spread.png -> spread, report.json -> report, sdps' light files
    light_directions_estimated.txt -> light_directions_estimated, ... (one file each)."""
    stem, ext = filename.rsplit(".", 1)
    return stem if stem in ("error", "spread", "report", "mask_found") or stem.endswith("_estimated") else \
        f"{stem}_{ext}"

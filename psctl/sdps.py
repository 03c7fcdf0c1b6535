"""sdps, the uncalibrated pipeline: LCNet's lights, the second stage's normals from them, the
lights refined against those normals, the second stage again, and the roll.

The sequence after LCNet is written once (``second_stage``) over a ``Source``: what sdps reads
its images from, in-memory arrays (``array_source``) or a capture folder streamed from disk
(``capture_source``). ``psctl.api`` (``estimate_normals``, ``estimate_lights``, ``run_normals``)
and ``psctl.lights.run_lights`` drive it; docs/uncalibrated.md describes each step.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from psctl.errors import PsctlError

if TYPE_CHECKING:
    from psctl.api import ProgressFactory
    from psctl.infer import InferResult
    from psctl.io.capture import Capture, DecodeMemo
    from psctl.lights import LightEstimate

# sdps (uncalibrated): LCNet estimates the lights (weights/lcnet.pt or --lcnet FILE), then PS-FCN†
# estimates the normals (weights/ps_fcn_dagger.pt or --weights FILE); LCNet's part is psctl/lights.py, the refinement's
# psctl/refine.py.
SDPS_NOTE = "sdps: lights estimated by LCNet, then normals by PS-FCN† (a light_directions.txt only scores the lights)"
# sdps's second stage, in order of preference: PS-FCN† was trained on LCNet's lights (the
# paper's choice); without it, a calibrated network runs on the estimated lights instead, PS-FCN
# before PS-FCN+N (on LCNet's lights it measured better on syntest and the dev split with every
# LCNet so far; docs/weights-history.md).
SDPS_SECOND = ("ps-fcn-dagger", "ps-fcn", "ps-fcn-n")
# True: with both calibrated networks installed (and no PS-FCN†), the average of their normals
# (psctl.infer.ENSEMBLE) is the second stage instead of PS-FCN alone. Off: by the second rule of
# benchmarks/ensemble.py it lost to PS-FCN alone (session 34: 20.67 vs 20.48 over three synthetic
# sdps sets); kept so that the rule can be rerun when the weights change
SDPS_ENSEMBLE = False
SHOWN = {"ps-fcn-dagger": "PS-FCN†", "ps-fcn-n": "PS-FCN+N", "ps-fcn": "PS-FCN", "lcnet": "LCNet",
         "ensemble": "the PS-FCN/PS-FCN+N average"}


def _elsewhere(shipped: str) -> str:
    """How to point psctl at weights, for a message: an installed wheel's copy hint, else the
    folder variable and what a clone ships."""
    from psctl.models.weights import ENV_VAR, install_hint

    return install_hint() or f"; set ${ENV_VAR} to use another folder; a clone of psctl ships {shipped} in weights/"


def sdps_second_stage(weights: str | os.PathLike | None = None, flag: str = "--weights for sdps") -> tuple[str, str]:
    """The network that estimates sdps's normals from LCNet's lights: (method, note for the user).

    ``weights`` (a file): PS-FCN† (psctl's or the authors' NENet), or psctl's PS-FCN / PS-FCN+N.
    None: the installed PS-FCN†, else PS-FCN, else PS-FCN+N; "ensemble" (the average of their
    normals) instead when both are installed and ``SDPS_ENSEMBLE`` is on (it ships off). Raises
    when there is none, or when the file holds another network (``flag`` names the option that
    passed it).
    """
    from psctl.models.weights import (file_name, installed_path, missing_folder_note, read_weights, source_files_note,
                                      weights_dir)

    if weights is not None:
        w = read_weights(weights)
        kind = w.method or w.metadata.get("kind")
        if w.official and kind == "ps-fcn" and w.lights:  # the authors' NENet has PS-FCN's keys
            kind = "ps-fcn-dagger"
        if kind not in SDPS_SECOND:
            raise PsctlError(weights, f"holds {SHOWN.get(kind, kind)} weights; {flag} takes "
                                      "PS-FCN† (or PS-FCN / PS-FCN+N) weights")
        method = kind
    else:
        have = [m for m in SDPS_SECOND if installed_path(m) is not None]
        if not have:  # LCNet alone: any of the three would do, so name them all
            where = weights_dir()
            raise PsctlError(None, f"sdps needs a normals network after LCNet (PS-FCN†, else PS-FCN or PS-FCN+N), and "
                                   f"none is installed (looked for {where / file_name('ps-fcn-dagger')}, "
                                   f"{where / file_name('ps-fcn')} and {where / file_name('ps-fcn-n')}"
                                   f"{missing_folder_note()}{_elsewhere('ps_fcn.pt')}). Train one with `psctl train "
                                   f"ps-fcn --config configs/ps_fcn.yaml --install` (a GPU is needed, see docs/training.md), or pass "
                                   f"{flag.split()[0]} FILE: psctl's PS-FCN†, PS-FCN or PS-FCN+N file, or the "
                                   f"authors' NENet (docs/uncalibrated.md){source_files_note()}")
        method = "ensemble" if SDPS_ENSEMBLE and have == ["ps-fcn", "ps-fcn-n"] else have[0]
    if method == "ps-fcn-dagger":
        return method, SDPS_NOTE
    # a file given on the command line was chosen by the user, whether or not PS-FCN† is installed
    why = f"from {weights}" if weights is not None else "PS-FCN†, trained on LCNet's lights, is not installed"
    return method, (f"sdps: lights estimated by LCNet, then normals by {SHOWN[method]} on those lights "
                    f"({why}; a light_directions.txt only scores the lights)")


def sdps_decode(method: str, weights: str | os.PathLike | None = None) -> str:
    """How sdps turns LCNet's classes into lights: the decoding the PS-FCN† file was trained on
    (its metadata ``lcnet.decode``), so it sees the kind of lights it learned from; argmax (the
    paper's) for the authors' files; soft-argmax for a calibrated second stage, which learned
    from continuous lights (sdps on syntest: 9.53 vs 9.83 degrees with argmax; weights/README.md)."""
    from psctl.models.weights import installed_path, read_weights

    if method != "ps-fcn-dagger":
        return "soft"
    path = weights if weights is not None else installed_path(method)
    lc = read_weights(path).metadata.get("lcnet") if path is not None else None
    return lc.get("decode", "argmax") if isinstance(lc, dict) else "argmax"


def sdps_lcnet_config(method: str, weights: str | os.PathLike | None, device: str) -> dict:
    """LCNet options for sdps (psctl.lights.DEFAULT_LIGHTS): the decoding of ``sdps_decode``;
    with argmax (a PS-FCN† trained on bin-centre lights, or the authors' file) one view, so that
    the second stage still gets bin centres; otherwise the default symmetric views."""
    from psctl.lights import DEFAULT_LIGHTS

    decode = sdps_decode(method, weights)
    return {"device": device, "decode": decode, "views": 1 if decode == "argmax" else DEFAULT_LIGHTS["views"]}


def check_sdps_weights(weights: str | os.PathLike | None = None, lcnet: str | os.PathLike | None = None) -> str:
    """Fail early, in one line, when sdps lacks weights: which files are missing and how to get
    them. Returns the note naming the second stage (``sdps_second_stage``)."""
    from psctl.models.weights import (file_name, installed_path, missing_folder_note, no_weights_error, read_weights,
                                      source_files_note, weights_dir)

    # a given file must hold what its flag is for, checked before minutes of LCNet work
    if lcnet is not None:
        w = read_weights(lcnet)
        kind = w.method or w.metadata.get("kind")
        if kind != "lcnet":
            raise PsctlError(lcnet, f"holds {SHOWN.get(kind, kind)} weights; --lcnet for sdps takes LCNet weights")
    second = weights is not None or any(installed_path(m) is not None for m in SDPS_SECOND)
    if lcnet is None and installed_path("lcnet") is None:
        if second:
            raise no_weights_error("lcnet", "--lcnet")
        where = weights_dir()
        raise PsctlError(None, f"sdps needs LCNet's weights and a normals network's (PS-FCN†, else PS-FCN or PS-FCN+N), "
                               f"and none is installed (looked for {where / file_name('lcnet')}, "
                               f"{where / file_name('ps-fcn-dagger')}, {where / file_name('ps-fcn')} and "
                               f"{where / file_name('ps-fcn-n')}{missing_folder_note()}"
                               f"{_elsewhere('lcnet.pt and ps_fcn.pt')}). Train them with `psctl train lcnet "
                               f"--config configs/lcnet.yaml --install` and `psctl train ps-fcn --config "
                               f"configs/ps_fcn.yaml --install` (docs/training.md), or pass --lcnet FILE and "
                               f"--weights FILE (docs/uncalibrated.md){source_files_note()}")
    return sdps_second_stage(weights)[1]


# --- the sequence after LCNet -----------------------------------------------------------------

@dataclass(frozen=True)
class Source:
    """Where sdps reads its images as captured (not divided by any intensity).

    normals(est) -> InferResult: the second stage on the images divided by est's intensities,
        with est's directions.
    refine(est, normals [H, W, 3], config) -> LightEstimate: est refined against the normals
        (``psctl.refine.refine_estimate``; config over DEFAULT_REFINE).
    mask: [H, W] bool or None (the whole image), where the light fit and the roll read the
        normals (the object: without a mask, the one ``psctl.masks.find_object`` found).
    """
    normals: Callable[["LightEstimate"], "InferResult"]
    refine: Callable[["LightEstimate", np.ndarray, "dict | None"], "LightEstimate"]
    mask: np.ndarray | None


def array_source(images: np.ndarray, mask: np.ndarray | None, method: str, weights: str | os.PathLike | None = None,
                 config: dict | None = None, saturated: np.ndarray | None = None,
                 fit_mask: np.ndarray | None = None) -> Source:
    """In-memory images [N, H, W, 3] float32 as captured; ``method`` (one of SDPS_SECOND, or
    "ensemble": the installed PS-FCN and PS-FCN+N averaged) and ``weights`` (None: installed) the
    second stage, ``config`` its run options (device, views); ``saturated`` [N, H, W] bool: the
    observations the light fit leaves out (integer images' top code). The normals cover
    ``mask``; the light fit and the roll read ``fit_mask`` (None: ``mask``), the object found
    in a capture without a mask."""
    fit_mask = mask if fit_mask is None else fit_mask
    from psctl.infer import array_normals
    from psctl.refine import refine_arrays

    def normals(est: "LightEstimate") -> "InferResult":
        return array_normals(images / est.intensities[:, None, None, None], est.directions, mask, method, weights,
                             config)

    def refine(est: "LightEstimate", n: np.ndarray, fit: dict | None) -> "LightEstimate":
        return refine_arrays(images, fit_mask, est, n, SHOWN[method], fit, saturated)

    return Source(normals, refine, fit_mask)


def capture_source(capture: "Capture", mask: np.ndarray, method: str, weights: str | os.PathLike | None = None,
                   config: dict | None = None, progress: "ProgressFactory | None" = None,
                   memo: "DecodeMemo | None" = None, fit_mask: np.ndarray | None = None) -> Source:
    """A capture folder, streamed from disk (its light files, if any, are not used); as
    ``array_source`` otherwise. The passes share a ``DecodeMemo`` (``memo``, or one of
    ``cache_mb``): each divides the images by other intensities, so what the first decodes is
    kept as decoded."""
    fit_mask = mask if fit_mask is None else fit_mask
    from psctl.infer import DEFAULT_INFER, capture_normals
    from psctl.io.capture import DecodeMemo
    from psctl.lights import lit_capture
    from psctl.refine import refine_capture

    if memo is None:
        memo = DecodeMemo({**DEFAULT_INFER, **(config or {})}["cache_mb"] << 20)

    def normals(est: "LightEstimate") -> "InferResult":
        return capture_normals(lit_capture(capture, est), mask, method, weights, config, progress, memo)

    def refine(est: "LightEstimate", n: np.ndarray, fit: dict | None) -> "LightEstimate":
        return refine_capture(capture, fit_mask, est, n, SHOWN[method], progress, fit, memo)

    return Source(normals, refine, fit_mask)


def second_stage(source: Source, est: "LightEstimate", refine: bool = True, config: dict | None = None,
                 normals: bool = True) -> tuple["LightEstimate", "InferResult | None"]:
    """sdps after LCNet: the second stage on ``est`` (LCNet's lights); with ``refine``, the lights
    refined against its normals, the second stage again on them when the fit moved them, and
    lights and normals turned about the view axis by the roll of those normals when ``config``
    (over DEFAULT_REFINE) asks for it.

    ``normals=False`` (the lights alone, as ``psctl lights``): the second stage runs again only
    when the roll needs the refined lights' normals, and no normals are returned.
    Returns (lights, the second stage's result for them, its normals turned with the lights; None
    with ``normals=False``).
    """
    from psctl.refine import roll_estimate, wants_roll

    net = source.normals(est)
    if refine:
        est = source.refine(est, net.normals, config)
        if est.info["refine"]["weight"] > 0 and (normals or wants_roll(config)):
            net = source.normals(est)  # the roll is read from the normals of the final lights
        est, rolled = roll_estimate(est, net.normals, source.mask, config)
        net = replace(net, normals=rolled)
    return est, (net if normals else None)

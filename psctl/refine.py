"""Light refinement for uncalibrated photometric stereo (sdps): the lights LCNet estimated, refit
against the normals a network estimated from them, then turned about the view axis by the roll
that makes those normals most integrable.

    >>> from psctl.refine import refine_lights, integrability_roll
    >>> ref = refine_lights(observations, normals, directions, intensities)   # [N, P], [P, 3], [N, 3], [N]
    >>> ref.directions, ref.intensities, ref.quality, ref.weight

``refine_lights`` is the fit on arrays; ``refine_estimate``, ``refine_capture`` and
``refine_arrays`` run it on a ``psctl.lights.LightEstimate`` over a capture folder's or an array's
pixels; ``roll_estimate`` applies the roll. ``psctl.sdps`` drives them; docs/uncalibrated.md
("Light refinement", "Falloff", "Roll from integrability") says how each was chosen.

The same curl terms give ``mirror_ratio``: how much more integrable a normal map's mirror image is,
the check behind the note on a light file (``psctl.api.mirror_notes``) or a given normal map
(``psctl.depth.mirror_map_notes``) with an axis flipped.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from psctl.arrays import bounding_box
from psctl.errors import ProgressFactory, PsctlError

if TYPE_CHECKING:
    from psctl.infer import Reader
    from psctl.io.capture import Capture, DecodeMemo
    from psctl.lights import LightEstimate

__all__ = ["FALLOFFS", "DEFAULT_REFINE", "Refinement", "refine_lights", "sample_observations", "refine_estimate",
           "integrability_roll", "erode_mask", "MIRROR_NOTE", "mirror_ratio", "turn_about_view_axis", "lights_changed",
           "wants_roll", "roll_estimate", "refine_config", "refine_capture", "refine_arrays"]



# --- the fit ---------------------------------------------------------------------------------

# Why: LCNet classifies each image's light from a 128 x 128 view; once a network has estimated
# the normals from those lights, the full-resolution pixels pin each light down better wherever
# the surface is mostly diffuse. Chosen on synthetic folders (docs/uncalibrated.md, "Light
# refinement"); the gate keeps LCNet's lights where a diffuse model explains the pixels badly
# (metals, deep concavities).
_REFINE_BLOCK = 2048  # pixels per block of refine_lights' [pixels, images] arrays
FALLOFFS = ("shifted", "lambertian")  # refine_lights' shading models (DEFAULT_REFINE["falloff"])
DEFAULT_REFINE = {
    "pixels": 20000,  # mask pixels sampled for the fit (seeded): enough to fix 3 numbers per light
    "iters": 5,  # alternations of per-pixel albedo and per-image light
    "margin": 0.1,  # a light lights a pixel when n.s > margin |s|: keeps the terminator out of the fit
    # per image, only pixels whose observed / predicted ratio lies within these quantiles: cast
    # shadows and interreflections (low) and highlights (high) out
    "trim": (0.1, 0.9),
    # the fit's relative residual q (median |o - rho (n.s + b)| / median o over lit observations,
    # n.s + b > 0 too): at or below gate[0] the fitted lights are used, at or above gate[1]
    # LCNet's are kept, blended between. gate[1] was 0.10 for the Lambertian fit (sessions 16-19);
    # 0.15 since session 20, chosen with the shifted falloff on synthetic folders
    # (docs/uncalibrated.md, "Falloff")
    # (0.05, 0.15) until the dark observations left the fit and q (helper-195): scaled by 0.75, the ratio
    # of median q without / with them on a fresh tuning set (psctl synth --seed 83, mixed, 3 bounces)
    "gate": (0.0375, 0.1125),
    # a fitted light further than this from its start (degrees) means the fit went astray (on a
    # mirror-like surface it can shrink the lit set until a few pixels fit): the start is kept.
    # There is no horizon check: a fitted light may end slightly below it (z < 0) and is then
    # written and used as it is
    "max_change": 30.0,
    # observations darker than this fraction of the object's 99.9th-percentile observation are
    # left out of the fit (the albedo and light steps), as saturated ones are: mostly cast
    # shadows, zeros where the model says lit, which pull each pixel's albedo and each light
    # toward the shadow. 0: all kept (the fit of sessions 20-78). One threshold for all images: an
    # image over ~100x dimmer than the brightest loses all its observations and keeps LCNet's light
    "dark": 0.01,
    # with "dark" > 0, which observations the gate's q is computed over: "all" (those the fit of
    # sessions 20-78 used, dark ones included, the albedo refit over them for the fitted lights:
    # the gate's meaning before session 79) or "fit" (only those the fit used; since session 79)
    "gate_q": "fit",
    # the shading model: "shifted", o = rho (n.s + b) with b <= 0 per image, a cosine that falls
    # to zero before the terminator; or "lambertian", o = rho max(n.s, 0) (b = 0; the default until
    # session 20). Cast shadows and many real reflectances fall off faster than a cosine near the
    # terminator, which pulls a Lambertian fit's lights outward (docs/uncalibrated.md, "Falloff");
    # b > 0 (a flatter falloff: glossy surfaces) is refused because there the extra freedom lets
    # the fit run away
    "falloff": "shifted",
    "seed": 0,
    # after the fit, turn the lights and the final normals about the view axis by the roll that
    # makes those normals most integrable (``integrability_roll``): the one part of a rotation
    # shared by lights and normals that the fit cannot see and integrability can
    # (docs/uncalibrated.md, "Roll from integrability"; on since session 22: lower normal and light
    # errors on all four synthetic decision sets)
    "roll": True,
    "roll_erode": 3,  # mask pixels this close to the edge left out (rims and silhouettes are unreliable)
    "max_roll": 15.0,  # a larger roll (degrees) is refused and the lights kept: not a small correction
}


@dataclass
class Refinement:
    directions: np.ndarray  # [N, 3] unit
    intensities: np.ndarray  # [N], on the scale of the intensities passed in (their geometric mean)
    quality: float  # q, the fit's relative residual (inf when nothing was fitted)
    weight: float  # in [0, 1]: 1 = the fitted lights, 0 = the ones passed in
    status: str = "fitted"  # fitted | too few pixels | astray (see DEFAULT_REFINE["max_change"]) | undetermined
    unfitted: tuple[int, ...] = ()  # images (0-based) with too few lit, usable observations: their light kept


def refine_lights(observations: np.ndarray, normals: np.ndarray, directions: np.ndarray,
                  intensities: np.ndarray, config: dict | None = None) -> Refinement:
    """Refine lights by a robust Lambertian (or shifted-cosine) fit against known normals.

    Model: o[j, p] = rho[p] * max(n[p] . s[j] + b[j], 0) with s[j] = |s[j]| l[j]; b = 0 for the
    "lambertian" falloff, b[j] <= 0 fitted per image for "shifted" (then e[j] = |s[j]| + b[j], the
    brightness where n = l). Starting from the given lights, alternate rho (least squares per
    pixel over the observations it is lit in) and s[j], b[j] (least squares per image over lit
    pixels, trimmed by ``trim``). The fit's residual q decides, through ``gate``, how much of it
    replaces the lights passed in.

    Args:
        observations: [N, P] grey values as captured (not divided by any intensity); NaN where
            one is not to be used (saturated).
        normals: [P, 3] unit normals of the same pixels (e.g. PS-FCN's from the lights below).
        directions: [N, 3] unit light directions to start from (LCNet's).
        intensities: [N] their intensities.
        config: overrides of DEFAULT_REFINE.
    Returns:
        Refinement (directions [N, 3], intensities [N], quality q, weight, status).
    """
    unknown = sorted(set(config or {}) - set(DEFAULT_REFINE))
    if unknown:  # a typo ("gates") would fit with the defaults without a word (helper-196)
        raise PsctlError(None, f"refine_lights: unknown config keys {', '.join(map(repr, unknown))}; known: "
                               f"{', '.join(DEFAULT_REFINE)}")
    cfg = {**DEFAULT_REFINE, **(config or {})}
    # observations stay float32 (as sampled) and [P, N] arrays are only made a block of pixels at a
    # time: whole, in float64, they were about 0.5 GB for 960 images (session 38)
    o = np.asarray(observations, np.float32)
    n = np.asarray(normals, np.float64)
    d0 = np.asarray(directions, np.float64)
    e0 = np.asarray(intensities, np.float64).reshape(-1)
    if o.ndim != 2 or n.shape != (o.shape[1], 3) or d0.shape != (o.shape[0], 3) or e0.shape != (o.shape[0],):
        raise PsctlError(None, f"refine_lights: shapes must be observations [N, P], normals [P, 3], directions "
                               f"[N, 3], intensities [N]; got {list(o.shape)}, {list(n.shape)}, {list(d0.shape)}, "
                               f"{list(e0.shape)}")
    if cfg["falloff"] not in FALLOFFS:
        raise PsctlError(None, f"refine_lights: falloff must be one of {', '.join(FALLOFFS)}, not {cfg['falloff']!r}")
    keep = Refinement(d0.astype(np.float32), e0.astype(np.float32), float("inf"), 0.0, "too few pixels")
    # NaN: an observation not to use (a saturated one: its true value is unknown, and taking the top
    # code for it pulls the light toward the clipped highlight); a pixel keeps its other observations
    seen = np.isfinite(o)
    ok = seen.any(0) & np.isfinite(n).all(1) & (np.linalg.norm(n, axis=1) > 0.5)
    if not ok.all():
        o, n, seen = o[:, ok], n[ok], seen[:, ok]
    if cfg["gate_q"] not in ("all", "fit"):
        raise PsctlError(None, f"refine_lights: gate_q must be 'all' or 'fit', not {cfg['gate_q']!r}")
    dark = float(cfg["dark"]) > 0 and bool(seen.any())
    if dark:  # the fit leaves out observations too dark to use (DEFAULT_REFINE["dark"]), as saturated ones
        o_all, seen_all = np.where(seen, o, np.float32(0.0)), seen
        seen = seen & ~(o < np.float32(float(cfg["dark"]) * float(np.percentile(o[seen], 99.9))))
    gaps = not seen.all()
    if gaps:
        o = np.where(seen, o, np.float32(0.0))
    if n.shape[0] < 50 or not (np.all(e0 > 0) and np.isfinite(d0).all()):
        return keep
    from psctl.classic import lights_problem

    if lights_problem(d0) is not None:  # fewer than 3 lights, or coplanar: any light fits (residual 0)
        return replace(keep, status="undetermined")
    shifted = cfg["falloff"] == "shifted"
    lo_q, hi_q = cfg["trim"]
    s = d0 * e0[:, None]
    b = np.zeros(len(s))
    blocks = [slice(a, a + _REFINE_BLOCK) for a in range(0, len(n), _REFINE_BLOCK)]

    def shading(px: slice, s: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shading n.s + b [p, N] of a block of pixels, and where each light lights them."""
        sh = n[px] @ s.T
        lit = sh > cfg["margin"] * np.linalg.norm(s, axis=1)[None]
        sh += b[None]
        lit &= sh > 0
        if gaps:
            lit &= seen[:, px].T  # an observation left out counts as not lit: in no sum below
        return sh, lit

    def albedo(s: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """lit [P, N] and the least-squares albedo rho [P] over each pixel's lit observations."""
        lit, rho = np.empty((len(n), len(s)), bool), np.empty(len(n))
        for px in blocks:
            sh, lit[px] = shading(px, s, b)
            shl = sh * lit[px]
            den = (shl ** 2).sum(1)
            rho[px] = np.where(den > 0, (o[:, px].T * shl).sum(1) / np.maximum(den, 1e-300), 0.0)
        return lit, rho

    unfitted: list[int] = []
    for _ in range(int(cfg["iters"])):
        lit, rho = albedo(s, b)
        new, new_b = s.copy(), b.copy()
        unfitted = []
        for j in range(len(s)):
            use = np.flatnonzero(lit[:, j] & (rho > 0))
            if use.size < 10:
                unfitted.append(j)  # (nearly) no lit pixel for this light (or all under "dark"): keep it
                continue
            ratio = o[j, use] / (rho[use] * (n[use] @ s[j] + b[j]))
            lo, hi = np.quantile(ratio, (lo_q, hi_q))
            use = use[(ratio >= lo) & (ratio <= hi)]
            if use.size < 10:
                unfitted.append(j)
                continue
            a = rho[use, None] * n[use]
            oj = o[j, use].astype(np.float64)
            sol4 = np.linalg.lstsq(np.concatenate([a, rho[use, None]], 1), oj, rcond=None)[0] if shifted else None
            if sol4 is not None and sol4[3] < 0 and np.linalg.norm(sol4[:3]) + sol4[3] > 0:
                sol, off = sol4[:3], sol4[3]
            else:  # b = 0: the Lambertian fit
                sol, off = np.linalg.lstsq(a, oj, rcond=None)[0], 0.0
            if np.isfinite(sol).all() and np.isfinite(off) and np.linalg.norm(sol) > 0:
                new[j], new_b[j] = sol, off
        k = np.linalg.norm(new, axis=1).mean()  # the fit fixes rho * e only up to one scale
        s, b = new / k, new_b / k
    if not (np.isfinite(s).all() and np.isfinite(b).all()):
        return keep
    fitted = s / np.linalg.norm(s, axis=1, keepdims=True)
    change = np.degrees(np.arccos(np.clip((fitted * d0).sum(1), -1, 1)))
    if (change > cfg["max_change"]).any():
        return replace(keep, status="astray")
    if dark and cfg["gate_q"] == "all":  # q over the observations today's fit uses (dark ones in)
        o, seen = o_all, seen_all
        gaps = not seen.all()
    lit, rho = albedo(s, b)
    if not lit.any():
        return keep
    lit_obs = np.empty(int(lit.sum()))  # one buffer: the residuals' median, then the observations'
    medians = []
    for residual in (True, False):
        at = 0
        for px in blocks:
            sh, li = shading(px, s, b)
            v = o[:, px].T[li].astype(np.float64)
            lit_obs[at:at + v.size] = np.abs(v - (rho[px, None] * sh)[li]) if residual else v
            at += v.size
        medians.append(float(np.median(lit_obs, overwrite_input=True)))
    q = medians[0] / max(medians[1], 1e-12)
    lo_g, hi_g = cfg["gate"]
    w = float(np.clip((hi_g - q) / (hi_g - lo_g), 0.0, 1.0)) if np.isfinite(q) else 0.0
    e = np.linalg.norm(s, axis=1) + b  # the brightness of a pixel facing the light (b = 0: |s|)
    d = w * fitted + (1 - w) * d0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # intensities blended in log space, each set first divided by its geometric mean; the result
    # is given the geometric mean of the intensities passed in
    g0 = np.exp(np.log(e0).mean())
    e = g0 * np.exp(w * (np.log(e) - np.log(e).mean()) + (1 - w) * (np.log(e0) - np.log(g0)))
    return Refinement(d.astype(np.float32), e.astype(np.float32), q, w, unfitted=tuple(unfitted))


def sample_observations(reader: "Reader", n: int, mask: np.ndarray, normals: np.ndarray,
                        config: dict | None = None,
                        advance: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Grey observations [n, P] and normals [P, 3] at up to ``pixels`` seeded mask pixels.

    ``reader(start, box)`` yields the images as captured (see ``psctl.infer.Reader``); they are
    read once, and only the sampled pixels are kept (P values per image)."""
    cfg = {**DEFAULT_REFINE, **(config or {})}
    mask = np.asarray(mask, bool) & (np.linalg.norm(normals, axis=-1) > 0.5)
    if not mask.any():
        return np.zeros((n, 0), np.float32), np.zeros((0, 3), np.float32)
    box = bounding_box(mask)
    ys, xs = np.nonzero(mask[box])
    if ys.size > cfg["pixels"]:
        pick = np.sort(np.random.default_rng(cfg["seed"]).choice(ys.size, int(cfg["pixels"]), replace=False))
        ys, xs = ys[pick], xs[pick]
    obs = np.empty((n, ys.size), np.float32)
    k = 0
    for img in reader(0, box):
        if k >= n:
            break
        img = np.asarray(img, np.float32)
        obs[k] = img[ys, xs].mean(-1) if img.ndim == 3 else img[ys, xs]
        k += 1
        if advance is not None:
            advance(1)
    if k != n:
        raise PsctlError(None, f"expected {n} images, got {k}")
    return obs, np.asarray(normals, np.float32)[box][ys, xs]


def refine_estimate(est: LightEstimate, reader: "Reader", n: int, mask: np.ndarray, normals: np.ndarray,
                    config: dict | None = None, method: str = "PS-FCN", progress: "ProgressFactory | None" = None,
                    label: str = "reading for the light fit") -> LightEstimate:
    """``est`` with its lights refined against ``normals`` [H, W, 3] (``refine_lights``); the
    capture is read once more. ``info["refine"]`` and a note say what happened."""
    t0 = time.perf_counter()
    advance = progress(label, n) if progress is not None else None
    obs, nrm = sample_observations(reader, n, mask, normals, config, advance)
    ref = refine_lights(obs, nrm, est.directions, est.intensities, config)
    cfg = {**DEFAULT_REFINE, **(config or {})}
    info = {**est.info, "refine": {"quality": None if not np.isfinite(ref.quality) else round(ref.quality, 4),
                                   "weight": round(ref.weight, 3), "status": ref.status, "pixels": int(obs.shape[1]),
                                   "gate": list(cfg["gate"]), "falloff": cfg["falloff"],
                                   "seconds": round(time.perf_counter() - t0, 3)}}
    if ref.status == "astray":
        note = (f"lights: LCNet's lights kept (refitting them against {method}'s normals moved a light by more than "
                f"{cfg['max_change']:g} degrees)")
    elif ref.status == "undetermined":
        note = (f"lights: LCNet's lights kept ({len(est.directions)} image(s) with (nearly) coplanar estimated "
                f"lights: a fit against {method}'s normals would be undetermined)" if len(est.directions) >= 3 else
                f"lights: LCNet's lights kept (only {len(est.directions)} image(s): a fit against {method}'s normals "
                f"would be undetermined)")
    elif not np.isfinite(ref.quality):
        note = "lights: too few usable pixels to refine LCNet's lights against the normals; LCNet's kept"
    elif ref.weight >= 1:
        note = f"lights: LCNet's lights refined against {method}'s normals (fit residual {ref.quality:.3g})"
    elif ref.weight <= 0:
        note = (f"lights: LCNet's lights kept (a diffuse fit against {method}'s normals explains this object "
                f"poorly: residual {ref.quality:.3g} >= {cfg['gate'][1]})")
    else:
        note = (f"lights: LCNet's lights {info['refine']['weight']:.0%} refined against {method}'s normals (fit "
                f"residual {ref.quality:.3g})")
    notes = [*est.notes, note]
    if ref.unfitted and ref.weight > 0:
        # one dark threshold for the object: an image ~100x dimmer than the brightest has no usable
        # observation and keeps LCNet's light, whose intensity classes stop at 0.2 (helper-208: 10x too bright)
        info["refine"]["unfitted"] = [j + 1 for j in ref.unfitted]
        above = f" above {cfg['dark']:g} of the object's brightest" if float(cfg["dark"]) > 0 else ""
        shown = ", ".join(str(j + 1) for j in ref.unfitted[:8]) + (", ..." if len(ref.unfitted) > 8 else "")
        notes.append(f"lights: image{'s' * (len(ref.unfitted) > 1)} {shown} (1-based, in the capture's order) had "
                     f"too few lit pixels{above} for the light fit: LCNet's light kept there (a far dimmer image? its "
                     "intensity may be far off)")
    return replace(est, directions=ref.directions, intensities=ref.intensities, info=info, notes=notes)


# --- the roll from integrability ---------------------------------------------------------------

def integrability_roll(normals: np.ndarray, mask: np.ndarray | None = None, erode: int = 3) -> tuple[float, float, int]:
    """The turn about the view axis that makes a normal map most integrable.

    A surface's gradient field (dz/dcol, dz/drow) = (-nx/nz, +ny/nz) has no curl; scaled by
    nz^2 (bounded where the surface is steep) the curl is, per pixel with its four neighbours
    (central differences, so that a mirrored map's roll is the negative and a half-turned one's
    the same),
    r = -nz dnx/drow + nx dnz/drow - nz dny/dcol + ny dnz/dcol. Turning the normals by an angle t
    about the view axis leaves nz and turns (nx, ny), so r(t) = cos(t) r(0) + sin(t) r(90 deg) and
    the t minimising the sum of r(t)^2 has a closed form. Turns about in-plane axes change r far
    less (docs/uncalibrated.md, "Roll from integrability"), so only the roll is estimated.

    Args:
        normals: [H, W, 3] normals, x right / y up / z toward the camera.
        mask: [H, W] bool (None: the pixels with a nonzero normal).
        erode: pixels this close to the mask's edge are left out.
    Returns:
        (roll in degrees, counterclockwise seen from the camera: turning the normals by it makes
        them most integrable; the residual's relative drop sum r(0)^2 / sum r(roll)^2 >= 1; the
        number of pixels used, each with its four neighbours inside). (0, 1, k) when fewer than 100
        are usable.
    """
    terms, k = _curl_terms(normals, mask, erode)
    if k < 100:
        return 0.0, 1.0, k
    aa, ab, bb = terms[0]
    t = 0.5 * np.arctan2(-2.0 * ab, bb - aa)  # where E(t) below is smallest
    e = _smallest_residual(aa, ab, bb)
    return float(np.degrees(t)), float(aa / e) if e > 0 else 1.0, k


def _smallest_residual(aa: float, ab: float, bb: float) -> float:
    """min over t of E(t) = (aa + bb)/2 + (aa - bb)/2 cos 2t + ab sin 2t, the curl residual of
    the normals turned by t (the minimum is where (cos 2t, sin 2t) points against ((aa - bb)/2, ab))."""
    return (aa + bb) / 2 - float(np.sqrt(((aa - bb) / 2) ** 2 + ab ** 2))


def erode_mask(mask: np.ndarray, iterations: int) -> np.ndarray:
    """[H, W] bool eroded ``iterations`` times by the 4-neighbour cross, outside the image counting
    as background: scipy.ndimage.binary_erosion's default, in numpy (importing scipy.ndimage took
    0.17 s of every calibrated run, which checks the normals' integrability with it)."""
    ok = np.asarray(mask, bool)
    for _ in range(iterations):
        e = ok.copy()
        e[1:] &= ok[:-1]
        e[:-1] &= ok[1:]
        e[:, 1:] &= ok[:, :-1]
        e[:, :-1] &= ok[:, 1:]
        e[[0, -1]] = False
        e[:, [0, -1]] = False
        ok = e
    return ok


def _curl_terms(normals: np.ndarray, mask: np.ndarray | None, erode: int,
                mirrors: tuple[bool, ...] = (False,)) -> tuple[list[tuple[float, float, float]], int]:
    """([(aa, ab, bb) per entry of ``mirrors``], k): the sums r0.r0, r0.r90, r90.r90 of
    integrability_roll's curl residual r0 of the normals (x negated for a True entry) and r90 of
    the same turned by 90 degrees, over the k usable pixels (no sums when k < 100)."""
    n = np.asarray(normals, np.float64)
    ok = np.isfinite(n).all(-1)
    n = np.where(ok[..., None], n, 0.0)
    ok &= np.linalg.norm(n, axis=-1) > 0.5
    if mask is not None:
        ok &= np.asarray(mask, bool)
    if erode > 0:
        ok = erode_mask(ok, int(erode))
    # central differences about each pixel, its four neighbours inside: forward ones at a corner
    # pixel made the roll depend on the capture's orientation (a mirrored capture's was not the
    # negative, a half-turned one's not the same: cat's lights 5.97 / 5.27 / 5.92 degrees as
    # stored / flipped up-down / left-right, a review, session 73)
    block = ok[1:-1, 1:-1] & ok[:-2, 1:-1] & ok[2:, 1:-1] & ok[1:-1, :-2] & ok[1:-1, 2:]
    k = int(block.sum())
    if k < 100:
        return [], k

    def curl(nx: np.ndarray, ny: np.ndarray, nz: np.ndarray) -> np.ndarray:
        def drow(a: np.ndarray) -> np.ndarray:  # down the rows
            return (a[2:, 1:-1] - a[:-2, 1:-1]) / 2

        def dcol(a: np.ndarray) -> np.ndarray:  # along the columns
            return (a[1:-1, 2:] - a[1:-1, :-2]) / 2

        x, y, z = nx[1:-1, 1:-1], ny[1:-1, 1:-1], nz[1:-1, 1:-1]
        return (-z * drow(nx) + x * drow(nz) - z * dcol(ny) + y * dcol(nz))[block]

    sums = []
    for mirror in mirrors:
        nx, ny, nz = (-1.0 if mirror else 1.0) * n[..., 0], n[..., 1], n[..., 2]
        a0, a90 = curl(nx, ny, nz), curl(-ny, nx, nz)  # turned by 90 degrees: (nx, ny) -> (-ny, nx)
        sums.append((float(a0 @ a0), float(a0 @ a90), float(a90 @ a90)))
    return sums, k


# A light file with one axis flipped (y down, as image rows, is the usual case) gives the mirror
# image of the normals, which is far less integrable than the true field. On the DiLiGenT dev
# split the ratio is 1.3-18.6 with the files as given and 0.12-0.75 with y flipped (L2 and
# PS-FCN; the ball, a sphere, is the weak case), on syntest and syntest_dl see docs/usage.md.
# Below this ratio psctl normals (psctl.api.mirror_notes) and psctl depth (a given map) say so
MIRROR_NOTE = 0.5


def mirror_ratio(normals: np.ndarray, mask: np.ndarray | None = None, erode: int = 3) -> float | None:
    """How much less integrable a normal map is than its mirror image: the smallest curl residual
    over turns about the view axis (integrability_roll) of the normals with x negated, over that
    of the normals as they are. Below 1 the mirrored field is the more integrable one, which is
    what a light file with one axis flipped (y down, as image rows) gives: L2 then returns exactly
    the mirrored normals, and the networks nearly. x and y flips cannot be told apart (they
    differ by a half turn). None when fewer than 100 pixels are usable."""
    terms, k = _curl_terms(normals, mask, erode, mirrors=(False, True))
    if k < 100:
        return None
    e0, e1 = (_smallest_residual(*t) for t in terms)
    return float(e1 / e0) if e0 > 0 else None


def turn_about_view_axis(vectors: np.ndarray, degrees: float) -> np.ndarray:
    """[..., 3] vectors turned counterclockwise (seen from the camera) about the z axis."""
    t = np.radians(degrees)
    c, s = np.cos(t), np.sin(t)
    v = np.asarray(vectors)
    out = v.copy()
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


# --- on estimates, captures and arrays ----------------------------------------------------------

def lights_changed(info: dict | None) -> bool:
    """Whether a refinement report (``info["refine"]``) says LCNet's lights were changed: fitted
    with some weight, or turned by the roll."""
    return bool(info) and (info["weight"] > 0 or (info.get("roll") or {}).get("status") == "applied")


def wants_roll(config: dict | None = None) -> bool:
    """Whether the refinement ``config`` (over DEFAULT_REFINE) turns the lights by the normals' roll."""
    return bool({**DEFAULT_REFINE, **(config or {})}["roll"])


def roll_estimate(est: LightEstimate, normals: np.ndarray, mask: np.ndarray | None,
                  config: dict | None = None) -> tuple[LightEstimate, np.ndarray]:
    """``est`` and the normals it gave [H, W, 3], both turned about the view axis by the normals'
    ``integrability_roll`` when ``config`` (over DEFAULT_REFINE) has "roll" on; unchanged
    otherwise. ``info["refine"]["roll"]`` and a note say what happened."""
    cfg = {**DEFAULT_REFINE, **(config or {})}
    if not cfg["roll"]:
        return est, normals
    t, gain, k = integrability_roll(normals, mask, cfg["roll_erode"])
    if k < 100:
        status, note = "too few pixels", "lights: too few pixels to read the normals' roll; not turned"
    elif abs(t) > cfg["max_roll"]:
        status, note = "refused", (f"lights: not turned about the view axis (the normals' roll, {t:+.1f} degrees, "
                                   f"is beyond {cfg['max_roll']:g})")
    else:
        status, note = "applied", (f"lights: turned {t:+.1f} degrees about the view axis, the roll that makes the "
                                   "normals from them most integrable")
    info = {**est.info, "refine": {**(est.info.get("refine") or {}),
                                   "roll": {"degrees": round(t, 3), "gain": round(gain, 5), "status": status}}}
    if status == "applied" and abs(t) < 0.05:  # "+0.0 degrees" says nothing; the report keeps the value
        note = None
    est = replace(est, info=info, notes=[*est.notes, *([note] if note else [])])
    if status != "applied":
        return est, normals
    est = replace(est, directions=turn_about_view_axis(est.directions, t).astype(np.float32))
    return est, turn_about_view_axis(normals, t).astype(np.float32)


def refine_config(falloff: str | None, roll: bool | None = None) -> dict | None:
    """The refinement's config for a user's ``--falloff`` and ``--roll/--no-roll`` (None:
    DEFAULT_REFINE's); one-line error for a falloff other than "shifted" or "lambertian"."""
    if isinstance(falloff, str):
        falloff = falloff.lower()  # as --method: Lambertian is lambertian
    if falloff is not None and falloff not in FALLOFFS:
        raise PsctlError(None, f"--falloff must be {' or '.join(FALLOFFS)}, not {falloff!r}")
    if roll is not None and not isinstance(roll, (bool, np.bool_)):
        raise PsctlError(None, f"roll must be True, False or None, not {roll!r}")
    cfg = {k: v for k, v in (("falloff", falloff), ("roll", roll)) if v is not None}
    return cfg or None


def refine_capture(capture: "Capture", mask: np.ndarray, est: LightEstimate, normals: np.ndarray,
                   method: str = "PS-FCN", progress: "ProgressFactory | None" = None,
                   config: dict | None = None, memo: "DecodeMemo | None" = None) -> LightEstimate:
    """``refine_estimate`` on a capture folder's images as captured (its light_intensities.txt,
    if any, is not applied: the fit estimates the intensities). ``memo``: as ``iter_images``."""
    from psctl.io.capture import iter_images

    # the estimate's directions: near lights' falloff follows them (psctl.nearlight)
    raw = replace(capture, lights=est.directions, intensities=np.ones_like(capture.intensities))

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        top: dict[int, np.ndarray] = {}  # each integer image's pixels at its top code (saturated)
        for k, img in enumerate(iter_images(raw.subset(range(start, raw.n_images)), box, memo=memo,
                                            clipped=top.__setitem__)):
            sat = top.pop(k, None)
            if sat is not None and sat.any():  # left out of the fit (refine_lights: NaN)
                img = img.copy()
                img[sat] = np.nan
            yield img

    return refine_estimate(est, reader, capture.n_images, mask, normals, config, method=method, progress=progress,
                           label=f"{capture.name}: reading for the light fit")


def refine_arrays(images: np.ndarray, mask: np.ndarray | None, est: LightEstimate, normals: np.ndarray,
                  method: str = "PS-FCN", config: dict | None = None,
                  saturated: np.ndarray | None = None) -> LightEstimate:
    """``refine_estimate`` on in-memory images [N, H, W, 3] as captured; ``saturated`` [N, H, W]
    bool, the observations to leave out (as ``refine_capture`` leaves out a file's top code)."""
    m = np.ones(images.shape[1:3], bool) if mask is None else np.asarray(mask, bool)

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        for k in range(start, len(images)):
            img = images[k][box]
            if saturated is not None and saturated[k][box].any():
                img = np.where(saturated[k][box][..., None], np.float32(np.nan), img).astype(np.float32)
            yield img

    return refine_estimate(est, reader, len(images), m, normals, config, method=method)



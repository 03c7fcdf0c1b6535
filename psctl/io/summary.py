"""Human-readable summaries: ``psctl info`` and the tables printed after a run (Rich)."""

from __future__ import annotations

import collections
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.errors import PsctlError, few, quoted_tilde, visible

if TYPE_CHECKING:
    from psctl.io.capture import Capture

SATURATED_SHARE = 0.01  # an image with more of the object than this at its top code value is listed


def check_pixels(cap: "Capture", mask: np.ndarray, progress: Callable[[int], None] | None = None,
                 gt_problems: "list[PsctlError] | None" = None) -> dict:
    """Decode every file of a capture (images, ambient image, ground truth) and describe the
    images over the object (``mask``), as captured: what ``psctl info --check`` adds.

    Every damaged image is found before the first is reported (PsctlError naming it and
    counting the rest), so one run lists what to re-copy. Per image: ``mean``, the mean linear
    value over the object (sRGB decoded, not divided by the intensities), and ``saturated``,
    the share of the object's pixels with a channel at the file's top code value (null for
    float files, which have none). Black images, negative values and isolated hot pixels are the
    notes psctl normals would give, judged as it reads the images (after the ambient image is
    subtracted; hot pixels before any intensity is divided out); what would stop it (every image black over the object, an ambient image that blacks an image
    out) stops the check with the same message."""
    import time

    from psctl.hotpixels import clamp_hot_pixels, hot_pixel_notes
    from psctl.arrays import bounding_box
    from psctl.io.capture import ImageCheck, ground_truth_error, has_top_code, minus_ambient, saturated_map
    from psctl.io.images import read_image, to_rgb

    t0 = time.perf_counter()
    check = ImageCheck(cap)
    damaged: list[PsctlError] = []
    blacked_out: PsctlError | None = None  # by the ambient image: reported after any damaged file
    per_image = []
    hot: dict[int, int] = {}  # image index -> isolated hot values (psctl.hotpixels)
    box = bounding_box(mask, 1) if mask.any() else (slice(0, 0), slice(0, 0))  # the object and its neighbours
    box_mask = mask[box]
    ambient = None
    if cap.ambient_path is not None:  # in linear values, as psctl.io.capture.iter_images subtracts it
        try:
            ambient = to_rgb(read_image(cap.ambient_path)[0])
        except PsctlError as e:
            damaged.append(e)
        else:
            ambient = cap.to_linear(cap.ambient_path, ambient)
    for k, p in enumerate(cap.image_paths):
        try:
            pixels, info = read_image(p)
        except PsctlError as e:
            damaged.append(e)
            per_image.append({"image": p.name, "mean": None, "saturated": None})
            if progress is not None:
                progress(1)
            continue
        full = to_rgb(pixels)
        rgb = full[mask]  # [pixels over the object, 3]
        saturated = float(saturated_map(rgb).mean()) if has_top_code(info) and len(rgb) else None
        check.see_ceiling(k, full[box], box_mask)  # (any sample type) as well
        rgb = cap.to_linear(k, rgb)
        if ambient is not None and ambient.shape == full.shape:  # (a size mismatch: open_capture's error)
            full = cap.to_linear(k, full)
            try:
                lit = minus_ambient(full, ambient, cap, p.name)
            except PsctlError as e:
                blacked_out, lit = blacked_out or e, np.zeros_like(full)
            # divided by the intensities, as psctl normals reads them: its brightness note compares them so
            check.see(k, lit[mask], cap.intensities[k])
            region = lit[box]
        else:
            check.see(k, rgb, cap.intensities[k])
            region = cap.to_linear(k, full[box])
        # as the networks find them: around the object, zero outside it
        _, count = clamp_hot_pixels(np.where(box_mask[..., None], region, np.float32(0.0)), box_mask)
        if count:
            hot[k] = count
        # float64: a float image's values near float32's limit would overflow its sum (a warning, then inf)
        per_image.append({"image": p.name, "mean": float(rgb.mean(dtype=np.float64)) if len(rgb) else 0.0,
                          "saturated": saturated})
        if progress is not None:
            progress(1)
    if damaged:
        e = damaged[0]
        more = ""
        if len(damaged) > 1:
            names = ", ".join(Path(d.path).name for d in damaged[1:4] if d.path) + (" ..." if len(damaged) > 4 else "")
            more = f" (and {len(damaged) - 1} more damaged: {names})"
        raise PsctlError(e.path, f"{e.message}{more}")
    if blacked_out is not None:
        raise blacked_out
    if not check.lit:  # as psctl normals: nothing to estimate from
        raise PsctlError(cap.path, "all images are black inside the mask")
    # as psctl normals refuses it, in its words (``gt_problems``: describe_capture's, read once)
    for e in _gt_problems(cap, mask) if gt_problems is None else gt_problems:
        raise ground_truth_error(e)
    means = [r["mean"] for r in per_image]
    mixed, named = _mixed_type_notes(cap, means)  # (its darker images are not named twice)
    over = [r for r in per_image if r["saturated"] is not None and r["saturated"] > SATURATED_SHARE]
    return {
        "seconds": round(time.perf_counter() - t0, 3),
        "images": per_image,
        "mean_range": [float(min(means)), float(np.median(means)), float(max(means))],
        "saturated_images": [r["image"] for r in over],  # above SATURATED_SHARE of the object
        "notes": check.notes(named) + hot_pixel_notes({"hot_pixels": hot}, [p.name for p in cap.image_paths]) +
                 mixed,
    }


MIXED_DARKER = 16.0  # a sample type's median image this many times darker than another's: a note


def _mixed_type_notes(cap: "Capture", means: list[float]) -> tuple[list[str], set[int]]:
    """Images of mixed sample types compared by brightness over the object, as the notes on
    opening promise: 8-bit values saved in a 16-bit file read 257 times darker than their 8-bit
    neighbours (a helper's repro: one such image of ball's 96 took l2 from 4.49 to 4.91 degrees).
    -> (the notes, the images they call darker)."""
    groups: dict[str, list[int]] = {}
    for k, kind in enumerate(cap.sample_kinds):
        groups.setdefault(kind, []).append(k)
    if len(groups) < 2:
        return [], set()
    med = {g: float(np.median([means[k] for k in ks])) for g, ks in groups.items()}
    top = max(med, key=med.get)
    notes, named = [], set()
    for g, ks in groups.items():
        if 0 < med[g] * MIXED_DARKER < med[top]:
            named.update(ks)
            names = few([cap.image_paths[k].name for k in ks])
            one = len(ks) == 1
            notes.append(f"images: the {g} {'image' if one else 'ones'} ({names}) {'is' if one else 'are'} "
                         f"{med[top] / med[g]:.0f} times darker over the object than the {top} ones (medians): "
                         f"values of another depth saved in {'it' if one else 'them'}? Convert them alike")
    return notes, named


def _in_rows(note: str) -> bool:
    """Whether ``psctl info``'s encoding and ambient rows already say what a note says: how the
    images are decoded does; a note that some are read as stored against what their files
    suggest (a JPEG name, a PNG chunk, an unreadable or linear profile) does not."""
    return note.startswith("ambient:") or (note.startswith("encoding:") and "read as" not in note)


def describe_capture(path: str | os.PathLike, encoding: str = "auto", check: bool = False,
                     progress: Callable[[str, int], Callable[[int], None]] | None = None) -> dict:
    """What a capture folder holds, as a JSON-ready dict. ``check``: also decode every file
    (``check_pixels``) under the key ``check``; otherwise only headers and text files are read."""
    from psctl.io.capture import capture_notes, load_mask, open_capture, relative_exposures
    from psctl.io.icc import ToneCurve

    cap = open_capture(path, encoding)
    mask = load_mask(cap)
    gt_problems = _gt_problems(cap, mask)  # the ground truth decoded once, for the notes and --check
    curves = [d for d in map(cap.decoding, range(cap.n_images)) if isinstance(d, ToneCurve)]
    srgb, profiled = cap.srgb_images, len(curves)
    exposures = relative_exposures(cap)
    e = cap.intensities
    kinds = sorted(set(cap.kinds))  # from the headers open_capture read
    report = {
        "kind": "capture",
        "object": cap.name,
        "path": str(cap.path),
        "n_images": cap.n_images,
        "height": cap.height,
        "width": cap.width,
        "channels": cap.channels,  # the first image's
        "channel_counts": sorted(set(cap.channel_counts or (cap.channels,))),  # the distinct counts over the images
        "bit_depth": cap.bits,  # the first image's
        "sample_type": cap.dtype,
        "bit_depths": sorted({b for b, _ in kinds}),  # the distinct depths over the images: more than one when mixed
        "sample_types": list(dict.fromkeys(t for _, t in kinds)),  # in the order of bit_depths
        # how the values are read: linear, srgb (decoded to linear), profile (decoded through the files'
        # ICC profiles' tone curves), or mixed
        "encoding": "linear" if srgb + profiled == 0 else "srgb" if srgb == cap.n_images else
                    "profile" if profiled == cap.n_images else "mixed",
        "srgb_images": srgb,
        "profile_images": profiled,
        # the curves of the profiles decoded through ('Adobe RGB (1998)', gamma 2.2), each once
        "profiles": sorted({d.describe() for d in curves}),
        # what the images' PNG colour chunks say, counted ({"sRGB": 12}; psctl reads them as stored unless
        # --encoding srgb: the notes), and how many images embed an ICC profile psctl cannot take curves from
        "png_tags": dict(collections.Counter(t for t in cap.png_tags if t)),
        "unreadable_profiles": sum(map(bool, cap.profile_problems)),
        "calibrated": cap.calibrated,
        "intensities": cap.intensities_path.name if cap.intensities_path else "none (all ones)",
        "lights": cap.lights_path.name if cap.lights_path else None,
        "intensity_range": [float(e.min()), float(e.max())],
        "mask": cap.mask_path.name if cap.mask_path else None,
        "mask_coverage": float(mask.mean()),
        "mask_pixels": int(mask.sum()),
        "ground_truth": cap.gt_path.name if cap.gt_path else None,
        "ambient": cap.ambient_path.name if cap.ambient_path else None,
        "ambient_srgb": bool(cap.ambient_path and cap.is_srgb(cap.ambient_path)),
        "ambient_profile": bool(cap.ambient_path and isinstance(cap.decoding(cap.ambient_path), ToneCurve)),
        # each image's EXIF exposure over the images' median (time x ISO / f-number^2), null without EXIF:
        # what to multiply light_intensities.txt's rows by where they differ (the exposure note)
        "relative_exposures": None if exposures is None else [round(float(v), 6) for v in exposures],
        "first_image": cap.image_paths[0].name,
        "last_image": cap.image_paths[-1].name,
        # the first image's EXIF focal length in pixels, for psctl calibrate --focal exif; else None
        "camera": _exif_camera(cap.image_paths[0]),
        # the folder's K.txt (psctl depth's pinhole; psctl calibrate --K), or None
        "intrinsics": _intrinsics(cap.path),
        # what normals, lights and depth will say about how they read it
        "notes": capture_notes(cap) + [f"{cap.gt_path.name}: {e.message} (psctl normals and eval stop on it)"
                                         for e in gt_problems],
        **_auto_method(cap),
    }
    if cap.n_images < 3:  # said before a run, not only by it (a helper's finding)
        report["notes"].append(f"images: {cap.n_images} of them: l2 needs at least 3, and fewer than 3 leave the "
                               "networks' normals undetermined (expect large errors)")
    if check:
        bar = progress(f"check {cap.name}", cap.n_images) if progress is not None else None
        report["check"] = check_pixels(cap, mask, bar, gt_problems)
    return report


def _auto_method(cap: "Capture") -> dict:
    """What ``psctl normals PATH`` (--method auto) would run with the weights installed now:
    {"auto_method": name or None where it would stop, "auto_note": its note or error, or None}
    (a helper's finding: info passed a folder that normals then refused for want of weights)."""
    from psctl.api import resolve_method

    try:
        method, note = resolve_method("auto", cap.calibrated, lights_file=cap.path / "light_directions.txt")
    except PsctlError as e:
        return {"auto_method": None, "auto_note": e.message}
    return {"auto_method": method, "auto_note": note}


def _gt_problems(cap: "Capture", mask: np.ndarray) -> list[PsctlError]:
    """The ground truth read whole (one file: open_capture read only its header or variable list):
    what psctl normals would refuse in its values (an HDF5 .mat, an image's codes, no normal
    inside the mask). A note in psctl info, as lights and depth read no ground
    truth; --check stops on it as psctl normals does."""
    from psctl.io.capture import check_ground_truth_inside, load_ground_truth

    if cap.gt_path is None:
        return []
    try:
        check_ground_truth_inside(load_ground_truth(cap), mask, cap.gt_path)
    except PsctlError as e:
        return [e]
    return []


def _intrinsics(folder: Path) -> dict | None:
    from psctl.depth import find_intrinsics, read_intrinsics

    try:
        path = find_intrinsics(folder)
        if path is None:
            return None
        K = read_intrinsics(path)
    except PsctlError as e:  # psctl depth will stop on it: said here, not refused
        return {"file": Path(e.path).name if e.path and Path(e.path) != folder else "K.txt", "error": e.message}
    return {"file": path.name, "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def _exif_camera(path: Path) -> dict | None:
    from psctl.io.images import exif_focal

    try:
        f, how = exif_focal(path)
    except PsctlError:  # no EXIF focal length (most captures), or a cropped image's
        return None
    return {"focal": round(f, 3), "from": f"EXIF: {how}"}


def describe(path: str | os.PathLike, encoding: str = "auto", check: bool = False,
             progress: Callable[[str, int], Callable[[int], None]] | None = None) -> dict:
    """A capture folder's description, or a benchmark root's with one entry per object.
    ``check``: decode every file too (``check_pixels``); ``progress``: a factory as
    psctl.api.ProgressFactory, used only by the check."""
    from psctl.io.capture import find_objects, is_benchmark_root, root_notes

    path = Path(path)
    if not path.exists():
        raise PsctlError(path, "folder does not exist" + quoted_tilde(path))
    if is_benchmark_root(path):
        return {"kind": "benchmark", "path": str(path),
                "objects": [describe_capture(f, encoding, check, progress) for f in find_objects(path)],
                "notes": root_notes(path)}
    return describe_capture(path, encoding, check, progress)


def escape(text: object) -> str:
    """``text`` shown as it is by Rich (a path like cap[red]x is not markup; control characters
    written out, ``psctl.errors.visible``: table cells too)."""
    from rich.markup import escape as _escape

    from psctl.errors import visible

    return _escape(visible(str(text)))


def _console():
    from psctl.errors import console

    return console()


def print_notes(con, notes: Iterable[str], prefix: str = "") -> None:
    """Each note on its own line(s), marked "note:" in yellow (``prefix``: an object's name, say)."""
    for note in notes:
        con.print(f"[yellow]note:[/] {escape(prefix + note)}", highlight=False, soft_wrap=True)


def print_written(con, outputs: dict) -> None:
    """One "wrote PATH" line per output file, in the report's order."""
    for p in outputs.values():
        con.print(f"  wrote {p}", highlight=False, markup=False)


def render_info(report: dict) -> None:
    """The human-readable summary of ``psctl info``'s report (Rich, stdout)."""
    from rich.table import Table

    con = _console()
    if report["kind"] == "benchmark":
        con.print(escape(f"benchmark root {report['path']}"), highlight=False, soft_wrap=True)
        extra = any(o.get("encoding", "linear") != "linear" or o.get("ambient") for o in report["objects"])
        checked = all("check" in o for o in report["objects"])
        cols = ("object", "images", "size", "bits", "calibrated", "mask", "ground truth") + (
            ("encoding", "ambient") if extra else ()) + (("median", "saturated") if checked else ())
        rows = []
        for o in report["objects"]:
            c = o.get("check")
            rows.append((o["object"], str(o["n_images"]), f"{o['width']}x{o['height']}", str(o["bit_depth"]),
                         "yes" if o["calibrated"] else "no", f"{o['mask_coverage']:.1%}", o["ground_truth"] or "-",
                         *((o.get("encoding", "linear"), o.get("ambient") or "-") if extra else ()),
                         *((f"{c['mean_range'][1]:.3g}", str(len(c["saturated_images"]))) if checked else ())))
        t = Table()
        for col in cols:
            t.add_column(col, no_wrap=True)
        for row in rows:
            t.add_row(*map(escape, row))
        if t.__rich_measure__(con, con.options).maximum <= con.width:
            con.print(t)
        else:  # too wide to show whole (a narrow terminal, a pipe): one line per object, nothing cut
            for row in rows:
                con.print(escape(f"{row[0]}: " + ", ".join(f"{k} {v}" for k, v in zip(cols[1:], row[1:]))),
                          highlight=False, soft_wrap=True)
        if checked:
            con.print(f"check: every file decoded, none damaged; median: the median over images of the mean "
                      f"linear value over the object; saturated: images with over {SATURATED_SHARE:.0%} of the object "
                      f"at the top code value", highlight=False, soft_wrap=True)
        print_notes(con, report.get("notes", []))
        for o in report["objects"]:  # what psctl eval would say of each (encoding and ambient are columns)
            notes = [n for n in o.get("notes", []) if not _in_rows(n)]
            print_notes(con, notes + (o["check"]["notes"] if checked else []), f"{o['object']}: ")
        return
    r = report
    con.print(escape(f"{r['object']}  ({r['path']})"), highlight=False, soft_wrap=True)
    t = Table(show_header=False)
    t.add_column("", style="bold")
    t.add_column("", overflow="fold")  # wrapped, not cut: a long image name keeps its extension
    t.add_row("images", escape(f"{r['n_images']} ({r['first_image']} .. {r['last_image']})"))
    counts = r.get("channel_counts") or [r["channels"]]
    t.add_row("size", f"{r['width']} x {r['height']}, " + (f"{counts[0]} channel{'s' if counts[0] != 1 else ''}"
              if len(counts) == 1 else f"mixed: {'/'.join(map(str, counts))} channels (grey is read as RGB)"))
    if len(r.get("bit_depths", [])) > 1 or len(r.get("sample_types", [])) > 1:  # each is read at its own depth
        t.add_row("bit depth", f"mixed: {'/'.join(map(str, r['bit_depths']))} ({'/'.join(r['sample_types'])})")
    else:
        t.add_row("bit depth", f"{r['bit_depth']} ({r['sample_type']})")
    enc = r.get("encoding", "linear")
    profiles = "; ".join(r.get("profiles", []))
    t.add_row("encoding", escape(
        "linear" if enc == "linear" else "sRGB, decoded to linear" if enc == "srgb" else
        f"decoded to linear through their ICC profiles ({profiles})" if enc == "profile" else
        "mixed: " + ", ".join(part for part in (
            f"{r['srgb_images']} of {r['n_images']} images decoded from sRGB to linear" if r["srgb_images"] else "",
            f"{r.get('profile_images', 0)} of {r['n_images']} through their ICC profiles ({profiles})"
            if r.get("profile_images") else "",
            f"{r['n_images'] - r['srgb_images'] - r.get('profile_images', 0)} read as stored") if part)))
    t.add_row("calibrated", escape(f"yes ({r.get('lights') or 'light_directions.txt'})") if r["calibrated"]
              else "no light_directions.txt: uncalibrated")
    lo, hi = r["intensity_range"]
    t.add_row("intensities", r["intensities"] if r["intensities"].startswith("none") else
              f"{r['intensities']}, range {lo:.3g} .. {hi:.3g}")
    t.add_row("mask", escape(f"{r['mask']}, {r['mask_coverage']:.1%} of pixels ({r['mask_pixels']})" if r["mask"] else
                             f"none: the networks and psctl lights find the object (l2: the whole image, "
                             f"{r['mask_pixels']} pixels)"))
    t.add_row("ground truth", escape(r["ground_truth"] or "none"))
    if "auto_method" in r:
        t.add_row("normals", escape(f"--method auto runs {r['auto_method']}" if r["auto_method"] else
                                    f"--method auto stops: {r['auto_note']}"))
    if r.get("camera"):
        t.add_row("camera", escape(f"focal length {r['camera']['focal']:,.0f} pixels ({r['camera']['from']}; "
                                   "psctl calibrate --focal exif uses it)"))
    k = r.get("intrinsics")
    if k and "error" in k:
        t.add_row("intrinsics", escape(f"{k['file']}: cannot be read ({k['error']}); psctl depth stops on it"))
    elif k:
        from psctl.calibrate import SQUARE_PIXELS

        square = abs(k["fx"] - k["fy"]) <= SQUARE_PIXELS * max(k["fx"], k["fy"])  # what psctl calibrate --K takes
        t.add_row("intrinsics", escape(f"{k['file']}: fx {k['fx']:g}, fy {k['fy']:g}, principal point {k['cx']:g}, "
                                       f"{k['cy']:g} (psctl depth's pinhole camera"
                                       + ("; psctl calibrate --K)" if square else ")")))
    if r.get("ambient"):
        decoded = ", decoded from sRGB" if r.get("ambient_srgb") else \
            ", decoded through its ICC profile" if r.get("ambient_profile") else ""
        t.add_row("ambient", escape(f"{r['ambient']}{decoded}, subtracted from every image"))
    con.print(t)
    print_notes(con, [n for n in r.get("notes", []) if not _in_rows(n)])
    if "check" in r:
        _render_check(con, r["check"])
        return
    # info is quick because it reads headers: a damaged image shows only when it is decoded
    con.print("[dim]headers read, and the ground truth; --check decodes every file (normals, lights and depth do "
              "as they read)[/]", highlight=False, soft_wrap=True)


def _render_check(con, c: dict) -> None:
    lo, med, hi = c["mean_range"]
    con.print(f"check: every file decoded in {c['seconds']:.1f} s, none damaged; mean linear value over the object "
              f"{lo:.3g} .. {hi:.3g} (median {med:.3g}) across images", highlight=False, soft_wrap=True)
    sat = [r["saturated"] for r in c["images"] if r["saturated"] is not None]
    if c["saturated_images"]:
        worst = max(c["images"], key=lambda r: r["saturated"] or 0.0)
        names = few(c["saturated_images"])
        con.print(escape(f"saturated: {len(c['saturated_images'])} of {len(c['images'])} images have over "
                         f"{SATURATED_SHARE:.0%} of the object at the top code value ({names}; most: {worst['image']}, "
                         f"{worst['saturated']:.1%})"), highlight=False, soft_wrap=True)
    elif sat and max(sat) > 0:
        con.print(f"saturated: at most {max(sat):.2%} of the object in any image", highlight=False, soft_wrap=True)
    elif sat:
        con.print("saturated: no pixel of the object at the top code value", highlight=False, soft_wrap=True)
    print_notes(con, c["notes"])


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def render_normals(r: dict, quiet: bool = False) -> None:
    """The human-readable summary of ``run_normals``'s report (Rich, stdout); notes only when ``quiet``."""
    con = _console()
    print_notes(con, r.get("notes", []))
    from psctl.eval import method_label

    # the method with the settings that change the normals (views, downsampling, precision)
    line = f"[bold]{escape(r['object'])}[/]: {method_label(r)}, {r['n_images']} images, " \
        f"{r['width']}x{r['height']}, {r['seconds']:.2f} s"
    if r["mae"] is not None:
        w = r["within"]
        line += (f"\n  mean angular error [bold]{r['mae']:.2f}°[/], median {r['median']:.2f}°, "
                 f"<11.25° {w['11.25']:.1%}, <22.5° {w['22.5']:.1%}, <30° {w['30']:.1%}")
    sp = r.get("spread")
    if sp:  # the ensemble: where its members disagree
        line += (f"\n  spread (angle between the ensemble's networks) mean {sp['mean']:.2f}°, "
                 f"90th percentile {sp['p90']:.2f}°")
        if sp.get("mae_top10") is not None and sp.get("mae_rest") is not None:
            line += f"; error where it is above that {sp['mae_top10']:.2f}°, elsewhere {sp['mae_rest']:.2f}°"
    if r.get("n_dark"):
        line += f"\n  {r['n_dark']} mask pixels are dark in every image (given the normal (0, 0, 1))"
    alb = r.get("albedo")
    if alb and alb.get("median") is not None:
        line += f"\n  albedo median (R, G, B) {', '.join(f'{v:.3g}' for v in alb['median'])}"
        pngs = [k.replace("_png", ".png") for k in ("albedo_png", "albedo_8bit_png") if k in r.get("outputs", {})]
        if pngs:  # the pictures' white, to read their values back
            line += f"; {' and '.join(pngs)} white at {alb['png_scale']:.3g}"
    con.print(line, highlight=False, soft_wrap=True)
    print_written(con, r["outputs"])


# headers of the narrow layout
SHORT = {"light direction (°)": "light", "intensity RE": "RE", "scored as the paper": "as paper"}


def _named(rows: list[tuple[str, list[str], str, str]]) -> list[tuple[str, list[str], str, str]]:
    """Rows whose label stands under its method's (indented: "  scored as the paper") named with
    it ("l2, scored as the paper"), for layouts where the row does not sit under its method's."""
    method, named = "", []
    for label, vals, avg, style in rows:
        if label.startswith("  "):
            label = f"{method}, {label.strip()}"
        elif label.endswith(" (psctl)"):
            method = label[:-len(" (psctl)")]
        named.append((label, vals, avg, style))
    return named


def _benchmark_table(rows: list[tuple[str, list[str], str, str]], names: list[str], width: int):
    """The paper's layout, objects as columns, when it fits ``width``; otherwise objects as rows
    (a folder benchmark of 16 objects at 80 columns): Rich would squeeze columns to nothing; and
    when neither fits (a comparison of several methods at 40 columns), each row as a line."""
    from rich.table import Table

    title = "mean angular error (degrees)"
    label_w = max(len("method"), *(len(r[0]) for r in rows))
    wide = 1 + (label_w + 3) + sum(max(len(n), 5) + 3 for n in names) + (5 + 3)
    if wide <= width:
        t = Table(title=title)
        t.add_column("method", min_width=6, overflow="fold")
        for name in names:
            t.add_column(escape(name), justify="right", min_width=5, no_wrap=True)
        t.add_column("avg", justify="right", style="bold", min_width=5, no_wrap=True)
        for label, vals, avg, style in rows:
            t.add_row(label, *vals, avg, style=style)
        return t
    rows = _named(rows)

    def short(label: str) -> str:  # "light direction (°) (LCNet)" -> "light" over "LCNet"
        if ", " in label:  # "l2, scored as the paper" -> "l2" over "as paper"
            head, rest = label.split(", ", 1)
            return f"{head}\n{SHORT.get(rest, rest)}"
        if not label.endswith(")"):
            return SHORT.get(label, label)
        head, source = label[:label.rindex("(")].strip(), label[label.rindex("(") + 1:-1]
        return f"{SHORT.get(head, head)}\n{source}"

    heads = [short(r[0]) for r in rows]
    name_w = min(16, max(len("object"), *map(len, names)))
    narrow = 1 + (name_w + 3) + sum(max(5, *map(len, h.split("\n"))) + 3 for h in heads)
    lights = any(r[0].startswith(tuple(SHORT)[:2]) for r in rows)  # sdps: the light rows' short names
    if narrow > width:  # each row a line: every number stays, none cut off
        from rich.console import Group
        from rich.text import Text

        return Group(Text(title, justify="center"),
                     *(Text(f"{label}: " + ", ".join(f"{n} {v}" for n, v in zip(names, vals)) + f", avg {avg}",
                            style=style) for label, vals, avg, style in rows))
    t = Table(title=title + ("; light: light direction error (degrees); RE: intensity error" if lights else ""))
    t.add_column("object", overflow="fold", min_width=name_w)
    for head, (_, _, _, style) in zip(heads, rows):
        t.add_column(head, justify="right", style=style, min_width=5)
    for i, name in enumerate(names):
        t.add_row(escape(name), *[r[1][i] for r in rows])
    t.add_section()
    t.add_row("avg", *[r[2] for r in rows], style="bold")
    return t


def _benchmark_rows(result: dict) -> list[tuple[str, list[str], str, str]]:
    """The rows of a ``psctl eval`` result as data: (label, one value per object, their average,
    style); the paper's rows end in "(paper)"."""
    from psctl.eval import method_label

    objs = result["objects"]
    # what ran, with the settings that change the numbers (views, downsampling, precision)
    rows = [(f"{method_label(result)} (psctl)", [_fmt(o["mae"]) for o in objs], _fmt(result["mean_mae"]), "")]
    paper = result.get("paper") or {}
    if paper:
        from psctl.eval import PAPER_DECIMALS

        # the paper's code scores mask pixels without ground truth at 90 degrees (pot2 has 73):
        # where that changes a number, psctl's score that way too, to set beside the paper's
        if any(o.get("mae_missing_as_90") not in (None, o["mae"]) for o in objs):
            rows.append(("  scored as the paper", [_fmt(o.get("mae_missing_as_90")) for o in objs],
                         _fmt(result.get("mean_mae_missing_as_90")), ""))
        vals = [paper.get(o["name"]) for o in objs]
        avg = result.get("mean_paper") if "mean_paper" in result else (
            float(np.mean(vals)) if all(v is not None for v in vals) else None)
        digits = PAPER_DECIMALS.get(result.get("paper_method"), 2)
        rows.append((f"{result.get('paper_method') or result['method']} (paper)",
                     ["-" if v is None else f"{v:.{digits}f}" for v in vals], _fmt(avg), "dim"))
    if "mean_light_mae" in result:  # sdps: the lights LCNet estimated, and the paper's LCNet
        paper_l = result.get("paper_lights") or {}
        for key, label, fmt in (("light_mae", "light direction (°)", _fmt),
                                ("intensity_re", "intensity RE", lambda x: "-" if x is None else f"{x:.3f}")):
            if all(o.get(key) is None for o in objs):  # no ground truth to score against
                continue
            rows.append((f"{label} (psctl)", [fmt(o.get(key)) for o in objs], fmt(result[f"mean_{key}"]), ""))
            if any((o.get("lights_refined") or {}).get("weight", 0) > 0 for o in objs):  # refined: LCNet's own too
                rows.append((f"{label} (LCNet)", [fmt(o.get(f"lcnet_{key}")) for o in objs],
                             fmt(result.get(f"mean_lcnet_{key}")), "dim"))
            if paper_l:
                vals = [paper_l.get(o["name"], {}).get(key) for o in objs]
                avg = float(np.mean(vals)) if all(v is not None for v in vals) else None
                rows.append((f"{label} (paper)", [fmt(v) for v in vals], fmt(avg), "dim"))
    return rows


def _object_notes(con, runs: list[dict]) -> None:
    """Under the table, the objects' notes that change what it means, one line per note (not per
    object): how the images were read where not as stored, ground truth that looks like another
    axis convention, images used other than asked, pixels not scored, what --method auto chose
    where it says why (no weights installed: l2) (the other notes are in
    --json and --out's reports). Of several runs' (a comparison), each note once."""
    from psctl.io.capture import READ_NOTES

    shown = (*READ_NOTES, "ground truth:", "images: --", "scoring:", "auto:")  # auto: what ran, where not asked
    by_note: dict[str, list[str]] = {}
    for run in runs:
        for o in run["objects"]:
            for n in o.get("notes", []):
                if n.startswith("scoring:") and len(runs) > 1:  # the same pixels for every method
                    n = n.split("; at 90 degrees")[0] + " (rows 'scored as the paper': at 90 degrees each)"
                if n.startswith(shown) and o["name"] not in by_note.get(n, []):
                    by_note.setdefault(n, []).append(o["name"])
    n_objects = len(runs[0]["objects"])
    for note, names in by_note.items():
        who = "every object" if len(names) == n_objects > 1 else ", ".join(names)
        con.print(escape(f"  {who}: {note}"), highlight=False)


def _near_lights_line(con, distance: float | None) -> None:
    if distance:  # not the paper's model: say so beside its rows
        con.print(f"near lights: each image divided by the falloff of point lights {distance:g} "
                  f"pixels from the object (--light-distance); the paper assumed distant lights", highlight=False)


def _paper_avg(runs: list[dict]) -> str:
    """Where a paper row has an avg on fewer than DiLiGenT's ten objects: what that avg is (the
    paper publishes its means over all ten), for the line under the table."""
    from psctl.eval import DILIGENT_OBJECTS

    n = len(runs[0]["objects"])
    if n >= len(DILIGENT_OBJECTS) or not any(run.get("mean_paper") is not None for run in runs):
        return ""
    return (f"; the paper's avg is of its numbers on these {n} object{'s' if n != 1 else ''}, as ours "
            f"(its published means are over DiLiGenT's {len(DILIGENT_OBJECTS)})")


def _seconds(secs: float) -> str:
    return f"{secs:.{2 if secs < 10 else 1}f} s"


def render_benchmark(result: dict) -> None:
    """The table of ``psctl eval``'s result, one row an object, with the paper's numbers where known."""
    con = _console()
    objs = result["objects"]
    # the path on a line of its own: in a table title Rich wraps it mid-word at a narrow terminal
    con.print(escape(f"{result['benchmark']}: {result['root']}"), highlight=False, soft_wrap=True)
    con.print(_benchmark_table(_benchmark_rows(result), [o["name"] for o in objs], con.width))
    n = {o["n_images"] for o in objs}
    con.print(f"{len(objs)} object{'s' if len(objs) != 1 else ''}, {'/'.join(map(str, sorted(n)))} images each, "
              f"{_seconds(sum(o['seconds'] for o in objs))}{_paper_avg([result])}", highlight=False)
    if result.get("outputs"):  # --out
        spread = ", spread maps" if any("spread" in o for o in objs) else ""
        con.print(escape(f"wrote {result['outputs']['eval.png']} (every object's normal and error maps{spread}), eval.json "
                         f"and one folder per object"), highlight=False)
    print_notes(con, result.get("notes", []))
    _near_lights_line(con, result.get("light_distance"))
    _object_notes(con, [result])


def _comparison_rows(result: dict) -> list[tuple[str, list[str], str, str]]:
    """A comparison's rows: each method's in turn, then the paper's rows of those methods, once each."""
    ours, papers = [], {}
    for run in result["runs"]:
        for row in _benchmark_rows(run):
            if row[0].endswith("(paper)"):
                papers.setdefault(row[0], row)  # ensemble's stand-in may be ps-fcn-n's own row
            else:
                ours.append(row)
    return ours + list(papers.values())


def benchmark_markdown(result: dict) -> str:
    """The table of a ``psctl eval`` result (one method, or ``compare_methods``' several) as a
    Markdown table, objects as columns, the average last: ``psctl eval --markdown`` for a
    README or a paper's draft. Values as the terminal table prints them."""
    rows = _comparison_rows(result) if "runs" in result else _benchmark_rows(result)
    names = [o["name"] for o in (result["runs"][0] if "runs" in result else result)["objects"]]

    def cell(text: str) -> str:  # a | or a line break inside a cell would end it
        return " ".join(visible(text).split()).replace("|", "\\|")

    lines = ["| method | " + " | ".join(cell(n) for n in names) + " | avg |",
             "| --- |" + " ---: |" * (len(names) + 1)]
    for label, vals, avg, _ in _named(rows):  # no indentation in Markdown: each row named with its method
        lines.append(f"| {cell(label)} | " + " | ".join(vals) + f" | {avg} |")
    return "\n".join(lines) + "\n"


def render_benchmark_markdown(result: dict) -> None:
    """``psctl eval --markdown``: the table on stdout, the notes on stderr (stdout stays a table)."""
    import sys

    from psctl.errors import console

    sys.stdout.write(benchmark_markdown(result))
    runs = result.get("runs") or [result]
    err = console(stderr=True)
    paper_avg = _paper_avg(runs)
    print_notes(err, _run_notes(result) + ([paper_avg[2].upper() + paper_avg[3:]] if paper_avg else []))
    _object_notes(err, runs)


def _run_notes(result: dict) -> list[str]:
    """A result's notes about its run(s): a comparison's own, then each run's, once where every
    run has it (the root's), else under its method's name. One run: its notes as they are."""
    runs = result.get("runs")
    if runs is None:
        return list(result.get("notes", []))
    run_notes = [run.get("notes", []) for run in runs]
    common = [n for n in run_notes[0] if all(n in other for other in run_notes[1:])]
    return [*result.get("notes", []), *common] + [f"{method}: {n}" for method, own in zip(result["methods"], run_notes)
                                                  for n in own if n not in common]


def render_comparison(result: dict) -> None:
    """The table of ``psctl eval -m A -m B ...`` (``psctl.eval.compare_methods``): each method's
    rows in turn, then the paper's rows of those methods, each once."""
    con = _console()
    runs = result["runs"]
    objs = runs[0]["objects"]
    con.print(escape(f"{result['benchmark']}: {result['root']}"), highlight=False, soft_wrap=True)
    con.print(_benchmark_table(_comparison_rows(result), [o["name"] for o in objs], con.width))
    n = {o["n_images"] for run in runs for o in run["objects"]}
    times = ", ".join(f"{run['method']} {_seconds(sum(o['seconds'] for o in run['objects']))}" for run in runs)
    con.print(f"{len(objs)} object{'s' if len(objs) != 1 else ''}, {'/'.join(map(str, sorted(n)))} images each; "
              f"{times}{_paper_avg(runs)}", highlight=False)
    if result.get("outputs"):
        con.print(escape(f"wrote {result['outputs']['compare.png']} (each method's eval.png, one above the other), "
                         f"compare.json and one folder per method"), highlight=False)
    print_notes(con, _run_notes(result))
    _near_lights_line(con, runs[0].get("light_distance"))
    _object_notes(con, runs)

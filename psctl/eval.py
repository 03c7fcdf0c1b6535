"""Benchmark tables: run a method over every object of a benchmark root."""

from __future__ import annotations

import contextlib
import inspect
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from psctl.api import OUTPUTS_LIST, ProgressFactory, run_normals
from psctl.errors import PsctlError, check_bool, check_path, check_progress
from psctl.io.atomic import OutputBatch

if TYPE_CHECKING:
    from psctl.io.capture import Capture

# Mean angular error (degrees, all 96 images) published in the PS-FCN TPAMI paper, for the
# objects of the DiLiGenT development split (L2: DiLiGenT's own baseline, to two decimals; the
# networks to one, as the issues give them). Shown beside our numbers, never mixed with them,
# and printed with the decimals published (PAPER_DECIMALS: 4.10 and 2.8, not 4.1 and 2.80).
PAPER_DECIMALS = {"l2": 2, "ps-fcn": 1, "ps-fcn-n": 1, "sdps": 1}
PAPER_DILIGENT = {
    "l2": {"ball": 4.10, "cat": 8.41, "pot1": 8.89, "bear": 8.39, "pot2": 14.65},
    "ps-fcn": {"ball": 2.8, "cat": 6.2, "pot1": 7.1, "bear": 7.6, "pot2": 7.3},
    "ps-fcn-n": {"ball": 2.7, "cat": 4.8, "pot1": 6.2, "bear": 7.7, "pot2": 7.2},
    "sdps": {"ball": 2.8, "cat": 8.1, "pot1": 8.1, "bear": 6.9, "pot2": 7.5},
}

# Methods the paper has no row for, and the row shown beside them instead: the ensemble averages
# psctl's PS-FCN and PS-FCN+N, so the paper's better calibrated network is the one to beat.
PAPER_STAND_IN = {"ensemble": "ps-fcn-n"}

# LCNet's light estimates on the same objects, from the same paper: mean light direction error
# (degrees) and scale-invariant intensity relative error.
PAPER_DILIGENT_LIGHTS = {
    "ball": {"light_mae": 3.27, "intensity_re": 0.039}, "cat": {"light_mae": 4.08, "intensity_re": 0.095},
    "pot1": {"light_mae": 5.44, "intensity_re": 0.058}, "bear": {"light_mae": 3.47, "intensity_re": 0.061},
    "pot2": {"light_mae": 2.87, "intensity_re": 0.048},
}

BENCHMARKS = ("diligent", "folder")
# DiLiGenT's ten objects (folders ballPNG, ...): a root of none of them is read as --benchmark folder
DILIGENT_OBJECTS = ("ball", "cat", "pot1", "bear", "pot2", "buddha", "goblet", "reading", "cow", "harvest")


def default_diligent_root() -> Path:
    """$PSCTL_DATA/DiLiGenT/pmsData (or .../diligent/pmsData, as in psctl's development data),
    then ~/.cache/psctl/DiLiGenT/pmsData; the error lists every place looked in."""
    candidates = []
    if os.environ.get("PSCTL_DATA"):
        data = Path(os.environ["PSCTL_DATA"])
        candidates += [data / "DiLiGenT" / "pmsData", data / "diligent" / "pmsData"]
    with contextlib.suppress(RuntimeError):  # no home folder (a container's arbitrary user id)
        candidates.append(Path.home() / ".cache" / "psctl" / "DiLiGenT" / "pmsData")
    for c in candidates:
        if c.is_dir():
            return c
    raise PsctlError(
        None,
        f"DiLiGenT not found in {', '.join(map(str, candidates))}. Get it from the DiLiGenT benchmark page "
        "(Shi et al., 'A Benchmark Dataset and Evaluation for Non-Lambertian and Uncalibrated Photometric "
        "Stereo'), unpack it so that a folder above holds ballPNG/, catPNG/, ... ($PSCTL_DATA sets where "
        "psctl looks first), or pass --root DIR (a pmsData or pmsData_crop folder); psctl never downloads at run time",
    )


def run_benchmark(benchmark: str, root: str | os.PathLike | None = None, method: str = "auto",
                  n_images: int | None = None, seed: int | None = None,
                  out: str | os.PathLike | None = None,
                  progress: ProgressFactory | None = None, weights: str | os.PathLike | None = None,
                  device: str = "auto", lcnet: str | os.PathLike | None = None, views: int = 1,
                  refine: bool = True, falloff: str | None = None, roll: bool | None = None,
                  encoding: str = "auto", light_distance: float | None = None, downsample: int = 1,
                  precision: str = "float32", albedo: bool = False, batch: OutputBatch | None = None,
                  snap: bool = True, reuse: dict | None = None) -> dict:
    """Evaluate ``method`` on every object under ``root``.

    Returns {"benchmark", "root", "method", "objects": [{"name", "mae", "median", "mae_missing_as_90",
    "n_images", "n_dark", "seconds", "notes", "provenance"}], "mean_mae", "mean_mae_missing_as_90" (None where an
    object has no mask file), "paper",
    "paper_method", "light_distance", "views",
    "downsample", "precision", "notes"}
    (docs/formats.md has each key; "paper": the published numbers of
    "paper_method", the method itself or, for ``ensemble``, the paper's PS-FCN+N). With ``out``,
    each object's outputs go to out/<object>/, and out/eval.png (every object's normal and error
    maps, and the ensemble's spread maps, ``psctl.io.report.benchmark_sheet``)
    and out/eval.json (this result) join them; the result then has "outputs".
    ``weights`` (a file), ``device``, ``views``, ``downsample`` and ``precision`` are passed on to the network methods, ``lcnet``,
    ``refine``, ``falloff``, ``roll`` and ``snap`` to sdps; ``encoding`` and ``light_distance`` (pixels,
    near point lights: ``psctl.api.run_normals``) to every object's capture.
    sdps also gives each object's "light_mae" and "intensity_re" (the lights used, refined or
    not), "lcnet_light_mae" and "lcnet_intensity_re" (LCNet's own) and "lights_refined", the
    means "mean_light_mae", "mean_intensity_re", "mean_lcnet_light_mae" and
    "mean_lcnet_intensity_re", and "paper_lights" (None where the folder has no ground truth).
    The ensemble gives each object's "spread" (its report's: ``psctl.api.spread_stats``).
    "notes": about the run (with ``out``: object folders of an earlier run left there).
    ``albedo`` (with ``out``): each object's folder also gets its albedo maps, as ``psctl
    normals --albedo`` writes them (every object's method must have lights: not ups-fcn).
    ``batch`` (with ``out``): stage the files into this ``OutputBatch``, which its owner commits
    (``compare_methods``: several runs' files appear together), instead of one of its own.
    ``reuse``: passed to every object's ``psctl.api.run_normals`` (``compare_methods``: the
    ensemble takes its members' normals from the runs of them).
    """
    from psctl.io.capture import root_notes
    from psctl.io.images import write_image
    from psctl.io.report import benchmark_sheet, object_panel, sheet_layout, write_json
    from psctl.models import check_downsample, check_precision
    from psctl.refine import refine_config
    from psctl.symmetry import check_views

    refine_config(falloff, roll)  # a bad value stops before any object runs
    views, downsample = check_views(views), check_downsample(downsample)  # ints: eval.json must serialise them
    precision = check_precision(precision)
    check_progress(progress)
    albedo, snap = check_bool("albedo", albedo), check_bool("snap", snap)
    for name, value in (("root", root), ("out", out), ("weights", weights), ("lcnet", lcnet)):
        check_path(name, value, optional=True)
    benchmark, root, caps, names = _benchmark_objects(benchmark, root, encoding)
    folders = [cap.path for cap in caps]
    if albedo and out is not None:  # before any object runs, not minutes in
        _check_albedo(caps, method, weights, lcnet)
    if out is not None:  # an empty one was refused by check_path above
        _check_out(out, root, EVAL_FILES, weights, lcnet)
    objects = []
    used = []  # `auto` can resolve differently per object (calibrated or not)
    precisions, used_views, used_k = [], set(), set()  # what each object's run used
    panels = []  # with --out: each object's small picture for eval.png
    # with --out every object's files appear together at the end, or none do
    own = OutputBatch(out) if out is not None and batch is None else contextlib.nullcontext(
        None if out is None else batch)
    with own as batch:
        for folder, name in zip(folders, names):
            arrays = {} if out is not None else None
            r = run_normals(folder, method=method, out=None if out is None else Path(out) / name,
                            n_images=n_images, seed=seed, write=out is not None, progress=progress,
                            weights=weights, device=device, lcnet=lcnet, views=views, refine=refine,
                            falloff=falloff, roll=roll, batch=batch, encoding=encoding,
                            light_distance=light_distance, arrays=arrays, downsample=downsample,
                            precision=precision, albedo=albedo and out is not None, snap=snap, reuse=reuse)
            _collect(objects, used, r)
            precisions.append(r["precision"])  # float32 for l2 (float64), whatever was asked
            used_views.add(r["views"])  # 1 for l2, whatever was asked
            used_k.add(r["downsample"])
            if arrays is not None:
                panels.append(object_panel(r["object"], r["mae"], arrays["normals"], arrays["error"],
                                           arrays["scored"], height=sheet_layout(len(folders))[1],
                                           spread=arrays.get("spread")))
        # what ran: the objects' own values where they agree (l2 runs one view at full size)
        result = _table(benchmark, root, objects, used, light_distance,
                        used_views.pop() if len(used_views) == 1 else views,
                        used_k.pop() if len(used_k) == 1 else downsample, " + ".join(dict.fromkeys(precisions)),
                        {n for f, n in zip(folders, names) if f.name == n + "PNG"})
        result["notes"] += root_notes(root)
        from psctl.api import unused_note, unused_options
        from psctl.models import check_device_name

        # options the run ignored: said once for the table, as psctl normals says them; only those every
        # object's method ignored (auto may run sdps on one object, which uses --no-refine, l2 on another)
        ignored = [dict(unused_options(m, refine, views, downsample, precision, falloff, roll, snap)) for m in set(used)]
        for k, why in ignored[0].items() if ignored else ():
            if all(k in other for other in ignored):
                result["notes"].append(unused_note(k, why, precision))
        if set(used) == {"l2"} and check_device_name(device).startswith("cuda"):
            result["notes"].append(f"device: l2 solves with NumPy on the CPU; --device {device} unused")
        if albedo and out is None:
            result["notes"].append("albedo: --albedo writes each object's albedo maps under --out; unused without it")
        if out is not None:
            # object folders an earlier run wrote there (each holds psctl normals' list of outputs),
            # not in this run: left as they are, but never silently beside a table without them
            earlier = sorted(d.name for d in Path(out).iterdir() if d.is_dir() and d.name not in names
                             and (d / OUTPUTS_LIST).is_file()) if Path(out).is_dir() else []
            if earlier:
                result["notes"].append(
                    f"outputs: {out} also holds {', '.join(earlier[:5])}{' ...' if len(earlier) > 5 else ''} from an "
                    f"earlier run, not in this run's eval.json and eval.png (left as they are)")
            result["notes"] += _other_run_notes(Path(out), "eval")
        if batch is not None:
            from psctl.io.atomic import replaced_notes, write_outputs_list

            result["outputs"] = {"eval.png": os.path.abspath(Path(out) / "eval.png"),
                                 "eval.json": os.path.abspath(Path(out) / "eval.json")}
            # a file of the user's replaced, here or in an object's folder: said on the terminal too
            result["notes"] += [n for o in objects for n in o["notes"] if n.startswith("outputs: replaced ")]
            result["notes"] += replaced_notes(Path(out), EVAL_FILES, "eval")
            stage = batch.stage(out).path
            write_outputs_list(stage, EVAL_FILES, "eval")
            title = f"{method_label(result)}  MEAN {result['mean_mae']:.2f}°" + (
                f"  LIGHTS {result['mean_light_mae']:.2f}°" if result.get("mean_light_mae") is not None else "") + (
                f"  D {light_distance:g}" if light_distance is not None else "") + f"  ({root.resolve().name})" + (
                "  ROWS: NORMALS, ERROR, SPREAD" if any(p["spread"] is not None for p in panels) else "")
            write_image(stage / "eval.png", benchmark_sheet(panels, title, per_row=sheet_layout(len(folders))[0]), "uint8")
            write_json(stage / "eval.json", result)
    return result


EVAL_FILES = ("eval.png", "eval.json")


def _other_run_notes(out: Path, kind: str) -> list[str]:
    """A note when ``out`` holds what the other kind of run wrote there before (``kind`` "eval": an
    earlier comparison's compare.json, compare.png and method folders; "compare": an earlier
    single-method eval's eval.json, eval.png and object folders): left as they are, but said, as
    an earlier run of the same kind's leftovers are (a QA helper's finding)."""
    from psctl.io.atomic import outputs_list

    other, files, folder_list = (("compare", COMPARE_FILES, outputs_list("eval")) if kind == "eval"
                                 else ("eval", EVAL_FILES, OUTPUTS_LIST))
    if not out.is_dir() or not (out / outputs_list(other)).is_file():
        return []
    held = [f for f in files if (out / f).is_file()]
    held += sorted(d.name + "/" for d in out.iterdir() if d.is_dir() and (d / folder_list).is_file())
    if not held:
        return []
    what = "comparison's (several methods)" if other == "compare" else "single-method eval's"
    return [f"outputs: {out} also holds an earlier {what} {', '.join(held[:6])}{' ...' if len(held) > 6 else ''} "
            f"(left as they are)"]
COMPARE_FILES = ("compare.png", "compare.json")


def method_names(given: Sequence[str]) -> list[str]:
    """Method names as given (``-m a -m b``, ``-m a,b``; any case, spaces around them) -> each
    once, lower case, in order; an unknown or empty one is an error."""
    from psctl.api import METHODS

    names = []
    for g in given:
        if not isinstance(g, str):
            raise PsctlError(None, f"unknown --method {g!r}; choose from {', '.join(METHODS)}")
        names += [m.strip().lower() for m in g.split(",")]
    for m in names:
        if m not in METHODS:
            raise PsctlError(None, f"unknown --method {m!r}; choose from {', '.join(METHODS)}")
    return list(dict.fromkeys(names))


# what compare_methods passes on to each run_benchmark (the rest it sets itself)
_RUN_OPTIONS = set(inspect.signature(run_benchmark).parameters) - {"benchmark", "root", "method", "out", "progress",
                                                                    "batch", "reuse"}


def compare_methods(benchmark: str, methods: Sequence[str], root: str | os.PathLike | None = None,
                    out: str | os.PathLike | None = None, progress: ProgressFactory | None = None,
                    **options: Any) -> dict:
    """Run several methods over the same benchmark, for one table with a row per method
    (``psctl eval -m l2 -m ps-fcn -m ps-fcn-n``, the layout of the paper's tables).

    ``methods``: names as ``run_benchmark``'s ``method`` (repeats dropped); ``options``: the
    other arguments of ``run_benchmark`` (``views``, ``device``, ...), the same for every method;
    ``weights`` is refused (it names one network's file). Every method is resolved on every
    object before any runs, so that a missing weights file stops the comparison at once.
    Returns {"benchmark", "root", "methods", "runs": [``run_benchmark``'s result per method],
    "notes"}. With ``out``: OUT/<method>/ holds what ``psctl eval -m METHOD --out
    OUT/<method>`` writes, OUT/compare.png their eval.png one above the other, and
    OUT/compare.json this result (then with "outputs"); they all appear together, or none does.
    """
    from psctl.api import METHODS, NETWORKS, resolve_method
    from psctl.infer import ENSEMBLE, REUSED_NOTE, KeptNormals
    from psctl.models.weights import installed_path, no_weights_error
    from psctl.io.atomic import outputs_list, replaced_notes, write_outputs_list

    if isinstance(methods, str) or not isinstance(methods, Sequence) or not methods:
        raise PsctlError(None, f"methods must be a list of method names ({', '.join(METHODS)}), not {methods!r}")
    methods = method_names(methods)
    for key in options:
        if key not in _RUN_OPTIONS:
            raise TypeError(f"compare_methods() got an unexpected keyword argument {key!r}")
    check_path("weights", options.get("weights"), optional=True)
    if options.get("weights") is not None:
        raise PsctlError(options["weights"], "--weights names one network's file; a comparison runs each method "
                                             "with its installed weights (run psctl eval once per weights file)")
    check_path("out", out, optional=True)
    encoding, lcnet = options.get("encoding", "auto"), options.get("lcnet")
    benchmark, root, caps, _ = _benchmark_objects(benchmark, root, encoding)
    ran: dict[tuple, str] = {}  # what each method runs on every object: two names of one run (auto, ensemble) run once
    notes = []
    for m in list(methods):  # a missing weights file or light file now, not after the first method's minutes
        used = []
        for cap in caps:
            used.append(resolve_method(m, cap.calibrated, None, lcnet, cap.path / "light_directions.txt")[0])
            if used[-1] in NETWORKS and installed_path(used[-1]) is None:  # resolve_method leaves this to loading
                raise no_weights_error(used[-1])
        if tuple(used) in ran:
            methods.remove(m)
            notes.append(f"methods: {m} runs what {ran[tuple(used)]} runs on every object "
                         f"({', '.join(dict.fromkeys(used))}); compared once")
            continue
        ran[tuple(used)] = m
        if options.get("albedo") and out is not None:
            _check_albedo(caps, m, None, lcnet)
    if out is not None:
        _check_out(out, root, COMPARE_FILES, None, lcnet)
        for m in methods:
            _check_out(Path(out) / m, root, EVAL_FILES, None, lcnet)
    # the ensemble's members run as methods of their own too: each network once per object (a
    # result held in memory until a later run takes it, within KeptNormals' budget; helper-165: 10 of
    # the dev split's 20 network runs were repeats, the ensemble's minutes)
    runs_of = [set(k) for k, m in ran.items() if m in methods]
    reuse = KeptNormals() if any("ensemble" in r for r in runs_of) and \
        sum(bool(r & {"ensemble", *ENSEMBLE}) for r in runs_of) > 1 else None
    with OutputBatch(out) if out is not None else contextlib.nullcontext() as batch:
        runs = [run_benchmark(benchmark, root, method=m, out=None if out is None else Path(out) / m,
                              progress=progress, batch=batch, reuse=reuse, **options) for m in methods]
        took = [run["method"] for run in runs
                if any(REUSED_NOTE in n for o in run["objects"] for n in o["notes"])]
        if took:  # its seconds would read as the ensemble's speed
            notes.append(f"methods: {' and '.join(took)} took the normals of the networks that ran before "
                         f"{'it' if len(took) == 1 else 'them'} on the same inputs from those runs (each network "
                         f"ran once per object): {'its' if len(took) == 1 else 'their'} seconds leave that time out")
        result = {"benchmark": benchmark, "root": os.path.abspath(root), "methods": methods, "runs": runs,
                  "notes": notes}
        if batch is not None:
            from psctl.io.images import read_image, write_image
            from psctl.io.report import stack_sheets, write_json

            # method folders an earlier comparison wrote there, not in this one: left, but said
            earlier = sorted(d.name for d in Path(out).iterdir() if d.is_dir() and d.name not in methods
                             and (d / outputs_list("eval")).is_file()) if Path(out).is_dir() else []
            if earlier:
                result["notes"].append(f"outputs: {out} also holds {', '.join(earlier)} from an earlier run, not in "
                                       f"this run's compare.json and compare.png (left as they are)")
            result["notes"] += _other_run_notes(Path(out), "compare")
            result["notes"] += replaced_notes(Path(out), COMPARE_FILES, "compare")
            sheets = [read_image(next(s.path for s in batch.stagings if s.out_dir == Path(out) / m) / "eval.png")[0]
                      for m in methods]
            result["outputs"] = {f: os.path.abspath(Path(out) / f) for f in COMPARE_FILES}
            stage = batch.stage(out).path
            write_outputs_list(stage, COMPARE_FILES, "compare")
            write_image(stage / "compare.png", stack_sheets(sheets), "uint8")
            write_json(stage / "compare.json", result)
    return result


def _benchmark_objects(benchmark: str, root: str | os.PathLike | None,
                       encoding: str) -> tuple[str, Path, list["Capture"], list[str]]:
    """(benchmark, root, object captures, object names) of a benchmark, every object checked to
    be scorable before any is run (and before any output is written)."""
    from psctl.io.capture import GT_FILES, find_objects, object_name, open_capture

    if not isinstance(benchmark, str):
        raise PsctlError(None, f"benchmark must be one of {', '.join(BENCHMARKS)}, not {benchmark!r}")
    benchmark = benchmark.lower()
    if benchmark not in BENCHMARKS:
        raise PsctlError(None, f"unknown benchmark {benchmark!r}; choose from {', '.join(BENCHMARKS)}")
    check_path("root", root, optional=True)
    if root is None:
        if benchmark != "diligent":
            raise PsctlError(None, f"--benchmark {benchmark} needs --root DIR")
        root = default_diligent_root()
    root = Path(root)
    folders = find_objects(root)
    caps = [open_capture(folder, encoding) for folder in folders]
    for cap in caps:
        if cap.gt_path is None:
            raise PsctlError(cap.path, "has no ground truth normals (" + " / ".join(GT_FILES) + ")")
    names = [object_name(f) for f in folders]
    if benchmark == "diligent" and not any(n in DILIGENT_OBJECTS for n in names):
        benchmark = "folder"  # one's own objects under the default --benchmark: not headed "diligent"
    for name in dict.fromkeys(names):
        same = [f.name for f, n in zip(folders, names) if n == name]
        if len(same) > 1:  # one column (and one out/<object>/ folder) each
            raise PsctlError(root, f"holds {len(same)} objects named {name} ({', '.join(same)}); rename all but one")
    return benchmark, root, caps, names


def _check_albedo(caps: list["Capture"], method: str, weights: str | os.PathLike | None,
                  lcnet: str | os.PathLike | None) -> None:
    """--albedo needs lights: refuse, before any object runs, a method that resolves to ups-fcn."""
    from psctl.api import resolve_method, ups_fcn_albedo_message

    for cap in caps:
        if resolve_method(method, cap.calibrated, weights, lcnet, cap.path / "light_directions.txt")[0] == "ups-fcn":
            raise PsctlError(cap.path if weights is None else weights,
                             ups_fcn_albedo_message(method, weights, cap.calibrated))


def _check_out(out: str | os.PathLike, root: Path, files: tuple[str, ...], weights: str | os.PathLike | None,
               lcnet: str | os.PathLike | None) -> None:
    """Refuse, before any work, an --out that is the root, holds a capture, or would replace a
    file the run reads with one of ``files`` (written into OUT itself)."""
    from psctl.io.atomic import check_inputs_kept, check_output_dir
    from psctl.io.capture import holds_capture

    if os.path.realpath(out) == os.path.realpath(root):  # realpath: a link loop gets its own message later
        raise PsctlError(out, "is the benchmark root: its folders are inputs; choose another --out")
    if holds_capture(out):  # eval.png and eval.json go into OUT itself, beside someone's images
        raise PsctlError(out, f"holds a capture (images, an image list, a mask or ground truth): psctl eval "
                              f"writes {files[0]} there; choose another --out")
    check_inputs_kept(out, files, (("--weights", weights), ("--lcnet", lcnet)))
    check_output_dir(out)


def method_label(result: dict) -> str:
    """The method of a ``run_benchmark`` result with the settings that change its numbers, for the
    table and eval.png: "ensemble, 8 views, 1/2 size, bf16" (the defaults are left out)."""
    parts = [result["method"]]
    if result.get("views", 1) > 1:
        parts.append(f"{result['views']} views")
    if result.get("downsample", 1) > 1:
        parts.append(f"1/{result['downsample']} size")
    if result.get("precision", "float32") != "float32":
        parts.append(result["precision"])
    return ", ".join(parts)


def _table(benchmark: str, root: Path, objects: list[dict], used: list[str], light_distance: float | None,
           views: int = 1, downsample: int = 1, precision: str = "float32",
           as_diligent: set[str] | None = None) -> dict:
    """The run's JSON object from its objects' rows. ``as_diligent``: the objects whose folders
    are named as DiLiGenT's (ballPNG): only those get the paper's numbers (None: all)."""
    used_method = " + ".join(dict.fromkeys(used))  # one name unless the objects differ
    paper_method = PAPER_STAND_IN.get(used_method, used_method)
    paper = PAPER_DILIGENT.get(paper_method, {}) if benchmark == "diligent" else {}
    # a folder "cat" of one's own data is not DiLiGenT's catPNG: no published number beside it
    unlike = [o["name"] for o in objects if as_diligent is not None and o["name"] not in as_diligent
              and (o["name"] in paper or o["name"] in PAPER_DILIGENT_LIGHTS)] if benchmark == "diligent" else []
    paper = {k: v for k, v in paper.items() if k not in unlike}
    result = {
        "benchmark": benchmark,
        "root": os.path.abspath(root),
        "method": used_method,
        "objects": objects,
        "mean_mae": float(np.mean([o["mae"] for o in objects])),
        # as the authors' code scores: mask pixels without a ground-truth normal at 90 degrees
        # (None where an object has no mask file: no mask to count over)
        "mean_mae_missing_as_90": None if any(o["mae_missing_as_90"] is None for o in objects) else
        float(np.mean([o["mae_missing_as_90"] for o in objects])),
        "light_distance": None if light_distance is None else float(light_distance),
        "views": views,
        "downsample": downsample,
        "precision": precision,
        "paper": {o["name"]: paper[o["name"]] for o in objects if o["name"] in paper},
        # whose published numbers "paper" holds
        "paper_method": paper_method if any(o["name"] in paper for o in objects) else None,
        # the mean of the paper's numbers over these objects (the table's avg), None unless all have one
        "mean_paper": float(np.mean([paper[o["name"]] for o in objects]))
        if objects and all(o["name"] in paper for o in objects) else None,
        "notes": [],  # about the run as a whole (each object's are in its row)
    }
    if unlike:
        result["notes"].append(f"paper: {', '.join(unlike)} not in folders named as DiLiGenT's ({unlike[0]}PNG): "
                               f"no published numbers beside {'them' if len(unlike) > 1 else 'it'} (--benchmark folder "
                               f"for data of your own)")
    if any("light_mae" in o for o in objects):
        for key in ("light_mae", "intensity_re", "lcnet_light_mae", "lcnet_intensity_re"):
            vals = [o.get(key) for o in objects]
            result[f"mean_{key}"] = None if any(v is None for v in vals) else float(np.mean(vals))
        lights = {k: v for k, v in PAPER_DILIGENT_LIGHTS.items() if k not in unlike} if benchmark == "diligent" else {}
        result["paper_lights"] = {o["name"]: lights[o["name"]] for o in objects if o["name"] in lights}
    return result


def _collect(objects: list[dict], used: list[str], r: dict) -> None:
    """One object's row of the table from its ``run_normals`` report."""
    used.append(r["method"])
    objects.append({"name": r["object"], "mae": r["mae"], "median": r["median"],
                    "mae_missing_as_90": r["mae_missing_as_90"],
                    "n_images": r["n_images"], "seconds": r["seconds"], "n_dark": r["n_dark"], "notes": r["notes"]})
    objects[-1]["provenance"] = r["provenance"]  # the weights (sha256) and versions behind the row
    if "images_used" in r:  # an --images subset: which images, to repeat the run
        objects[-1].update(images_used=r["images_used"], selection=r["selection"], seed=r["seed"])
    if "spread" in r:  # the ensemble: where its networks disagree
        objects[-1]["spread"] = r["spread"]
    if "light_mae" in r:  # sdps: the lights LCNet estimated
        objects[-1].update(light_mae=r["light_mae"], intensity_re=r["intensity_re"],
                           lcnet_light_mae=r["lcnet_light_mae"], lcnet_intensity_re=r["lcnet_intensity_re"],
                           lights_refined=r["lights_refined"])

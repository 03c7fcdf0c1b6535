"""How the release weights were made, stage by stage, and a replay of it from scratch.

    python -m psctl.lineage plan weights/ps_fcn_n.pt           # the stages, in order, with their costs
    python -m psctl.lineage rebuild weights/ps_fcn_n.pt --out runs/rebuild [--device cuda] [--max-minutes 9]

The release files were not trained by one recipe: each is the end of a chain of fine-tuning
stages (and two parameter averages), chosen one at a time by rules on synthetic sets
(docs/training.md, docs/weights-history.md). ``weights/lineage.yaml`` lists every stage: its
full recipe as the stage's own weights recorded it, the stage it started from, the sample count
of the file that was kept, and where and how it ran. ``benchmarks/lineage_from_git.py`` wrote it
from the weights committed over the project's history and checks each link against the child's
record of its start.

``rebuild`` trains the stages a release file needs, in order, each one from the previous one's
result (``train.init``), stopping each at its kept sample count with its own learning-rate
schedule: stage ``S`` is the run folder ``OUT/S`` and its result ``OUT/S/model.pt`` (an average:
``OUT/S/best.pt``). It is resumable: run it again with the same arguments and it continues the
unfinished stage (``--max-minutes`` splits it into commands of a fixed length, as on the GPU
machine). It replays the recipes with today's code, so the result is not the shipped file bit for
bit: the synthetic stream and the training loop have changed since the early stages, and the
early stages ran on a CPU in float32 or bf16 where a replay on a GPU runs bf16.

This module must not import OpenImageIO: it runs on the GPU machine, which lacks it.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from psctl.errors import PsctlError

LINEAGE = Path(__file__).resolve().parents[1] / "weights" / "lineage.yaml"
RECIPE_SECTIONS = ("method", "model", "normalization", "data", "train", "val", "lcnet")
HEADER = """\
# Every training stage behind the release weights (written by benchmarks/lineage_from_git.py from
# the weights committed over the project's history; do not edit by hand). `ships` names each
# release file's last stage; a stage has the stage it started from (`init`, null: from scratch) or
# the stages it averages (`average`), the sample count of the file that was kept (`samples`), and
# its recipe as its own weights recorded it (two stages that never shipped: their configs/ file as
# load_config reads it; `source` says which), train.init left out: the replay sets it.
# Replay: python -m psctl.lineage rebuild weights/ps_fcn_n.pt --out runs/rebuild (docs/training.md).
"""
# a replay's mechanics in seconds (tests, `--tiny`): every stage at tiny sizes, procedural shapes
TINY = {"data": {"size": 16, "pool": 1, "shapes": {"blobby": 1.0}, "require_meshes": False, "scale": None,
                 "interreflection": None},
        "train": {"batch_size": 2, "images_per_sample": 4, "crop": 8, "samples": 4, "log_every": 1,
                  "val_every": 4, "amp": "none", "checkpoint_minutes": 5.0},
        "val": {"samples": 2, "size": 8, "images": 4, "batch_size": 2, "data": {}}}


def load_lineage(path: str | os.PathLike | None = None) -> dict:
    """Read a lineage manifest (default: weights/lineage.yaml) and check it: each stage trains
    (a method, a recipe mapping, a positive sample count, ``init`` a stage or null) or averages (a
    list of at least two stages); ``ships`` maps files to stages; no stage depends on itself.
    Errors name the file and the stage."""
    import yaml

    given = path is not None
    path = Path(path) if given else LINEAGE
    if not path.is_file():
        raise PsctlError(path, "lineage manifest is missing" if given else
                         "no lineage manifest here (it is weights/lineage.yaml of psctl's source checkout or sdist, "
                         "not in the wheel): pass --lineage FILE")
    try:
        lineage = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, OSError, UnicodeDecodeError) as e:
        raise PsctlError(path, f"cannot be read as a lineage manifest ({' '.join(str(e).split())[:160]})") from None
    if not (isinstance(lineage, dict) and isinstance(lineage.get("stages"), dict) and isinstance(lineage.get("ships"), dict)):
        raise PsctlError(path, "is not a lineage manifest (needs 'ships' and 'stages' mappings)")
    stages = lineage["stages"]
    for sid, s in stages.items():
        if not isinstance(s, dict) or ("recipe" in s) == ("average" in s):
            raise PsctlError(path, f"stage {sid!r} must have either a recipe or an average")
        if not isinstance(s.get("method"), str):
            raise PsctlError(path, f"stage {sid!r} names no method")
        if "recipe" in s:
            n = s.get("samples")
            if not isinstance(s["recipe"], dict) or not (isinstance(n, int) and not isinstance(n, bool) and n > 0):
                raise PsctlError(path, f"stage {sid!r} needs a recipe mapping and a positive whole 'samples' "
                                       f"(the kept file's count)")
            parents = [s.get("init")]
        else:
            parents = s["average"]
            if not (isinstance(parents, list) and len(parents) >= 2):
                raise PsctlError(path, f"stage {sid!r}: 'average' must list at least two stages")
        for parent in parents:
            if parent is not None and (not isinstance(parent, str) or parent not in stages):
                raise PsctlError(path, f"stage {sid!r} starts from {parent!r}, which is not a stage")
    for file, sid in lineage["ships"].items():
        if not isinstance(sid, str) or sid not in stages:
            raise PsctlError(path, f"{file} ships stage {sid!r}, which is not a stage")
    for sid in stages:
        stages_for(lineage, sid, path)  # a cycle raises
    lineage["path"] = str(path)
    return lineage


def _parents(stage: dict) -> list[str]:
    return list(stage["average"]) if "average" in stage else [stage["init"]] if stage.get("init") else []


def stages_for(lineage: dict, target: str, path: str | os.PathLike | None = None) -> list[str]:
    """The stages ``target`` (a stage id, or a release file that ``ships`` names, e.g.
    ``weights/ps_fcn_n.pt`` or ``ps_fcn_n.pt``) needs, each after the ones it starts from,
    ``target`` last."""
    stages, ships = lineage["stages"], lineage["ships"]
    key = os.path.normpath(str(target)).replace(os.sep, "/")  # ./weights/x.pt is weights/x.pt
    # the manifest's checkout's own file by its full path (--lineage: that checkout, not the one psctl runs from)
    with contextlib.suppress(ValueError, OSError, IndexError):
        root = Path(lineage["path"]).resolve().parents[1] if lineage.get("path") else LINEAGE.parents[1]
        key = Path(target).resolve().relative_to(root).as_posix() if Path(target).is_absolute() else key
    sid = key if key in stages else ships.get(key) or ships.get(f"weights/{key}")
    if sid is None:
        raise PsctlError(path or lineage.get("path"), f"{target!r} is neither a stage nor a release file of the "
                                                      f"lineage ({', '.join(ships)})")
    order: list[str] = []
    visiting: set[str] = set()

    def visit(s: str) -> None:
        if s in order:
            return
        if s in visiting:
            raise PsctlError(path, f"stage {s!r} depends on itself")
        visiting.add(s)
        for p in _parents(stages[s]):
            visit(p)
        visiting.discard(s)
        order.append(s)

    visit(sid)
    return order


def stage_recipe(stage: dict, init: str | os.PathLike | None, tiny: bool = False) -> dict:
    """A stage's recipe as ``psctl.train.train`` takes it: its recorded recipe over the defaults,
    ``train.init`` the file it starts from and ``train.samples`` its kept sample count (the
    learning-rate schedule is the recipe's: halvings are counted in samples, not in fractions of
    the run). Where the recipe draws the training mesh (``data.shapes.mesh`` above 0) the mesh is
    required: the early recipes did not say so, and without it the stream falls back to procedural
    shapes with only a note. ``tiny``: the same at tiny sizes (``TINY``), procedural shapes, for
    checking a replay's mechanics."""
    from psctl.train import DEFAULT_CONFIG, check_recipe, merge

    recipe = copy.deepcopy(stage["recipe"])
    recipe.setdefault("train", {})["samples"] = int(stage["samples"])
    recipe["train"]["init"] = None if init is None else str(init)
    if tiny:
        for section, values in TINY.items():
            recipe.setdefault(section, {}).update(copy.deepcopy(values))
        recipe["data"] = {k: v for k, v in recipe["data"].items() if v is not None}
    elif ((recipe.get("data") or {}).get("shapes") or {}).get("mesh", 0) > 0:
        recipe["data"]["require_meshes"] = True
    config = merge(DEFAULT_CONFIG, recipe)
    if config["train"]["warmup"] > config["train"]["samples"]:
        config["train"]["warmup"] = config["train"]["samples"]
    return check_recipe(config)


def stage_output(run: Path, stage: dict) -> Path:
    """The file a finished stage leaves in its run folder: an average's ``best.pt``, a training
    stage's ``model.pt`` (its state at the kept sample count)."""
    return run / ("best.pt" if "average" in stage else "model.pt")


def _saved_run(run: Path) -> dict | None:
    """A run folder's state.json, or None where it cannot be read (``train``'s resume names it)."""
    try:
        st = json.loads((run / "state.json").read_text(encoding="utf-8"))
        return st if isinstance(st, dict) and isinstance(st.get("config"), dict) else None
    except (OSError, ValueError):
        return None


def _check_same_recipe(run: Path, saved: dict, config: dict, sid: str) -> None:
    """A stage's run folder must hold this stage's recipe in this mode: a real rebuild into a
    folder of a ``--tiny`` one (or the reverse) went on with the other's runs and reported their
    files as its result (helper-197)."""
    from psctl.train import DEFAULT_CONFIG, _differences, _plain_json, _recipe_core, merge

    a, b = _recipe_core(config), _recipe_core(_plain_json(merge(DEFAULT_CONFIG, saved["config"])))
    for core in (a, b):
        core["train"].pop("init", None)  # the same file under another spelling of --out
    changed = _differences(a, b)
    if changed:
        raise PsctlError(run, f"holds a run of another recipe than stage {sid!r} ({', '.join(changed[:3])}"
                              f"{' ...' if len(changed) > 3 else ''} differ; a --tiny replay's folder?): rebuild "
                              f"into another --out, or remove this folder to train the stage again")


def _check_average(path: Path, members: list[Path]) -> None:
    """An average made earlier must be of the members' files as they are now (a member stage
    trained again would leave a stale average)."""
    from psctl.models.weights import file_sha256, read_weights

    had = [m.get("sha256") for m in read_weights(path).metadata.get("averaged_from", [])]
    if had != [file_sha256(m) for m in members]:
        raise PsctlError(path, "is the average of other files than its members' now (a member stage was trained "
                               "again?): remove it to average them again")


@contextlib.contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """One rebuild at a time into ``out``: two at once trained the same stage into one folder
    and the second died with a traceback (helper-197). The folder itself locked for the whole
    replay (psctl.checkpoint.folder_lock)."""
    from psctl.checkpoint import folder_lock  # torch: rebuild's alone, not plan's

    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with folder_lock(out, "another rebuild is running into this folder; wait for it, or use another --out"):
            yield
    finally:
        # a folder this call made and left empty (its first stage refused at once, or
        # interrupted before writing): not left behind as an empty output
        if made:
            with contextlib.suppress(OSError):
                out.rmdir()  # only an empty folder goes


def rebuild(target: str, out_dir: str | os.PathLike, lineage: dict | None = None, device: str = "auto",
            max_seconds: float | None = None, tiny: bool = False, report: Callable[[str], object] = print,
            progress: Callable[[dict], object] | None = None) -> dict[str, Any]:
    """Replay the stages ``target`` needs (``stages_for``) into ``out_dir``, one run folder per
    stage, resuming where an earlier call stopped.

    Every stage's recipe is checked before the first one trains. Returns ``{"finished": bool,
    "file": the target's file or None, "stage": the stage it stopped in or None, "signal": a
    signal's number or None}``. It stops at ``max_seconds`` of training in this call (the
    unfinished stage checkpointed), or on SIGINT/SIGTERM/SIGHUP, as ``psctl train``. ``report``
    gets a line as each stage starts and the stream's notes (no training mesh, ...),
    ``progress`` ``train``'s status dicts.
    """
    import time

    from psctl.infer import pick_device
    from psctl.train import average_weights, check_method, check_method_recipe, train

    lineage = load_lineage() if lineage is None else lineage
    where = lineage.get("path")
    order = stages_for(lineage, target)
    if max_seconds is not None and not max_seconds > 0:
        raise PsctlError(None, f"the time limit must be above 0 (--max-minutes), not {max_seconds / 60:g}")
    pick_device(device)  # a device this machine lacks: one line before anything runs
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise PsctlError(out, "is a file; --out takes a folder (one run folder per stage)")
    stages = lineage["stages"]
    recipes: dict[str, dict] = {}
    methods: dict[str, str] = {}
    for sid in order:  # every recipe first: not a key refused hours into the replay
        stage = stages[sid]
        try:
            method = methods[sid] = check_method(stage["method"])
            if "recipe" in stage:
                init = stage_output(out / stage["init"], stages[stage["init"]]) if stage.get("init") else None
                recipes[sid] = stage_recipe(stage, init, tiny)
                check_method_recipe(method, recipes[sid])
        except PsctlError as e:
            raise PsctlError(where, f"stage {sid!r}: {e.message}") from None
    t0 = time.perf_counter()
    with _exclusive(out):
        for k, sid in enumerate(order, 1):
            stage, run, method = stages[sid], out / sid, methods[sid]
            if "average" in stage:
                members = [stage_output(out / m, stages[m]) for m in stage["average"]]
                if stage_output(run, stage).is_file():
                    _check_average(stage_output(run, stage), members)
                else:
                    report(f"[{k}/{len(order)}] {sid}: the average of {', '.join(stage['average'])}")
                    average_weights(members, run, method=method)
                continue
            config = recipes[sid]
            resume = (run / "state.json").is_file()
            saved = _saved_run(run) if resume else None
            if saved is not None:
                _check_same_recipe(run, saved, config, sid)
            finished = saved is not None and saved.get("samples", 0) >= config["train"]["samples"]
            left = None if max_seconds is None else max_seconds - (time.perf_counter() - t0)
            if not finished and left is not None and left <= 0:
                return {"finished": False, "file": None, "stage": sid, "signal": None}
            if not finished:
                begun = f", resumed at {saved['samples']:,}" if saved else ""
                start = f"from {stage['init']}" if stage.get("init") else "from scratch"
                report(f"[{k}/{len(order)}] {sid}: {method}, {config['train']['samples']:,} samples {start}{begun}")
            try:
                st = train(method, None if resume else config, run, resume=resume, device=device, max_seconds=left,
                           progress=progress, note=lambda text: report(f"    note: {text}"))
            except PsctlError as e:
                inside = e.path is not None and Path(e.path).resolve().is_relative_to(run.resolve())
                raise PsctlError(e.path, f"{e.message} (stage {sid!r} of the rebuild"
                                         f"{f'; removing {run} trains it again' if inside else ''})") from None
            if not st["finished"]:
                return {"finished": False, "file": None, "stage": sid, "signal": st.get("signal")}
    return {"finished": True, "file": stage_output(out / order[-1], stages[order[-1]]), "stage": None, "signal": None}


def plan(target: str, lineage: dict | None = None) -> list[dict]:
    """One row per stage ``target`` needs: id, method, samples (kept), from, device and wall
    seconds as recorded (an estimate of a replay's cost where it runs alike)."""
    lineage = load_lineage() if lineage is None else lineage
    rows = []
    for sid in stages_for(lineage, target):
        s = lineage["stages"][sid]
        rows.append({"stage": sid, "method": s["method"], "samples": s.get("samples"),
                     "from": ", ".join(_parents(s)) or "scratch", "device": s.get("device", ""),
                     "wall_seconds": s.get("wall_seconds"), "what": s.get("what", "")})
    return rows


def _every(seconds: float) -> Callable[[dict], None]:
    """A progress printer for hours-long replays: a line every ``seconds`` (samples, loss, rate, ETA)."""
    import time

    last = [time.perf_counter()]

    def show(rec: dict) -> None:
        now = time.perf_counter()
        if now - last[0] < seconds and rec["samples"] < rec["total"]:
            return
        last[0] = now
        eta = (rec["total"] - rec["samples"]) / max(rec["samples_per_s"], 1e-9)
        print(f"    {rec['samples']:,}/{rec['total']:,} samples, loss {rec['loss']:.4f}, "
              f"{rec['samples_per_s']:.1f} samples/s, ETA {eta / 60:.1f} min", flush=True)

    return show


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m psctl.lineage", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("plan", help="list the stages a release file needs")
    p.add_argument("target", help="a release file (weights/ps_fcn_n.pt) or a stage id")
    p.add_argument("--json", action="store_true")
    r = sub.add_parser("rebuild", help="train them in order (resumable)")
    r.add_argument("target")
    r.add_argument("--out", required=True, help="a folder for the stages' run folders")
    r.add_argument("--device", default="auto")
    r.add_argument("--max-minutes", type=float, default=None)
    r.add_argument("--tiny", action="store_true", help="every stage at tiny sizes: checks the mechanics in seconds")
    for q in (p, r):
        q.add_argument("--lineage", default=None, help="the manifest (default: weights/lineage.yaml)")
    args = ap.parse_args(argv)
    try:
        lineage = load_lineage(args.lineage)
        if args.verb == "plan":
            rows = plan(args.target, lineage)
            if args.json:
                print(json.dumps(rows, indent=1))
            else:
                for row in rows:
                    secs = row["wall_seconds"]
                    print(f"{row['stage']:<18} {row['method']:<9} {row['samples'] or '':>9} "
                          f"{'' if secs is None else f'{secs / 60:7.1f} min':>11}  {row['device'][:28]:<28}  {row['what']}")
                total = sum(r["samples"] or 0 for r in rows)
                print(f"{len(rows)} stage{'s' if len(rows) != 1 else ''}, {total:,} samples trained in all")
            return 0
        res = rebuild(args.target, args.out, lineage, args.device,
                      None if args.max_minutes is None else 60 * args.max_minutes, args.tiny,
                      progress=_every(30.0))
    except PsctlError as e:
        print(f"psctl.lineage: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # before train's own handlers are in place (setting up a stage)
        print("psctl.lineage: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `plan ... | head`: the reader left; nothing more to say (helper-198)
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    if res["finished"]:
        print(f"finished: {res['file']}")
        return 0
    print(f"stopped in stage {res['stage']}; run the same command again to continue")
    return 130 if res["signal"] else 0


if __name__ == "__main__":
    raise SystemExit(main())

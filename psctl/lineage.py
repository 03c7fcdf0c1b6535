"""How the release weights were made, stage by stage, and a replay of it from scratch.

    python -m psctl.lineage plan weights/ps_fcn_n.pt           # the stages, in order, with their costs
    python -m psctl.lineage rebuild weights/ps_fcn_n.pt --out runs/rebuild [--device cuda] [--max-minutes 9]

The release files were not trained by one recipe: each is the end of a chain of fine-tuning
stages (and two parameter averages), chosen one at a time by rules on synthetic sets
(docs/training.md, docs/weights-history.md). ``configs/lineage.yaml`` lists every stage: its
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
import copy
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from psctl.errors import PsctlError

LINEAGE = Path(__file__).resolve().parents[1] / "configs" / "lineage.yaml"
RECIPE_SECTIONS = ("method", "model", "normalization", "data", "train", "val", "lcnet")
HEADER = """\
# Every training stage behind the release weights (written by benchmarks/lineage_from_git.py from
# the weights committed over the project's history; do not edit by hand). `ships` names each
# release file's last stage; a stage has the stage it started from (`init`, null: from scratch) or
# the stages it averages (`average`), the sample count of the file that was kept (`samples`), and
# its recipe as its own weights recorded it (train.init left out: the replay sets it).
# Replay: python -m psctl.lineage rebuild weights/ps_fcn_n.pt --out runs/rebuild (docs/training.md).
"""
# a replay's mechanics in seconds (tests, `--tiny`): every stage at tiny sizes, procedural shapes
TINY = {"data": {"size": 16, "pool": 1, "shapes": {"blobby": 1.0}, "require_meshes": False, "scale": None,
                 "interreflection": None},
        "train": {"batch_size": 2, "images_per_sample": 4, "crop": 8, "samples": 4, "log_every": 1,
                  "val_every": 4, "amp": "none", "checkpoint_minutes": 5.0},
        "val": {"samples": 2, "size": 8, "images": 4, "batch_size": 2, "data": {}}}


def load_lineage(path: str | os.PathLike | None = None) -> dict:
    """Read a lineage manifest (default: configs/lineage.yaml) and check its links: every ``init``
    and ``average`` names a stage, every stage trains or averages, and no stage depends on itself."""
    import yaml

    path = Path(path) if path is not None else LINEAGE
    if not path.is_file():
        raise PsctlError(path, "no lineage manifest here (configs/lineage.yaml is in a git checkout, not in the wheel)")
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
        for parent in ([s.get("init")] if "recipe" in s else s["average"]):
            if parent is not None and parent not in stages:
                raise PsctlError(path, f"stage {sid!r} starts from {parent!r}, which is not a stage")
    for file, sid in lineage["ships"].items():
        if sid not in stages:
            raise PsctlError(path, f"{file} ships stage {sid!r}, which is not a stage")
    for sid in stages:
        stages_for(lineage, sid, path)  # a cycle raises
    return lineage


def _parents(stage: dict) -> list[str]:
    return list(stage["average"]) if "average" in stage else [stage["init"]] if stage.get("init") else []


def stages_for(lineage: dict, target: str, path: str | os.PathLike | None = None) -> list[str]:
    """The stages ``target`` (a stage id, or a release file that ``ships`` names, e.g.
    ``weights/ps_fcn_n.pt``) needs, each after the ones it starts from, ``target`` last."""
    stages, ships = lineage["stages"], lineage["ships"]
    key = str(target).replace(os.sep, "/")
    sid = key if key in stages else (ships.get(key) or ships.get(f"weights/{Path(key).name}"))
    if sid is None:
        raise PsctlError(path, f"{target!r} is neither a stage nor a release file of the lineage "
                               f"({', '.join(ships)})")
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
    the run). ``tiny``: the same at tiny sizes (``TINY``), for checking a replay's mechanics."""
    from psctl.train import DEFAULT_CONFIG, check_recipe, merge

    recipe = copy.deepcopy(stage["recipe"])
    recipe.setdefault("train", {})["samples"] = int(stage["samples"])
    recipe["train"]["init"] = None if init is None else str(init)
    if tiny:
        for section, values in TINY.items():
            recipe.setdefault(section, {}).update(copy.deepcopy(values))
        recipe["data"] = {k: v for k, v in recipe["data"].items() if v is not None}
    config = merge(DEFAULT_CONFIG, recipe)
    if config["train"]["warmup"] > config["train"]["samples"]:
        config["train"]["warmup"] = config["train"]["samples"]
    return check_recipe(config)


def stage_output(run: Path, stage: dict) -> Path:
    """The file a finished stage leaves in its run folder: an average's ``best.pt``, a training
    stage's ``model.pt`` (its state at the kept sample count)."""
    return run / ("best.pt" if "average" in stage else "model.pt")


def _finished(run: Path) -> bool:
    """A run folder whose checkpoint reached its recipe's sample count (an unreadable state.json
    is left to ``train``'s resume to name)."""
    try:
        st = json.loads((run / "state.json").read_text(encoding="utf-8"))
        return st["samples"] >= st["config"]["train"]["samples"]
    except (OSError, ValueError, KeyError, TypeError):
        return False


def rebuild(target: str, out_dir: str | os.PathLike, lineage: dict | None = None, device: str = "auto",
            max_seconds: float | None = None, tiny: bool = False, report: Callable[[str], object] = print,
            progress: Callable[[dict], object] | None = None) -> dict[str, Any]:
    """Replay the stages ``target`` needs (``stages_for``) into ``out_dir``, one run folder per
    stage, resuming where an earlier call stopped.

    Returns ``{"finished": bool, "file": the target's file or None, "stage": the stage it stopped
    in or None, "signal": a signal's number or None}``. It stops at ``max_seconds`` of training in
    this call (the unfinished stage checkpointed), or on SIGINT/SIGTERM/SIGHUP, as ``psctl train``.
    ``report`` gets a line as each stage starts, ``progress`` ``train``'s status dicts.
    """
    import time

    from psctl.train import average_weights, check_method, train

    lineage = load_lineage() if lineage is None else lineage
    order = stages_for(lineage, target)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise PsctlError(out, "is a file; --out takes a folder (one run folder per stage)")
    stages = lineage["stages"]
    t0 = time.perf_counter()
    for k, sid in enumerate(order, 1):
        stage, run = stages[sid], out / sid
        method = check_method(stage["method"])
        done = stage_output(run, stage)
        if "average" in stage:
            if not done.is_file():
                report(f"[{k}/{len(order)}] {sid}: the average of {', '.join(stage['average'])}")
                average_weights([stage_output(out / m, stages[m]) for m in stage["average"]], run, method=method)
            continue
        init = stage_output(out / stage["init"], stages[stage["init"]]) if stage.get("init") else None
        resume = (run / "state.json").is_file()
        left = None if max_seconds is None else max_seconds - (time.perf_counter() - t0)
        if left is not None and left <= 0:
            return {"finished": False, "file": None, "stage": sid, "signal": None}
        config = None if resume else stage_recipe(stage, init, tiny)
        if not (resume and _finished(run)):
            n = int(config["train"]["samples"] if config else stage["samples"])
            report(f"[{k}/{len(order)}] {sid}: {method}, {n:,} samples"
                   f"{', from ' + stage['init'] if init else ' from scratch'}{' (resumed)' if resume else ''}")
        st = train(method, config, run, resume=resume, device=device, max_seconds=left, progress=progress)
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
        q.add_argument("--lineage", default=None, help="the manifest (default: configs/lineage.yaml)")
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
                print(f"{len(rows)} stages, {total:,} samples trained in all")
            return 0
        res = rebuild(args.target, args.out, lineage, args.device,
                      None if args.max_minutes is None else 60 * args.max_minutes, args.tiny,
                      progress=_every(30.0))
    except PsctlError as e:
        print(f"psctl.lineage: {e}", file=sys.stderr)
        return 2
    if res["finished"]:
        print(f"finished: {res['file']}")
        return 0
    print(f"stopped in stage {res['stage']}; run the same command again to continue")
    return 130 if res["signal"] else 0


if __name__ == "__main__":
    raise SystemExit(main())

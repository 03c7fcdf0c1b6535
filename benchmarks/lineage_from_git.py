"""Write weights/lineage.yaml: every training stage behind the release weights, read from git (run by hand).

    python benchmarks/lineage_from_git.py [--out weights/lineage.yaml] [--check]

Each release file's metadata records its own recipe, its sample count and the file it started
from (path, samples seen, validation), and an average records its members' recipes. So the
weights committed over the project's history hold almost the whole lineage; this script reads
them (``git show REV:weights/FILE.pt``) and writes one manifest, ``weights/lineage.yaml``, that
``python -m psctl.lineage`` replays. Two stages never shipped and were not averaged, so their
recipes come from configs/ as they are today (their comments say which checkpoint was kept):
PS-FCN+N stage 4 (its 36,000-sample checkpoint started stage 5) and scale stage 3.

The edges (which stage started from which) are written below by hand, from docs/training.md; the
script checks each one whose child recorded its start (31 of 43): the parent's sample count and
its validation metric must be what the child's metadata says it started from; an average's
members by the sha256 it lists (6). The other 6 children recorded no start (average members,
configs/ stages): checked by hand in session 79 (docs/training.md). ``--check`` only
compares the result with the committed manifest (exit 1 on a difference).
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import io
import subprocess
import sys
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from psctl.lineage import HEADER, RECIPE_SECTIONS  # noqa: E402
from psctl.train import load_config  # noqa: E402

# stage id -> (source, parent, what). source: "FILE@REV" (the release file at that commit: its
# own metadata), "FILE@REV#k" (member k of that file's averaged_from) or "configs/X.yaml" (today's
# recipe, with the kept sample count). parent: the stage it started from, None (from scratch) or
# a list (an average).
STAGES: dict[str, tuple] = {
    "ps_fcn_n.1": ("ps_fcn_n@9485390", None, "PS-FCN+N from scratch on the 2-core CPU, the 175,008-sample checkpoint"),
    "ps_fcn.1": ("ps_fcn@95c1367", "ps_fcn_n.1", "PS-FCN without +N (configs/ps_fcn_cpu.yaml)"),
    "ps_fcn.2": ("ps_fcn@216af8e", "ps_fcn.1", "the ambient term (configs/ps_fcn_cpu_ambient.yaml)"),
    "ps_fcn.3": ("ps_fcn@bf8a9ab", "ps_fcn.2", "light cones (configs/ps_fcn_cpu_cones.yaml)"),
    "ps_fcn_n.2": ("ps_fcn_n@c901f80", "ps_fcn.3", "+N again (configs/ps_fcn_n_cpu_from_ps_fcn.yaml)"),
    "ps_fcn_n.3": ("ps_fcn_n@06a2d4b", "ps_fcn_n.2", "a fresh seed (configs/ps_fcn_n_cpu_stage3.yaml)"),
    "ps_fcn_n.4": ("configs/ps_fcn_n_cpu_stage4.yaml", "ps_fcn_n.3", "8-bit truncation; its 36,000-sample checkpoint"),
    "ps_fcn_n.5": ("ps_fcn_n@0d58380", "ps_fcn_n.4", "a fresh seed (configs/ps_fcn_n_cpu_stage5.yaml)"),
    "ps_fcn_n.gpu6": ("ps_fcn_n@066916b", "ps_fcn_n.5", "GPU stage 6 (configs/ps_fcn_n_gpu_stage6.yaml)"),
    "ps_fcn_n.miscal": ("ps_fcn_n@b107baa", "ps_fcn_n.gpu6", "mis-calibrated intensities (configs/ps_fcn_n_cpu_miscal.yaml)"),
    "ps_fcn_n.gpu9": ("ps_fcn_n@c803df4", "ps_fcn_n.miscal", "GPU stage 9 (configs/ps_fcn_n_gpu_stage9.yaml)"),
    "ps_fcn_n.scale": ("ps_fcn_n@63e0e28", "ps_fcn_n.gpu9", "views up to 320 px (configs/ps_fcn_n_cpu_scale.yaml)"),
    "ps_fcn_n.scale3": ("configs/ps_fcn_n_cpu_scale3.yaml", "ps_fcn_n.scale", "scale stage 3, never installed"),
    "ps_fcn_n.scale4": ("ps_fcn_n@193cedd", "ps_fcn_n.scale3", "sides log-uniform (configs/ps_fcn_n_cpu_scale4.yaml)"),
    "ps_fcn_n.scale5": ("ps_fcn_n@6a2d047#1", "ps_fcn_n.scale4", "an average's member (configs/ps_fcn_n_cpu_scale5.yaml)"),
    "ps_fcn_n.scale6": ("ps_fcn_n@6a2d047#2", "ps_fcn_n.scale4", "an average's member (configs/ps_fcn_n_cpu_scale6.yaml)"),
    "ps_fcn_n.scale7": ("ps_fcn_n@6a2d047#3", "ps_fcn_n.scale4", "an average's member (configs/ps_fcn_n_cpu_scale7.yaml)"),
    "ps_fcn_n.average": ("ps_fcn_n@6a2d047", ["ps_fcn_n.scale4", "ps_fcn_n.scale5", "ps_fcn_n.scale6", "ps_fcn_n.scale7"],
                         "the parameter average of scale stages 4-7"),
    "ps_fcn_n.gpu10": ("ps_fcn_n@4c60081", "ps_fcn_n.average", "GPU stage 10 (configs/ps_fcn_n_gpu_stage10.yaml)"),
    "ps_fcn_n.gpu11": ("ps_fcn_n@9ab299f", "ps_fcn_n.gpu10", "GPU stage 11 (configs/ps_fcn_n_gpu_stage11.yaml)"),
    "ps_fcn_n.gpu12": ("ps_fcn_n@6775e23", "ps_fcn_n.gpu11", "GPU stage 12 (configs/ps_fcn_n_gpu_stage12.yaml)"),
    "ps_fcn.4": ("ps_fcn@c901f80", "ps_fcn.3", "configs/ps_fcn_cpu_cones_long.yaml"),
    "ps_fcn.5": ("ps_fcn@7a616cd", "ps_fcn.4", "a fresh seed (configs/ps_fcn_cpu_stage5.yaml)"),
    "ps_fcn.6": ("ps_fcn@2f2c088", "ps_fcn.5", "8-bit truncation (configs/ps_fcn_cpu_stage6.yaml)"),
    "ps_fcn.7": ("ps_fcn@0d58380", "ps_fcn.6", "configs/ps_fcn_cpu_stage7.yaml"),
    "ps_fcn.gpu8": ("ps_fcn@066916b", "ps_fcn.7", "GPU stage 8 (configs/ps_fcn_gpu_stage8.yaml)"),
    "ps_fcn.9": ("ps_fcn@ce3b252", "ps_fcn.gpu8", "interreflections (configs/ps_fcn_cpu_stage9_ir.yaml)"),
    "ps_fcn.10": ("ps_fcn@de4a764", "ps_fcn.9", "configs/ps_fcn_cpu_stage10_ir.yaml"),
    "ps_fcn.11": ("ps_fcn@b107baa", "ps_fcn.10", "mis-calibrated intensities (configs/ps_fcn_cpu_stage11_miscal.yaml)"),
    "ps_fcn.12": ("ps_fcn@2aee5be", "ps_fcn.11", "mis-calibrated directions (configs/ps_fcn_cpu_stage12_dircal.yaml)"),
    "ps_fcn.gpu14": ("ps_fcn@fe46836#0", "ps_fcn.12", "GPU stage 14 (configs/ps_fcn_gpu_stage14_ir.yaml)"),
    "ps_fcn.average": ("ps_fcn@fe46836", ["ps_fcn.gpu14", "ps_fcn.12"], "the average of GPU stage 14 and stage 12"),
    "ups_fcn.1": ("ups_fcn@241c346", "ps_fcn.12", "UPS-FCN from PS-FCN stage 12 (configs/ups_fcn_cpu.yaml)"),
    "ups_fcn.2": ("ups_fcn@e72c228", "ups_fcn.1", "configs/ups_fcn_cpu_stage2.yaml"),
    "lcnet.1": ("lcnet@7821bdc", None, "LCNet from scratch on the CPU, 64 px views (configs/lcnet_cpu.yaml)"),
    "lcnet.2": ("lcnet@f11ded1", "lcnet.1", "light cones (configs/lcnet_cpu_cones.yaml)"),
    "lcnet.3": ("lcnet@643bd3c", "lcnet.2", "configs/lcnet_cpu_cones_long.yaml"),
    "lcnet.4": ("lcnet@308a42f", "lcnet.3", "mixed intensities (configs/lcnet_cpu_mixed.yaml)"),
    "lcnet.5": ("lcnet@31049bb", "lcnet.4", "configs/lcnet_cpu_mixed_stage5.yaml"),
    "lcnet.gpu6": ("lcnet@066916b", "lcnet.5", "GPU stage 6 (configs/lcnet_gpu_stage6.yaml)"),
    "lcnet.gpu7": ("lcnet@50a005f", "lcnet.gpu6", "GPU stage 7 with interreflections (configs/lcnet_gpu_stage7_ir.yaml)"),
}
SHIPS = {"weights/ps_fcn_n.pt": "ps_fcn_n.gpu12", "weights/ps_fcn.pt": "ps_fcn.average",
         "weights/lcnet.pt": "lcnet.gpu7", "weights/ups_fcn.pt": "ups_fcn.2"}
# the kept sample count of the two stages read from configs/ (their children's metadata say so)
KEPT = {"ps_fcn_n.4": 36_000, "ps_fcn_n.scale3": 16_000}


def _git_file(rev: str, path: str) -> bytes:
    return subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], capture_output=True, check=True).stdout


def _metadata(source: str) -> tuple[dict, str]:
    """The metadata a source names and the sha256 of the file it came from (a member: the one it lists)."""
    name, _, rest = source.partition("@")
    rev, _, member = rest.partition("#")
    data = _git_file(rev, f"weights/{name}.pt")
    md = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)["metadata"]
    if member:
        m = md["averaged_from"][int(member)]
        return {**m, "method": md["method"]}, m["sha256"]
    return md, hashlib.sha256(data).hexdigest()


class _Flow(dict):
    """A recipe section written on one line (the manifest stays readable at ~40 stages)."""


yaml.SafeDumper.add_representer(_Flow, lambda d, v: d.represent_mapping("tag:yaml.org,2002:map", v, flow_style=True))


def _recipe(recipe: dict, method: str) -> dict:
    """The recipe's sections, train.init dropped (the replay sets it), and LCNet's section only
    where a network uses it (LCNet, PS-FCN+'s frozen one)."""
    out = {k: copy.deepcopy(recipe[k]) for k in RECIPE_SECTIONS if k in recipe}
    out.get("train", {}).pop("init", None)
    if method not in ("lcnet", "ps-fcn-dagger"):
        out.pop("lcnet", None)
    return {k: _Flow(v) if isinstance(v, dict) else v for k, v in out.items()}


def build() -> dict:
    stages: dict[str, dict] = {}
    recorded: dict[str, dict] = {}  # what each stage's metadata says it started from
    for sid, (source, parent, what) in STAGES.items():
        entry: dict = {"what": what}
        if isinstance(parent, list):
            md, sha = _metadata(source)
            entry.update(method=md["method"], average=parent, source=f"weights/{source.replace('@', '.pt at ')}",
                         sha256=sha, samples_seen=md["samples_seen"])
            members = [m["sha256"] for m in md["averaged_from"]]
            entry["members_sha256"] = members
            if md.get("metrics"):  # measured by --average --config (a release average's only record)
                entry["val"] = md["metrics"]
        elif source.startswith("configs/"):
            cfg = load_config(ROOT / source)
            method = cfg.get("method")
            entry.update(method=method, init=parent, source=f"{source} (today's; never shipped)",
                         samples=KEPT[sid], recipe=_recipe(cfg, method))
        else:
            md, sha = _metadata(source)
            entry.update(method=md["method"], init=parent, source=f"weights/{source.replace('@', '.pt at ').replace('#', ', member ')}",
                         sha256=sha, samples=md["samples_seen"], recipe=_recipe(md["recipe"], md["method"]))
            for key in ("device", "precision", "wall_seconds"):
                if md.get(key) is not None:
                    entry[key] = md[key]
            entry["val"] = md.get("metrics", {})
            if "#" not in source:  # an average's member records no start (its recipe names a path only)
                recorded[sid] = md.get("init") or {}
        stages[sid] = entry
    # each edge against the child's own record of its start
    for sid, rec in recorded.items():
        parent = STAGES[sid][1]
        if parent is None or not rec:
            continue
        p = stages[parent]
        want = p.get("samples", p.get("samples_seen"))
        if rec.get("samples_seen") != want:
            raise SystemExit(f"{sid}: started from {rec.get('samples_seen')} samples, but {parent} has {want}")
        if p.get("val") and rec.get("metrics") and rec["metrics"] != p["val"]:
            raise SystemExit(f"{sid}: started from validation {rec['metrics']}, but {parent} has {p['val']}")
        if not p.get("val") and rec.get("metrics"):
            p["val"] = rec["metrics"]  # a configs/ stage: its validation, as its child recorded it
    for sid, entry in stages.items():  # an average's members must be its stages' files
        if "average" in entry:
            have = [stages[m].get("sha256") for m in entry["average"]]
            if have != entry["members_sha256"]:
                raise SystemExit(f"{sid}: members {entry['members_sha256']} are not the stages' files {have}")
    for file, sid in SHIPS.items():
        sha = hashlib.sha256((ROOT / file).read_bytes()).hexdigest()
        if stages[sid]["sha256"] != sha:
            raise SystemExit(f"{file} (sha256 {sha[:12]}) is not {sid}'s file ({stages[sid]['sha256'][:12]})")
    return {"ships": SHIPS, "stages": stages}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "weights" / "lineage.yaml"))
    ap.add_argument("--check", action="store_true", help="compare with the committed manifest only")
    args = ap.parse_args()
    text = HEADER + yaml.safe_dump(build(), sort_keys=False, default_flow_style=None, width=120)
    out = Path(args.out)
    if args.check:
        same = out.is_file() and out.read_text(encoding="utf-8") == text
        print(f"{out}: {'up to date' if same else 'differs from what git history gives'}")
        raise SystemExit(0 if same else 1)
    out.write_text(text, encoding="utf-8")
    print(f"wrote {out} ({len(text.splitlines())} lines)")


if __name__ == "__main__":
    main()

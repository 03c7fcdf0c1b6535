"""Does bf16 autocast cost training accuracy? The same recipe trained in bf16 and in float32.

    python benchmarks/amp_check.py --config configs/ps_fcn_n.yaml --samples 4000 --val-every 1000 \
        --out .cache/amp_check [--json RESULT.json]

Not a test: run it by hand on a CPU with native bf16 (AVX512-BF16 or AMX) or a GPU; the table
goes into docs/training.md. Three runs of ``--config`` from scratch (or from its ``train.init``),
each its own process with one torch thread, side by side:

* ``bf16``: ``train.amp: bf16``, seed 1;
* ``fp32``: ``train.amp: none``, seed 1 (the same initial weights and the same stream: a paired
  comparison, so the difference is precision alone);
* ``fp32 seed 2`` and ``bf16 seed 2``: the same pair on another seed: a second paired
  difference, and the run-to-run spread (fp32 seed 1 against seed 2) the differences are judged
  against.

On a GPU the float32 runs turn TF32 off (PyTorch's default lets cuDNN convolutions use it); on a
CPU without native bf16 psctl trains the "bf16" runs in float32, so the script refuses to report.

Each run validates every ``--val-every`` samples on the recipe's own validation set (psctl
train's, fixed seed). Printed: each run's validation MAE (degrees) at each point, then |bf16 -
fp32| against |fp32 - fp32 seed 2|. A bf16 difference well inside the seed spread means bf16
does not hurt at that length of training; a longer run says more.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

VARIANTS = {"bf16": ("bf16", 1), "fp32": ("none", 1), "fp32_seed2": ("none", 2), "bf16_seed2": ("bf16", 2)}


def run_one(config: str, samples: int, val_every: int, amp: str, seed: int, out: Path, device: str) -> None:
    """One training run in this process (one torch thread)."""
    import torch

    from psctl.train import load_config, merge, train

    torch.set_num_threads(1)
    if amp == "none":  # float32 means float32: no TF32 in cuDNN's convolutions or in matmuls
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cuda.matmul.allow_tf32 = False
    cfg = merge(load_config(config), {"train": {"samples": samples, "val_every": val_every, "amp": amp,
                                                "seed": seed, "checkpoint_minutes": 5.0}})
    train(cfg.get("method") or "ps-fcn-n", cfg, out, device=device)  # (configs/tiny.yaml names none)


def curve(run: Path) -> dict[int, float]:
    """{samples: validation error} from a run's log.jsonl (val_mae, or LCNet's val_light_mae)."""
    points = {}
    for line in (run / "log.jsonl").read_text().splitlines():
        r = json.loads(line)
        for key, value in r.items():
            if key.startswith("val_") and value is not None:
                points[int(r["samples"])] = float(value)
    return points


def check_run(run: Path, amp: str, samples: int) -> str:
    """Why a run folder cannot be read as this variant's finished run ("" when it can)."""
    st = json.loads((run / "state.json").read_text())
    if st.get("samples") != samples or st.get("config", {}).get("train", {}).get("samples") != samples:
        return f"{run} is not a finished run of {samples} samples (resume it, or remove the folder)"
    from psctl.models.weights import read_weights

    precision = read_weights(run / "model.pt").metadata.get("precision", "")
    if amp == "bf16" and "bf16" not in precision and "bfloat16" not in precision:
        return f"{run} trained in {precision!r}, not bf16: this machine has no native bf16"
    return ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "configs" / "ps_fcn_n.yaml"))
    ap.add_argument("--samples", type=int, default=4000)
    ap.add_argument("--val-every", type=int, default=1000)
    ap.add_argument("--out", default=str(ROOT / ".cache" / "amp_check"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json")
    ap.add_argument("--one", nargs=2, metavar=("VARIANT", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.one:  # a child: one run
        amp, seed = VARIANTS[args.one[0]]
        run_one(args.config, args.samples, args.val_every, amp, seed, Path(args.one[1]), args.device)
        return

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = {}
    for name in VARIANTS:
        if (out / name / "state.json").is_file():  # a finished (or interrupted) run is read, not redone
            continue
        cmd = [sys.executable, __file__, "--config", args.config, "--samples", str(args.samples), "--val-every",
               str(args.val_every), "--device", args.device, "--one", name, str(out / name)]
        procs[name] = subprocess.Popen(cmd, env=env, stdout=open(out / f"{name}.out", "w"), stderr=subprocess.STDOUT)
    for name, p in procs.items():
        if p.wait() != 0:
            sys.exit(f"{name} failed: see {out / (name + '.out')}")

    problems = [check_run(out / name, VARIANTS[name][0], args.samples) for name in VARIANTS]
    if any(problems):
        sys.exit("; ".join(p for p in problems if p))
    curves = {name: curve(out / name) for name in VARIANTS}
    points = sorted(set.intersection(*(set(c) for c in curves.values())))
    print(f"{'samples':>8} " + " ".join(f"{n:>11}" for n in VARIANTS)
          + f" {'bf16-fp32 s1':>13} {'bf16-fp32 s2':>13} {'fp32 s1-s2':>11}")
    for s in points:
        c = {n: curves[n][s] for n in VARIANTS}
        print(f"{s:>8} " + " ".join(f"{c[n]:>11.3f}" for n in VARIANTS) + f" {c['bf16'] - c['fp32']:>13.3f}"
              f" {c['bf16_seed2'] - c['fp32_seed2']:>13.3f} {c['fp32'] - c['fp32_seed2']:>11.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"config": args.config, "samples": args.samples,
                                               "curves": {n: {str(k): v for k, v in c.items()} for n, c in curves.items()}},
                                              indent=1))


if __name__ == "__main__":
    main()

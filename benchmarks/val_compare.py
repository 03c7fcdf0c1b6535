"""Accuracy on a recipe's synthetic validation set: L2 and any number of weight files.

    python benchmarks/val_compare.py --config configs/ps_fcn_n.yaml [--weights run/best.pt ...]

Rebuilds exactly the validation set `psctl train` uses for the recipe (same stream, seed and
size), solves it with least squares (L2, the classic baseline) and with each weights file
(through the training task's own validation code), and prints one JSON object: mean angular
error in degrees over all object pixels. This is how release weights are judged against the
baseline without looking at DiLiGenT (docs/training.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", required=True)
    ap.add_argument("--method", default="ps-fcn-n")
    ap.add_argument("--weights", nargs="*", default=[])
    args = ap.parse_args()

    from psctl.classic import l2_normals
    from psctl.metrics import angular_error
    from psctl.models.weights import read_weights
    from psctl.train import evaluate, load_config, normals_task, validation_batches

    cfg = load_config(args.config)
    v, dev = cfg["val"], torch.device("cpu")
    batches = validation_batches(cfg, dev)  # the training loop's set, val.data included

    total, count = 0.0, 0
    for b in batches:
        imgs = b["images"]
        if "intensities" in b:
            imgs = imgs / b["intensities"][:, :, None, None, None].clamp_min(1e-6)
        for i in range(imgs.shape[0]):
            m = b["masks"][i, 0].bool().numpy()
            x = imgs[i].permute(0, 2, 3, 1).numpy()  # [N, H, W, 3]
            n = l2_normals(x, b["lights"][i].double().numpy(), m).normals
            gt = b["normals"][i].permute(1, 2, 0).numpy()
            total += float(angular_error(n, gt, m).sum())
            count += int(m.sum())
    out = {"config": args.config, "val": v, "pixels": count, "mae": {"l2": round(total / count, 4)}}

    def amp():
        return torch.autocast("cpu", enabled=False)  # float32: the reference numbers

    for path in args.weights:
        task = normals_task(args.method, cfg, dev, amp)
        task.model.load_state_dict(read_weights(path).state_dict)
        with torch.no_grad():
            items = [task.val_item(b) for b in batches]
        out["mae"][path] = round(evaluate(task, items), 4)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

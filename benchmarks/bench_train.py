"""Training throughput of the networks (run by hand; results go to docs/performance.md).

    python benchmarks/bench_train.py                          # CPU: float32 vs bf16, channels_last on/off
    python benchmarks/bench_train.py --device cuda --batch 32 # GPU
    python benchmarks/bench_train.py --net lcnet --size 128

Measures optimiser steps (forward, cosine loss, backward, Adam) of the full PS-FCN (or LCNet) on
random inputs shaped like the paper's training samples (--images images of --size x --size), in
samples per second, for each precision and memory format. The data stream is not included
(benchmarks/bench_synth.py measures it); `psctl train`'s log.jsonl gives the end-to-end rate.
bf16 runs on CUDA and on CPUs with native bf16 (AVX512-BF16 or AMX); elsewhere it is skipped.
On a CPU it first calls psctl.train.keep_freed_memory, as `psctl train` does (--malloc default:
glibc's own behaviour, for comparison). The script prints the load average: wall-clock numbers
are only as good as the machine is quiet.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def step_rate(net: str, device: torch.device, dtype: str, channels_last: bool, args) -> float:
    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN

    torch.manual_seed(0)
    b, n, s = args.batch, args.images, args.size
    if net == "ps-fcn":
        model = PSFCN().to(device)
        x = torch.rand(b, n, 3, s, s, device=device)
        lights = F.normalize(torch.randn(b, n, 3, device=device), dim=-1)
        target = F.normalize(torch.randn(b, 3, s, s, device=device), dim=1)

        def loss_fn():
            return (1 - (model(x, lights) * target).sum(1)).mean()
    else:
        model = LCNet().to(device)
        x = torch.rand(b, n, 3, s, s, device=device)
        mask = torch.ones(b, 1, s, s, device=device)
        labels = [torch.randint(0, k, (b * n,), device=device) for k in (36, 36, 20)]

        def loss_fn():
            out = model(x, mask)
            return sum(F.cross_entropy(out[k].reshape(b * n, -1).float(), y)
                       for k, y in zip(("dir_x", "dir_y", "ints"), labels))
    if channels_last:
        model.to(memory_format=torch.channels_last)
    optim = torch.optim.Adam(model.parameters(), lr=1e-4)
    enabled = dtype == "bf16"

    def step():
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=enabled):
            loss = loss_fn()
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()

    for _ in range(args.warmup):
        step()
    times = []
    for _ in range(args.steps):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return b / sorted(times)[len(times) // 2]  # median step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--net", choices=["ps-fcn", "lcnet"], default="ps-fcn")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--images", type=int, default=32)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--malloc", choices=["keep", "default"], default="keep",
                    help="keep: glibc keeps freed memory, as psctl train does on a CPU (keep_freed_memory)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    from psctl.train import amp_settings, keep_freed_memory

    kept = args.malloc == "keep" and keep_freed_memory()

    device = torch.device(args.device)
    has_bf16 = amp_settings("bf16", device)[0]
    from machine import machine

    out = {"machine": machine(), "threads": torch.get_num_threads(), "device": str(device),
           "net": args.net, "batch": args.batch, "images": args.images, "size": args.size, "keep_freed_memory": kept,
           "loadavg_before": os.getloadavg()[0], "samples_per_s": {}}
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
    for dtype in ("fp32", "bf16"):
        if dtype == "bf16" and not has_bf16:
            out["samples_per_s"]["bf16"] = "skipped: no native bf16 on this device"
            continue
        for cl in (False, True):
            key = f"{dtype}{'+channels_last' if cl else ''}"
            out["samples_per_s"][key] = round(step_rate(args.net, device, dtype, cl, args), 2)
            print(key, out["samples_per_s"][key], file=sys.stderr)
    out["loadavg_after"] = os.getloadavg()[0]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

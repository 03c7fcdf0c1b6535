"""Light estimation (psctl lights, LCNet): memory with the number of images, and argmax vs
soft-argmax decoding.

Not a test: run it by hand; the memory table goes into docs/performance.md and the decoding
comparison into docs/uncalibrated.md, with the machine and date.

    python benchmarks/bench_lights.py                          # psctl lights on 96, 288, 960 images
    python benchmarks/bench_lights.py --counts 96 --views 8 --refine   # psctl lights' defaults
    python benchmarks/bench_lights.py --counts "" --decode runs/lcnet/best.pt   # decoding only

Memory: ``psctl lights`` end to end (reading the images, LCNet, writing the three files) on the
full-size 16-bit DiLiGenT ball with its images repeated to 96, 288 and 960 (symlinks, as
bench_infer.py), each in a fresh process (peak RSS through bench_infer's wrapper). LCNet has
seeded random weights: time and memory do not depend on their values. The global feature is
a running max and at most ``cache_mb`` (64 MB, ~1000 images) of per-image features are kept,
so RSS should stay flat; 960 images also exercise the second read (more than the cache).
By default LCNet alone, one view (``--views 1``, no refinement): the table of 2026-11-22 in
docs/performance.md. ``psctl lights``' own defaults are 8 views and the refinement against the
installed PS-FCN's normals (``--views 8 --refine``), several times the work; each row records
its configuration.

Decoding (``--decode WEIGHTS``): the same LCNet decoded by argmax (class centres, the paper)
and by soft-argmax, LCNet alone (one view, no refinement), on (a) a held-out synthetic set from the recipe's data distribution (seed
2,000,003, never used for training or validation) and (b) the DiLiGenT dev split when
../shared/data is present (``--diligent``). Light direction MAE (degrees) and intensity RE
(scale-invariant, per object) for both.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_infer import machine, repeat_folder, run_measured  # noqa: E402  (same harness)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "diligent" / "pmsData" / "ballPNG"
DEFAULT_DILIGENT = REPO.parent / "shared" / "data" / "diligent" / "pmsData_crop"


def synthetic_decoding(weights: Path, config: Path, samples: int, images: int, device: str) -> dict:
    """Argmax vs soft-argmax on a held-out synthetic set; {mode: {"light_mae", "intensity_re"}}."""
    import numpy as np
    import torch

    from psctl.infer import pick_device
    from psctl.lights import intensity_error
    from psctl.models.lcnet import decode, resize_stack
    from psctl.models.weights import load_network
    from psctl.train import load_config, synth_stream

    dev = pick_device(device)
    model, _, _ = load_network("lcnet", weights, device=dev)
    size = int(model.config["size"])
    cfg = load_config(config)
    stream = synth_stream(cfg["data"], batch_size=16, images=images, crop=size, seed=2_000_003, device=dev)
    errs: dict[str, list] = {"argmax": [], "soft": []}
    res: dict[str, list] = {"argmax": [], "soft": []}
    done = 0
    with torch.no_grad():
        while done < samples:
            b = stream.next_batch()
            x, m = resize_stack(b["images"], b["masks"], size)
            logits = model(x, m)
            for mode in errs:
                dirs, ints = decode(logits, model.config, mode)
                cos = (dirs.double() * b["lights"].double()).sum(-1).clamp(-1, 1)
                errs[mode].append(torch.rad2deg(torch.acos(cos)).flatten().cpu().numpy())
                for e, g in zip(ints.cpu().numpy(), b["intensities"].cpu().numpy()):
                    res[mode].append(intensity_error(e, g))
            done += len(b["images"])
    return {mode: {"light_mae": float(np.concatenate(errs[mode]).mean()), "intensity_re": float(np.mean(res[mode])),
                   "samples": done, "images_per_sample": images} for mode in errs}


def diligent_decoding(weights: Path, root: Path, device: str) -> dict:
    """Argmax vs soft-argmax on each object of a DiLiGenT root; {mode: {object: {...}}}."""
    from psctl.io.capture import find_objects
    from psctl.lights import run_lights

    out: dict = {"argmax": {}, "soft": {}}
    for folder in find_objects(root):
        for mode in out:
            r = run_lights(folder, weights=weights, device=device, decode=mode, views=1, refine=False, write=False)
            out[mode][r["object"]] = {"light_mae": r["light_mae"], "intensity_re": r["intensity_re"]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="a capture folder (default: full-size 16-bit DiLiGenT ball)")
    ap.add_argument("--counts", default="96,288,960", help="image counts for psctl lights ('' to skip)")
    ap.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    ap.add_argument("--decode", type=Path, help="an LCNet weights file: compare argmax and soft-argmax decoding")
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "lcnet.yaml", help="recipe whose data section makes the synthetic set")
    ap.add_argument("--samples", type=int, default=256, help="synthetic samples for --decode")
    ap.add_argument("--images", type=int, default=32, help="images per synthetic sample for --decode")
    ap.add_argument("--diligent", default=str(DEFAULT_DILIGENT), help="DiLiGenT root for --decode ('' to skip)")
    ap.add_argument("--views", type=int, default=1, choices=(1, 2, 4, 8), help="psctl lights --views for the memory runs")
    ap.add_argument("--refine", action="store_true", help="memory runs: refine the lights against the installed "
                    "PS-FCN (psctl lights' default; off: LCNet alone)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()

    import torch

    from psctl.models.lcnet import LCNet
    from psctl.models.weights import save_weights

    results: dict = {"machine": machine(), "runs": []}
    print(json.dumps(results["machine"]))
    counts = [int(c) for c in args.counts.split(",") if c]
    diligent = Path(args.diligent) if args.diligent.strip() else None  # Path("") would be the current folder
    if args.decode and diligent is not None and not diligent.is_dir():
        raise SystemExit(f"{diligent}: not found (pass --diligent FOLDER, or '' to skip)")
    if counts:
        if not args.data.is_dir():
            raise SystemExit(f"{args.data}: not found (pass --data FOLDER)")
        with tempfile.TemporaryDirectory(prefix="psctl-bench-") as tmp:
            tmp = Path(tmp)
            torch.manual_seed(0)
            weights = save_weights(tmp / "lcnet.pt", LCNet(), {"method": "lcnet", "train_images": 32,
                                                               "data": "random initialisation (benchmark)"})
            for n in counts:
                folder = repeat_folder(args.data, tmp / f"obj{n}", n)
                out = run_measured(["psctl", "lights", str(folder), "-w", str(weights), "--device", args.device,
                                    "-o", str(tmp / f"out{n}"), "-q", "--json", "--views", str(args.views),
                                    "--refine" if args.refine else "--no-refine"])
                rep = json.loads(out["stdout"])
                name = f"psctl lights, {args.views} view{'s' if args.views > 1 else ''}" + (
                    ", refined" if args.refine else ", LCNet alone")
                row = {"name": name, "views": args.views, "refine": args.refine, "images": n, "wall_s": out["wall_s"],
                       "peak_rss_mb": out["peak_rss_mb"], "reported_s": rep["seconds"],
                       "load_avg_1m": round(os.getloadavg()[0], 2)}
                results["runs"].append(row)
                print(json.dumps(row), flush=True)
        print("\n| configuration | images | wall s | peak RSS MB | notes |\n|---|---:|---:|---:|---|")
        for r in results["runs"]:
            print(f"| {r['name']} | {r['images']} | {r['wall_s']} | {r['peak_rss_mb']} | "
                  f"reported {r['reported_s']} s, load {r['load_avg_1m']} |")
        if len(results["runs"]) > 1:
            lo, hi = results["runs"][0], results["runs"][-1]
            print(f"\nRSS ratio {hi['images']}/{lo['images']} images: {hi['peak_rss_mb'] / lo['peak_rss_mb']:.2f}")
    if args.decode:
        syn = synthetic_decoding(args.decode, args.config, args.samples, args.images, args.device)
        results["decode_synthetic"] = syn
        print("\nsynthetic (held-out seed):")
        for mode, r in syn.items():
            print(f"  {mode:6s} light MAE {r['light_mae']:.2f}°  intensity RE {r['intensity_re']:.4f}  "
                  f"({r['samples']} samples x {r['images_per_sample']} images)")
        if diligent is not None:
            dil = diligent_decoding(args.decode, diligent, args.device)
            results["decode_diligent"] = dil
            objs = list(dil["argmax"])
            print(f"\n| decoding | {' | '.join(objs)} | mean |\n|---|{'---:|' * (len(objs) + 1)}")
            for mode in dil:
                for key, fmt in (("light_mae", "{:.2f}"), ("intensity_re", "{:.3f}")):
                    vals = [dil[mode][o][key] for o in objs]
                    print(f"| {mode} {key} | {' | '.join(fmt.format(v) for v in vals)} | {fmt.format(sum(vals) / len(vals))} |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""Light estimation accuracy of LCNet weight files, side by side: what chooses an LCNet checkpoint.

Not a test: run it by hand; the tables go into the model card (weights/README.md).

    python benchmarks/eval_lcnet.py weights/lcnet.pt RUN/best.pt [--sets hemi cone45 syntest syntest_dl dev]
        [--decode soft|argmax] [--views 1 8]

Sets (light direction MAE in degrees and intensity relative error, with --decode, soft-argmax
by default as psctl lights; the paper: argmax, one view), each for every --views count
(psctl.lights: the images turned / mirrored about the view axis, estimates averaged):
  hemi        512 held-out synthetic samples (seed 2,000,003, never used for training or
              validation) of configs/lcnet_cpu.yaml's data: lights uniform over the hemisphere
  cone45      the same with lights within 45 degrees of the view axis (DiLiGenT-like rigs)
  hemi_dir, cone45_dir
              the same two with "directional" intensities (psctl.synth.lights): a smooth
              function of the light direction drawn per sample, as real rigs whose LEDs dim
              towards the rim, instead of independent per image
  syntest     .cache/syntest: test shapes (bunny, dragon, armadillo) x 4 MERL materials, 100
              lights over the hemisphere (benchmarks/eval_weights.py makes it)
  syntest_dl  the same shapes under 96 DiLiGenT-like lights, 4 other materials (.cache/syntest_dl)
  syntest_dl_dir
              syntest_dl with directional intensities, each object its own rig (`psctl synth
              .cache/syntest_dl_dir --preset syntest --lights 96 --light-dist diligent
              --intensities directional`)
  syntest_dl_ir
              syntest_dl's recipe with 3 diffuse interreflection bounces from a bright surface
              (`psctl synth .cache/syntest_dl_ir --preset syntest --light-dist diligent --lights 96
              --interreflections 3 --ir-albedo 0.8`; session 17 added it to the LCNet rule)
  dev         the DiLiGenT dev split (../shared/data); reported, never used for choosing

The synthetic sets (all but dev) choose; ``dev`` only reports.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_weights import make_set  # noqa: E402
from machine import machine  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DILIGENT = REPO.parent / "shared" / "data" / "diligent" / "pmsData_crop"
FOLDERS = {"syntest": REPO / ".cache" / "syntest", "syntest_dl": REPO / ".cache" / "syntest_dl",
           "syntest_dl_dir": REPO / ".cache" / "syntest_dl_dir", "syntest_dl_ir": REPO / ".cache" / "syntest_dl_ir",
           "dev": DILIGENT}
SETS = ("hemi", "cone45", "hemi_dir", "cone45_dir", "syntest", "syntest_dl", "syntest_dl_dir", "syntest_dl_ir", "dev")
STREAM_SETS = {"hemi": ("hemisphere", "random"), "cone45": ("diligent", "random"),
               "hemi_dir": ("hemisphere", "directional"), "cone45_dir": ("diligent", "directional")}


def synthetic(weights: Path, lights: dict, samples: int, device: str, decode: str, views: list[int]) -> dict:
    """{views: {light_mae, intensity_re}} on held-out stream samples with these light options."""
    import torch

    from psctl.infer import pick_device
    from psctl.lights import intensity_error
    from psctl.models.lcnet import decode as decode_logits, resize_stack
    from psctl.symmetry import SYMMETRIES, transform_images, untransform_dirs
    from psctl.models.weights import load_network
    from psctl.train import load_config, synth_stream

    dev = pick_device(device)
    model, _, _ = load_network("lcnet", weights, device=dev)
    size = int(model.config["size"])
    cfg = copy.deepcopy(load_config(REPO / "configs" / "lcnet_cpu.yaml"))
    cfg["data"].update(lights)
    stream = synth_stream(cfg["data"], batch_size=16, images=32, crop=size, seed=2_000_003, device=dev)
    errs: dict[int, list] = {v: [] for v in views}
    res: dict[int, list] = {v: [] for v in views}
    done = 0
    with torch.no_grad():
        while done < samples:
            b = stream.next_batch()
            x, m = resize_stack(b["images"], b["masks"], size)
            dirs, ints = [], []
            for sym in SYMMETRIES[:max(views)]:  # views k uses the first k symmetries, as psctl.lights
                d, i = decode_logits(model(transform_images(x, sym), transform_images(m, sym)), model.config, decode)
                dirs.append(untransform_dirs(d, sym))
                ints.append(i)
            for v in views:
                d = torch.nn.functional.normalize(torch.stack(dirs[:v]).mean(0), dim=-1)
                i = torch.stack(ints[:v]).mean(0)
                cos = (d.double() * b["lights"].double()).sum(-1).clamp(-1, 1)
                errs[v].append(torch.rad2deg(torch.acos(cos)).flatten().cpu().numpy())
                for e, g in zip(i.cpu().numpy(), b["intensities"].cpu().numpy()):
                    res[v].append(intensity_error(e, g))
            done += len(b["images"])
    return {v: {"light_mae": float(np.concatenate(errs[v]).mean()), "intensity_re": float(np.mean(res[v]))}
            for v in views}


def folders(weights: Path, root: Path, device: str, decode: str, views: int) -> dict:
    """{object: {light_mae, intensity_re}} plus "mean" over every object of a benchmark root."""
    from psctl.io.capture import find_objects
    from psctl.lights import run_lights

    rows = {}
    for folder in find_objects(root):
        # LCNet alone: refine=False, else its lights are refined against the installed PS-FCN normals
        r = run_lights(folder, weights=weights, device=device, decode=decode, views=views, refine=False, write=False)
        rows[r["object"]] = {"light_mae": r["light_mae"], "intensity_re": r["intensity_re"]}
    rows["mean"] = {k: float(np.mean([v[k] for v in rows.values()])) for k in ("light_mae", "intensity_re")}
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("weights", type=Path, nargs="+", help="LCNet weights files")
    ap.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    ap.add_argument("--samples", type=int, default=512, help="held-out synthetic samples per set")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--decode", default="soft", choices=("soft", "argmax"))
    ap.add_argument("--views", type=int, nargs="+", default=[1], choices=(1, 2, 4, 8))
    args = ap.parse_args()

    out: dict = {"machine": machine(), "decode": args.decode, "results": {}}
    rows = [(str(w), v) for w in args.weights for v in args.views]
    for w in args.weights:
        res: dict = {v: {} for v in args.views}
        for s in args.sets:
            if s in STREAM_SETS:
                lights = {"lights": STREAM_SETS[s][0], "max_zenith": None, "intensities": STREAM_SETS[s][1]}
                for v, r in synthetic(w, lights, args.samples, args.device, args.decode, args.views).items():
                    res[v][s] = r
            elif s != "dev" or FOLDERS[s].is_dir():
                root = FOLDERS[s] if s == "dev" else make_set(s)  # a missing synthetic folder is made first
                for v in args.views:
                    res[v][s] = folders(w, root, args.device, args.decode, v)
            else:
                print(f"{s}: {FOLDERS[s]} not found (../shared/data), skipped", file=sys.stderr)
                continue
            for v in args.views:
                r = res[v][s] if "light_mae" in res[v][s] else res[v][s]["mean"]
                print(json.dumps({"weights": str(w), "views": v, "set": s, "light_mae": round(r["light_mae"], 3),
                                  "intensity_re": round(r["intensity_re"], 4)}), flush=True)
        out["results"][str(w)] = {str(v): r for v, r in res.items()}

    print("\n| weights | views | " + " | ".join(args.sets) + " |")
    print("|---|---:|" + "---:|" * len(args.sets))
    for w, v in rows:
        res = out["results"][w][str(v)]
        cells = []
        for s in args.sets:
            r = res.get(s)
            r = None if r is None else (r if "light_mae" in r else r["mean"])
            cells.append("-" if r is None else f"{r['light_mae']:.2f} / {r['intensity_re']:.3f}")
        print(f"| {w} | {v} | " + " | ".join(cells) + " |")
    print(f"(light direction MAE degrees / intensity RE, {args.decode} decoding)")
    if "dev" in args.sets:
        print("\ndev split per object (light MAE):")
        for w, v in rows:
            dev = out["results"][w][str(v)].get("dev")
            if dev:
                print(f"  {w} views {v}: " + "  ".join(f"{k} {r['light_mae']:.2f}" for k, r in dev.items()))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

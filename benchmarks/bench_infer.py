"""Speed and memory of PS-FCN inference (psctl.infer) against a straightforward implementation.

Not a test: run it by hand and copy the table into docs/performance.md with the machine and date.

    python benchmarks/bench_infer.py                       # CPU, all configurations
    python benchmarks/bench_infer.py --device cuda         # on a GPU machine
    python benchmarks/bench_infer.py --counts 96 --naive "" --large 0   # the 96-image end-to-end
                                                       # run and its model-only child

What it runs, each configuration in a fresh process (peak RSS = that process's ru_maxrss, read by
a small wrapper process through RUSAGE_CHILDREN; wall = the whole command):

* ``psctl normals`` end to end (reading the 16-bit PNGs, the network, writing normal.png/.exr,
  error.png, report.json) with 96, 288 and 960 images: the object's images repeated through a
  temporary folder of symlinks with repeated light rows (flat memory: the 960/96 RSS ratio);
* the straightforward all-at-once implementation (psctl.infer.all_at_once_normals: every
  image's feature map kept, max at the end, as the authors' test code) on the same images, also
  end to end, on the whole frame ("naive-full") and on psctl's crop ("naive-crop");
* model time only: images already in memory, psctl.infer on ``--device``;
* ``--export-npz FOLDER OUT.npz`` then ``--model-child OUT.npz WEIGHTS METHOD DEVICE REPEATS``:
  model time on a machine without OpenImageIO (the GPU machine), from a capture saved here;
* tiling: a synthetic ``--large`` x ``--large`` all-foreground capture (4 random images made on
  the fly) with 512 px tiles and untiled.

The network has seeded random weights (speed and memory do not depend on the values); the
method is ps-fcn-n (+N, two passes over the images) unless ``--method ps-fcn``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import machine  # noqa: E402  (re-exported: the other benchmarks import it from here)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "diligent" / "pmsData" / "ballPNG"


def measure(cmd: list[str]) -> None:
    """Wrapper mode: run cmd, print {"wall_s", "peak_rss_mb", "rc"} of that one child."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # KiB on Linux
    out = {"wall_s": round(wall, 2), "peak_rss_mb": round(peak_kb / 1024, 1), "rc": proc.returncode}
    if proc.returncode:
        out["stderr"] = proc.stderr[-2000:]
    else:
        out["stdout"] = proc.stdout[-4000:]
    print(json.dumps(out))


def run_measured(cmd: list[str]) -> dict:
    res = subprocess.run([sys.executable, __file__, "--measure", "--", *cmd], stdout=subprocess.PIPE, text=True, check=True)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    if out["rc"]:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{out.get('stderr', '')}")
    return out


def repeat_folder(src: Path, dst: Path, n: int) -> Path:
    """A capture folder with n images: src's images repeated (symlinks), rows repeated to match."""
    import numpy as np

    from psctl.io.capture import open_capture

    cap = open_capture(src)
    dst.mkdir(parents=True)
    names = []
    for k in range(n):
        p = cap.image_paths[k % cap.n_images]
        name = f"{k + 1:04d}{p.suffix}"
        (dst / name).symlink_to(p.resolve())
        names.append(name)
    (dst / "filenames.txt").write_text("\n".join(names) + "\n")
    idx = np.arange(n) % cap.n_images
    np.savetxt(dst / "light_directions.txt", cap.lights[idx], fmt="%.8f")
    if cap.intensities_given:
        np.savetxt(dst / "light_intensities.txt", cap.intensities[idx], fmt="%.8f")
    for extra in (cap.mask_path, cap.gt_path):
        if extra is not None:
            (dst / extra.name).symlink_to(extra.resolve())
    return dst


def naive(folder: Path, weights: Path, method: str, crop: bool, out: Path) -> None:
    """Child mode: the all-at-once implementation, end to end (read all, run, write)."""
    import numpy as np

    from psctl.infer import HALO, all_at_once_normals, crop_region
    from psctl.io.capture import load_images, load_mask, open_capture
    from psctl.io.normals import write_normal_map
    from psctl.models.weights import build_network, read_weights

    model, run = build_network(read_weights(weights), method)
    cap = open_capture(folder)
    mask = load_mask(cap)
    box = (slice(None), slice(None))
    if crop:
        y0, y1, x0, x1 = crop_region(mask, HALO)
        box = (slice(y0, min(y1, cap.height)), slice(x0, min(x1, cap.width)))
    images = load_images(cap, box)
    normals = np.zeros((cap.height, cap.width, 3), np.float32)
    normals[box] = all_at_once_normals(model, images, cap.lights, mask[box], run["normalization"], run["train_images"])
    out.mkdir(parents=True, exist_ok=True)
    write_normal_map(out / "normal.png", normals, mask, "png16")
    np.save(out / "normals.npy", normals)


def model_time(folder: Path, weights: Path, method: str, device: str, repeats: int) -> None:
    """Child mode: psctl.infer on images already in memory; prints seconds per run."""
    import numpy as np
    import torch

    from psctl.infer import run_network
    from psctl.models.weights import build_network, read_weights

    model, run = build_network(read_weights(weights), method)
    if folder.suffix == ".npz":  # images, lights and mask saved beforehand (a GPU machine without OpenImageIO)
        with np.load(folder) as z:
            images, lights, mask = z["images"].astype(np.float32), z["lights"], z["mask"]
        n_images = len(images)
    else:
        from psctl.io.capture import load_images, load_mask, open_capture

        cap = open_capture(folder)
        mask = load_mask(cap)
        images, lights, n_images = load_images(cap), cap.lights, cap.n_images

    def reader(start, box):
        for k in range(start, n_images):
            yield images[k][box]

    gpu = device != "cpu" and torch.cuda.is_available()
    sync = torch.cuda.synchronize if gpu else (lambda: None)

    def timed(cfg: dict) -> tuple[list[float], object]:
        run_network(model, reader, n_images, lights, mask, run["normalization"], run["train_images"], cfg)  # warm-up
        times = []
        for _ in range(repeats):
            sync()
            t0 = time.perf_counter()
            res = run_network(model, reader, n_images, lights, mask, run["normalization"], run["train_images"], cfg)
            sync()
            times.append(round(time.perf_counter() - t0, 3))
        return times, res

    times, res = timed({"device": device})
    out = {"model_s": times, "info": res.info}
    if gpu:  # autocast: speed, and how far the normals move (random weights: indicative only)
        for kind in ("bf16", "fp16"):
            t, r = timed({"device": device, "autocast": kind})
            cos = np.clip((r.normals * res.normals).sum(-1)[mask], -1, 1)
            deg = np.degrees(np.arccos(cos))
            out[f"autocast_{kind}"] = {"model_s": t, "mean_deg": round(float(deg.mean()), 4),
                                       "max_deg": round(float(deg.max()), 4)}
    print(json.dumps(out))


def export_npz(folder: Path, out: Path) -> None:
    """Save a capture as --model-child reads it on a machine without OpenImageIO (the GPU machine):
    the images psctl would run on (cropped as psctl crops them, divided by the intensities, float16),
    the lights and the cropped mask."""
    import numpy as np

    from psctl.infer import HALO, crop_region
    from psctl.io.capture import load_images, load_mask, open_capture

    cap = open_capture(folder)
    mask = load_mask(cap)
    y0, y1, x0, x1 = crop_region(mask, HALO)
    box = (slice(y0, y1), slice(x0, x1))
    images = np.asarray(load_images(cap, box)).astype(np.float16)
    np.savez_compressed(out, images=images, lights=cap.lights.astype(np.float32), mask=mask[box],
                        full=np.array([cap.height, cap.width]))
    print(f"{out}: {images.shape[0]} images of {images.shape[1]} x {images.shape[2]}")


def large(side: int, n: int, tile: int) -> None:
    """Child mode: one side x side capture of n random images, mask = everything (tiling)."""
    import numpy as np
    import torch

    from psctl.infer import run_network
    from psctl.models.ps_fcn import PSFCN

    torch.manual_seed(0)
    model = PSFCN().eval()
    lights = np.tile(np.array([[0.2, 0.3, 0.93]], np.float32), (n, 1))

    def reader(start, box):  # images made on the fly, as a reader decodes files
        for k in range(start, n):
            yield np.random.default_rng(k).uniform(0, 1, (side, side, 3)).astype(np.float32)[box]

    t0 = time.perf_counter()
    res = run_network(model, reader, n, lights, np.ones((side, side), bool), "per-channel", 32, {"tile": tile})
    print(json.dumps({"model_s": round(time.perf_counter() - t0, 2), "info": res.info}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="a capture folder (default: full-size 16-bit DiLiGenT ball)")
    ap.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    ap.add_argument("--method", default="ps-fcn-n", choices=("ps-fcn", "ps-fcn-n"))
    ap.add_argument("--counts", default="96,288,960", help="image counts for the streaming engine")
    ap.add_argument("--naive", default="full:96,crop:96,crop:288",
                    help="all-at-once runs as MODE:COUNT, MODE full (whole frame) or crop; '' for none")
    ap.add_argument("--repeats", type=int, default=1, help="model-time repeats")
    ap.add_argument("--large", type=int, default=1536, help="side of a synthetic all-foreground capture run "
                    "tiled (512 px tiles) and untiled, 4 images; 0 to skip")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()

    import torch

    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    if not args.data.is_dir():
        raise SystemExit(f"{args.data}: not found (pass --data FOLDER)")
    results: dict = {"machine": machine(), "data": str(args.data), "method": args.method, "device": args.device, "runs": []}
    print(json.dumps(results["machine"]))
    with tempfile.TemporaryDirectory(prefix="psctl-bench-") as tmp:
        tmp = Path(tmp)
        torch.manual_seed(0)
        weights = save_weights(tmp / "w.pt", PSFCN(), {"method": args.method, "train_images": 32,
                                                       "data": "random initialisation (benchmark)"})
        counts = sorted({int(c) for c in args.counts.split(",") if c} | {int(s.split(":")[1]) for s in args.naive.split(",") if s})
        folders = {n: repeat_folder(args.data, tmp / f"obj{n}", n) for n in counts}

        def record(name: str, n: int, out: dict, **extra) -> None:
            row = {"name": name, "images": n, "wall_s": out["wall_s"], "peak_rss_mb": out["peak_rss_mb"],
                   "load_avg_1m": round(os.getloadavg()[0], 2), **extra}
            results["runs"].append(row)
            print(json.dumps(row), flush=True)

        for n in [int(c) for c in args.counts.split(",") if c]:
            out = run_measured(["psctl", "normals", str(folders[n]), "-m", args.method, "-w", str(weights),
                                "--device", args.device, "-o", str(tmp / f"out{n}"), "-f", "png16,exr,npy", "-q", "--json"])
            rep = json.loads(out["stdout"])
            record("psctl normals (streaming)", n, out, reported_s=rep["seconds"])
        for spec in [s for s in args.naive.split(",") if s]:
            mode, n = spec.split(":")
            out = run_measured([sys.executable, __file__, "--naive-child", mode, str(folders[int(n)]), str(weights),
                                args.method, str(tmp / f"naive-{mode}{n}")])
            extra = {}
            ours = tmp / f"out{n}" / "normal.npy"
            if ours.exists():  # the same normals?
                import numpy as np

                from psctl.io.normals import read_normal_map

                a = np.load(tmp / f"naive-{mode}{n}" / "normals.npy")
                b = read_normal_map(ours)
                extra["max_abs_diff_vs_streaming"] = float(np.abs(a - b).max())
            record(f"all-at-once ({mode})", int(n), out, **extra)
        n0 = min(counts)
        out = run_measured([sys.executable, __file__, "--model-child", str(folders[n0]), str(weights), args.method,
                            args.device, str(args.repeats)])
        mt = json.loads(out["stdout"].strip().splitlines()[-1])
        record("model only (images in memory)", n0, out, **{k: v for k, v in mt.items()})
        if args.large:
            for tile in (512, 1 << 20):
                out = run_measured([sys.executable, __file__, "--large-child", str(args.large), "4", str(tile)])
                lt = json.loads(out["stdout"].strip().splitlines()[-1])
                record(f"{args.large} x {args.large}, all foreground, {'tiled' if tile == 512 else 'untiled'}", 4, out,
                       model_s=lt["model_s"], tiles=lt["info"]["tiles"], passes=lt["info"]["passes"])

    print()
    print("| configuration | images | wall s | peak RSS MB | notes |")
    print("|---|---:|---:|---:|---|")
    for r in results["runs"]:
        note = ", ".join(f"{k}={v}" for k, v in r.items() if k not in ("name", "images", "wall_s", "peak_rss_mb", "info"))
        print(f"| {r['name']} | {r['images']} | {r['wall_s']} | {r['peak_rss_mb']} | {note} |")
    stream = {r["images"]: r for r in results["runs"] if r["name"].startswith("psctl normals")}
    if len(stream) > 1:
        lo, hi = min(stream), max(stream)
        print(f"\nRSS ratio {hi}/{lo} images: {stream[hi]['peak_rss_mb'] / stream[lo]['peak_rss_mb']:.2f}")
    for r in results["runs"]:
        if r["name"].startswith("all-at-once") and r["images"] in stream:
            s = stream[r["images"]]
            print(f"{r['name']} vs streaming, {r['images']} images: {r['wall_s'] / s['wall_s']:.2f}x time, "
                  f"{r['peak_rss_mb'] / s['peak_rss_mb']:.2f}x peak RSS")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--measure":
        measure(sys.argv[3:] if sys.argv[2] == "--" else sys.argv[2:])
    elif len(sys.argv) > 1 and sys.argv[1] == "--naive-child":
        naive(Path(sys.argv[3]), Path(sys.argv[4]), sys.argv[5], sys.argv[2] == "crop", Path(sys.argv[6]))
    elif len(sys.argv) > 1 and sys.argv[1] == "--large-child":
        large(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]))
    elif len(sys.argv) > 1 and sys.argv[1] == "--export-npz":
        export_npz(Path(sys.argv[2]), Path(sys.argv[3]))
    elif len(sys.argv) > 1 and sys.argv[1] == "--model-child":
        model_time(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4], sys.argv[5], int(sys.argv[6]))
    else:
        main()

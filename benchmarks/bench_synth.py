"""Speed of the synthetic data engine (run by hand; results go to docs/performance.md).

    python benchmarks/bench_synth.py                       # CPU, torch's default thread count
    python benchmarks/bench_synth.py --threads 1           # one core
    python benchmarks/bench_synth.py --threads 1 --workers 2 --skip pieces,writer   # + 2 DataLoader workers
    python benchmarks/bench_synth.py --device cuda --batches 50 --pool 512 --reuse 512 --refresh-chunk 32
    python benchmarks/bench_synth.py --threads 1 --skip pieces,writer --batches 64 --interreflection 0.5

Measures
  * the training stream: samples per second (a sample = --images images of --crop x --crop
    pixels, with its lights, normals and mask), after the pool is filled; the target is
    >= 200 samples/s of 32 images at 32 x 32 on the 2-core CPU and >= 5,000 on one H100;
  * the pieces: blobby shapes and mesh views per second (128 x 128), horizon maps per second;
  * the folder writer: seconds per syntest object (100 lights, 128 x 128, incl. PNG writing; CPU only).
Wall-clock numbers on a shared machine are only as good as the machine is quiet: the script
prints the load average before and after, and the process CPU time next to the wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _timed(fn, device: torch.device) -> tuple[float, float]:
    _sync(device)
    t, c = time.perf_counter(), time.process_time()
    fn()
    _sync(device)
    return time.perf_counter() - t, time.process_time() - c


def bench_stream(args, device: torch.device) -> dict:
    from psctl.synth.stream import SynthStream

    cfg = {"batch_size": args.batch_size, "n_images": args.images, "crop": args.crop, "size": args.size,
           "pool": args.pool, "reuse": args.reuse, "refresh_chunk": args.refresh_chunk, "device": str(device), "seed": 0,
           "intensities": args.intensities}
    if args.no_meshes:
        cfg["shapes"] = {"blobby": 1.0}
    if args.interreflection:
        cfg["interreflection"] = {"p": args.interreflection, "albedo": [0.0, 0.9]}
    holder = {}
    wall_init, _ = _timed(lambda: holder.setdefault("s", SynthStream(cfg)), device)
    stream = holder["s"]
    for _ in range(args.warmup):
        stream.next_batch()

    def run():
        for _ in range(args.batches):
            stream.next_batch()

    wall, cpu = _timed(run, device)
    n = args.batches * args.batch_size
    return {"what": "stream", "samples_per_s": n / wall, "samples": n, "wall_s": wall, "cpu_s": cpu,
            "pool_init_s": wall_init, "pool": args.pool, "reuse": args.reuse, "batch_size": args.batch_size,
            "images": args.images, "crop": args.crop, "size": args.size, "notes": stream.notes,
            "geometry_sources": [k for k, _ in stream.pool.sources]}


def bench_workers(args) -> dict:
    """The stream through a DataLoader with single-threaded worker processes (CPU)."""
    from torch.utils.data import DataLoader

    from psctl.synth.stream import SynthDataset

    cfg = {"batch_size": args.batch_size, "n_images": args.images, "crop": args.crop, "size": args.size,
           "pool": args.pool, "reuse": args.reuse, "refresh_chunk": args.refresh_chunk, "seed": 0,
           "intensities": args.intensities}
    if args.no_meshes:
        cfg["shapes"] = {"blobby": 1.0}
    loader = DataLoader(SynthDataset(cfg), batch_size=None, num_workers=args.workers, persistent_workers=True,
                        prefetch_factor=4)
    it = iter(loader)
    t = time.perf_counter()
    for _ in range(args.warmup + args.workers):  # every worker has filled its pool
        next(it)
    init = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(args.batches):
        next(it)
    wall = time.perf_counter() - t
    n = args.batches * args.batch_size
    return {"what": "stream-workers", "samples_per_s": n / wall, "samples": n, "wall_s": wall, "workers": args.workers,
            "startup_s": init, "pool": args.pool, "reuse": args.reuse, "batch_size": args.batch_size,
            "images": args.images, "crop": args.crop, "size": args.size}


def bench_pieces(args, device: torch.device) -> list[dict]:
    from psctl.synth import meshes
    from psctl.synth import render as R
    from psctl.synth.shapes import blobby_gbuffers, random_rotations

    out = []
    gen = torch.Generator(device=device).manual_seed(0)
    n = args.shapes
    blobby_gbuffers(2, args.size, gen)  # warm-up
    holder = {}
    wall, cpu = _timed(lambda: holder.setdefault("g", blobby_gbuffers(n, args.size, gen)), device)
    out.append({"what": "blobby shapes", "per_s": n / wall, "n": n, "wall_s": wall, "cpu_s": cpu, "size": args.size})
    g = holder["g"]
    wall, cpu = _timed(lambda: R.horizon_map(g.depth, 32), device)
    out.append({"what": "horizon maps (32 azimuths)", "per_s": n / wall, "n": n, "wall_s": wall, "cpu_s": cpu})
    try:
        path = meshes.find_mesh("lucy")
    except Exception:
        return out
    v, f = meshes.load_obj(path)
    v, f = v.to(device), f.to(device)
    rots = random_rotations((n,), gen)
    wall, cpu = _timed(lambda: meshes.mesh_views(v, f, rots, args.size, name="lucy"), device)
    out.append({"what": "lucy views (rasterised)", "per_s": n / wall, "n": n, "wall_s": wall, "cpu_s": cpu,
                "faces": int(f.shape[0])})
    return out


def bench_writer(args) -> dict | None:
    from psctl.synth import meshes
    from psctl.synth.write import write_preset

    if not (meshes.mesh_dir() / "bunny.obj").is_file():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        rep = write_preset(Path(tmp) / "syntest", "syntest", size=128, n_lights=100, k=1)
        wall = time.perf_counter() - t
    return {"what": "psctl synth --preset syntest --materials 1 (4 objects, 100 lights, 128 px)",
            "s_per_object": wall / len(rep["objects"]), "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--images", type=int, default=32)
    ap.add_argument("--crop", type=int, default=32)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--pool", type=int, default=64)
    ap.add_argument("--reuse", type=int, default=128)
    ap.add_argument("--refresh-chunk", type=int, default=8, help="new G-buffers rendered per call")
    ap.add_argument("--intensities", default="unit")
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--interreflection", type=float, default=0.0,
                    help="stream option interreflection.p (0: off); the pool then computes form factors per G-buffer, "
                         "one refresh chunk every refresh_chunk * reuse / batch_size batches (32 by default): time >= 64")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--shapes", type=int, default=16, help="shapes/views for the geometry timings")
    ap.add_argument("--no-meshes", action="store_true", help="procedural shapes only")
    ap.add_argument("--workers", type=int, default=0, help="also time a DataLoader with this many workers (CPU)")
    ap.add_argument("--skip", default="", help="comma list of stream,pieces,writer to skip")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    skip = set(filter(None, args.skip.split(",")))
    from machine import machine as describe_machine

    machine = {**describe_machine(), "device": str(device), "date": time.strftime("%Y-%m-%d %H:%M"),
               "loadavg_before": os.getloadavg()}
    results = []
    if "stream" not in skip:
        results.append(bench_stream(args, device))
    if args.workers and device.type == "cpu":
        results.append(bench_workers(args))
    if "pieces" not in skip:
        results += bench_pieces(args, device)
    if "writer" not in skip and device.type == "cpu":
        w = bench_writer(args)
        if w:
            results.append(w)
    machine["loadavg_after"] = os.getloadavg()
    if args.json:
        print(json.dumps({"machine": machine, "results": results}, indent=2))
        return
    print(f"{machine['date']}  {machine['device']}  cpus={machine['cores']}  torch threads={machine['threads']}  "
          f"torch {machine['torch']}  load {machine['loadavg_before'][0]:.1f} -> {machine['loadavg_after'][0]:.1f}")
    for r in results:
        if r["what"] == "stream":
            print(f"stream: {r['samples_per_s']:.0f} samples/s ({r['batch_size']} x {r['images']} images of "
                  f"{r['crop']}x{r['crop']}, pool {r['pool']} at {r['size']}px, reuse {r['reuse']}; "
                  f"wall {r['wall_s']:.2f} s, cpu {r['cpu_s']:.2f} s; pool fill {r['pool_init_s']:.1f} s; "
                  f"sources {'+'.join(r['geometry_sources'])})")
        elif r["what"] == "stream-workers":
            print(f"stream, DataLoader with {r['workers']} single-threaded workers: {r['samples_per_s']:.0f} samples/s "
                  f"(wall {r['wall_s']:.2f} s; startup {r['startup_s']:.1f} s)")
        elif "per_s" in r:
            print(f"{r['what']}: {r['per_s']:.1f}/s (wall {r['wall_s']:.2f} s, cpu {r['cpu_s']:.2f} s for {r['n']})")
        else:
            print(f"{r['what']}: {r['s_per_object']:.2f} s/object")


if __name__ == "__main__":
    main()

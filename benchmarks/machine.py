"""What ran a benchmark, recorded in every benchmark's results: the CPU's name alone ("AMD
EPYC") is the same for hosts whose speed differs threefold (AVX-512 and native bf16 or not,
docs/performance.md), so the instruction sets that change torch's kernels are recorded too."""

from __future__ import annotations

import datetime
import os
import platform
from pathlib import Path

FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16")  # what selects torch's CPU kernels


def cpu_flags() -> list[str]:
    """Those of FLAGS that /proc/cpuinfo lists (empty where there is none)."""
    try:
        have = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return []
    return [f for f in FLAGS if f in have]


def machine() -> dict:
    import torch

    from psctl.infer import cpu_has_bf16
    from psctl.train import cpu_name

    info = {"cpu": cpu_name(), "cpu_flags": cpu_flags(), "native_bf16": cpu_has_bf16(), "cores": os.cpu_count(),
            "torch": torch.__version__, "threads": torch.get_num_threads(),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "python": platform.python_version(),
            "date": datetime.date.today().isoformat(), "load_avg_1m": round(os.getloadavg()[0], 2)}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info

"""Shared fixtures: small synthetic capture folders made on the fly (no external data needed)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

if TYPE_CHECKING:
    import torch


@pytest.fixture(autouse=True)
def _isolated(monkeypatch):
    """Each test as on a fresh clone: the installed weights are the repository's (a developer's
    $PSCTL_WEIGHTS would change what auto picks, and tests that set it put the user's value back
    through monkeypatch), the data beside the checkout (not $PSCTL_DATA, $PSCTL_MESHES or
    $PSCTL_MERL), output as CI's (no $COLUMNS, $FORCE_COLOR, ...: helper-166 found tables 321
    columns wide under FORCE_COLOR=1), and torch's thread count as it was (some tests set it)."""
    import torch

    for name in ("PSCTL_WEIGHTS", "PSCTL_DATA", "PSCTL_MESHES", "PSCTL_MERL", "COLUMNS", "LINES", "FORCE_COLOR",
                 "NO_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE"):
        monkeypatch.delenv(name, raising=False)
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def shared_data(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test when the data is not there."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"needs {p} (the project's shared data; absent in a fresh clone)")
    return p


def sphere(size: int, radius: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic unit sphere: normals [H, W, 3] (x right, y up, z to camera), mask [H, W]."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c, -c)  # row 0 is the top: y up
    r2 = (x**2 + y**2) / radius**2
    mask = r2 < 1
    z = np.sqrt(np.clip(1 - r2, 0, None))
    n = np.stack([x / radius, y / radius, z], -1)
    n[~mask] = 0
    return n.astype(np.float32), mask


def hemisphere_lights(n: int, max_angle_deg: float = 35.0, seed: int = 0) -> np.ndarray:
    """n unit light directions within max_angle of the view direction."""
    rng = np.random.default_rng(seed)
    cos_max = np.cos(np.radians(max_angle_deg))
    z = rng.uniform(cos_max, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1).astype(np.float32)


def render_lambertian(normals: np.ndarray, mask: np.ndarray, lights: np.ndarray,
                      albedo: np.ndarray | float = 0.8) -> np.ndarray:
    """[N, H, W, 3] Lambertian images with attached shadows (max(n.l, 0))."""
    shading = np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None)
    alb = np.asarray(albedo, np.float32)
    alb = np.broadcast_to(alb if alb.ndim == 3 else alb.reshape(1, 1, -1), mask.shape + (3,))
    imgs = shading[..., None] * alb
    return (imgs * mask[None, ..., None]).astype(np.float32)


def random_biases(net: "torch.nn.Module", seed: int = 0, std: float = 0.1) -> "torch.nn.Module":
    """Give ``net``'s biases seeded random values. Fresh networks start with zero biases, and with
    zero biases and LeakyReLU a layer ignores any positive scale of its input, so an exactness
    test on them cannot see a wrong scale (a mean fusion that divides by n - 1: a mutation audit)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in net.named_parameters():
            if name.endswith("bias"):
                p.copy_(torch.randn(p.shape, generator=g, dtype=torch.float64).to(p.dtype) * std)
    return net


def write_capture(folder: Path, n: int = 12, size: int = 40, bits: int = 16, intensities: bool = True,
                  gt: str = "mat", mask: bool = True, seed: int = 0) -> dict:
    """Write a DiLiGenT-style folder of a Lambertian sphere; return its arrays."""
    import scipy.io

    from psctl.io.images import write_image

    folder.mkdir(parents=True, exist_ok=True)
    normals, m = sphere(size)
    lights = hemisphere_lights(n, seed=seed)
    rng = np.random.default_rng(seed)
    e = rng.uniform(0.5, 1.5, (n, 3)).astype(np.float32) if intensities else np.ones((n, 3), np.float32)
    imgs = render_lambertian(normals, m, lights, 0.7) * e[:, None, None, :] / 1.6
    names = []
    for k in range(n):
        name = f"{k + 1:03d}.png"
        write_image(folder / name, imgs[k], "uint16" if bits == 16 else "uint8", kind="linear")  # as psctl synth
        names.append(name)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights, fmt="%.6f")
    if intensities:
        np.savetxt(folder / "light_intensities.txt", e / 1.6, fmt="%.6f")
    if mask:
        write_image(folder / "mask.png", m.astype(np.float32), "uint8", kind="data")
    if gt == "mat":
        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": normals.astype(np.float64)})
    elif gt == "png":
        write_image(folder / "Normal_gt.png", np.where(m[..., None], (normals + 1) / 2, 0), "uint16", kind="data")
    return {"normals": normals, "mask": m, "lights": lights, "intensities": e / 1.6, "images": imgs}


@pytest.fixture
def capture(tmp_path: Path) -> Path:
    """A valid 16-bit capture folder: 12 images of a 40 x 40 Lambertian sphere."""
    folder = tmp_path / "spherePNG"
    write_capture(folder)
    return folder


@pytest.fixture(scope="module")
def fake_weights(tmp_path_factory) -> Path:
    """A weights folder with seeded random LCNet and PS-FCN† files (stand-ins for trained ones)."""
    import torch

    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    folder = tmp_path_factory.mktemp("weights")
    torch.manual_seed(0)
    save_weights(folder / "lcnet.pt", LCNet().eval(), {"method": "lcnet", "train_images": 32})
    torch.manual_seed(1)
    save_weights(folder / "ps_fcn_dagger.pt", PSFCN(), {"method": "ps-fcn-dagger", "train_images": 32})
    return folder


@contextlib.contextmanager
def weights_in(folder: str | os.PathLike):
    """$PSCTL_WEIGHTS set to ``folder`` for the block; its value before (a user's own) restored."""
    old = os.environ.get("PSCTL_WEIGHTS")
    os.environ["PSCTL_WEIGHTS"] = str(folder)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("PSCTL_WEIGHTS", None)
        else:
            os.environ["PSCTL_WEIGHTS"] = old

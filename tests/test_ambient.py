"""An ambient image (every light off) in the capture folder is subtracted from every image."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from psctl.api import run_normals
from psctl.cli import app
from psctl.errors import PsctlError
from psctl.io.capture import load_images, open_capture
from psctl.io.images import write_image
from tests.conftest import write_capture


def _with_ambient(folder, level: float = 0.08):
    """The conftest sphere with a smooth room light added to every image (as recorded, before
    the intensities are divided out), and that light alone as ambient.png."""
    data = write_capture(folder, n=12, size=40)
    h, w = data["mask"].shape
    ramp = np.linspace(0.5, 1.0, w, dtype=np.float32)[None, :, None] * np.array([1.0, 0.9, 0.8], np.float32)
    ambient = np.broadcast_to(level * ramp, (h, w, 3)).copy()
    for k, img in enumerate(data["images"]):
        write_image(folder / f"{k + 1:03d}.png", img + ambient, "uint16")
    write_image(folder / "ambient.png", ambient, "uint16")
    return data


def test_ambient_image_is_subtracted(tmp_path):
    folder = tmp_path / "roomPNG"
    data = _with_ambient(folder)
    cap = open_capture(folder)
    assert cap.ambient_path == folder / "ambient.png" and cap.n_images == 12  # not an input image
    truth = data["images"] / data["intensities"][:, None, None, :]
    assert np.abs(load_images(cap) - truth).max() < 1e-4

    with_ambient = run_normals(folder, method="l2", write=False)
    assert any("ambient.png subtracted" in n for n in with_ambient["notes"])
    (folder / "ambient.png").rename(tmp_path / "elsewhere.png")
    without = run_normals(folder, method="l2", write=False)
    assert with_ambient["mae"] < 1.5 and without["mae"] > with_ambient["mae"] + 2


def test_ambient_errors_and_info(tmp_path):
    folder = tmp_path / "roomPNG"
    _with_ambient(folder)
    runner = CliRunner()
    r = runner.invoke(app, ["info", str(folder), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["ambient"] == "ambient.png"
    # an output folder may not be a capture's, its ambient image included
    out = tmp_path / "out"
    out.mkdir()
    write_image(out / "ambient.png", np.zeros((4, 4, 3), np.float32), "uint8")
    r = runner.invoke(app, ["normals", str(folder), "-m", "l2", "-o", str(out)])
    assert r.exit_code == 2 and "Traceback" not in r.output
    # wrong size: one line naming the file
    write_image(folder / "ambient.png", np.zeros((8, 8, 3), np.float32), "uint16")
    with pytest.raises(PsctlError, match="ambient.png: size 8x8 differs"):
        open_capture(folder)
    # listed as an input image too: ambiguous
    write_image(folder / "ambient.png", np.zeros((40, 40, 3), np.float32), "uint16")
    names = (folder / "filenames.txt").read_text()
    (folder / "filenames.txt").write_text(names + "ambient.png\n")
    with pytest.raises(PsctlError, match="is the ambient image"):
        open_capture(folder)

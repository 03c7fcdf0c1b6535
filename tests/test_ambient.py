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
        write_image(folder / f"{k + 1:03d}.png", img + ambient, "uint16", kind="linear")
    write_image(folder / "ambient.png", ambient, "uint16", kind="linear")
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


def test_a_negative_ambient_image_gets_a_note(tmp_path):
    """A float ambient image below 0 (a dark frame's noise about 0) adds light where subtracted: a
    note says where and how far (an audit: -0.01 everywhere, not a word). None at or above 0."""
    folder = tmp_path / "roomPNG"
    _with_ambient(folder)
    (folder / "ambient.png").unlink()
    amb = np.full((40, 40, 3), 0.01, np.float32)
    amb[:10] = -0.02
    write_image(folder / "ambient.exr", amb, "float")
    r = run_normals(folder, method="l2", write=False)
    assert [n for n in r["notes"] if "is negative" in n] == [
        "ambient: ambient.exr is negative in 25% of its pixels (down to -0.02): taken as stored, so subtracting it "
        "adds light there"]
    write_image(folder / "ambient.exr", np.abs(amb), "float")
    assert not any("is negative" in n for n in run_normals(folder, method="l2", write=False)["notes"])


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


def test_ambient_name_case_two_files_and_a_wiped_image(tmp_path):
    folder = tmp_path / "roomPNG"
    _with_ambient(folder)
    (folder / "ambient.png").rename(folder / "Ambient.PNG")  # the image list leaves it out: so must this
    assert open_capture(folder).ambient_path == folder / "Ambient.PNG"
    assert run_normals(folder, method="l2", write=False)["mae"] < 1.5
    write_image(folder / "ambient.exr", np.zeros((40, 40, 3), np.float32), "float")
    with pytest.raises(PsctlError, match="holds 2 ambient images"):
        open_capture(folder)
    (folder / "ambient.exr").unlink()
    write_image(folder / "Ambient.PNG", np.ones((40, 40, 3), np.float32), "uint16")  # brighter than any image
    with pytest.raises(PsctlError, match="Ambient.PNG: subtracting it leaves 001.png black"):
        run_normals(folder, method="l2", write=False)


def test_ambient_listed_by_another_path_is_refused(tmp_path):
    folder = tmp_path / "roomPNG"
    _with_ambient(folder)
    (folder / "sub").mkdir()
    names = (folder / "filenames.txt").read_text().split()
    (folder / "filenames.txt").write_text("\n".join(names[:-1] + ["sub/../ambient.png"]) + "\n")
    with pytest.raises(PsctlError, match="is the ambient image"):
        open_capture(folder)


def test_only_the_ambient_name_itself_is_kept_out_of_the_images(tmp_path):
    """ambient_room.png is not the ambient image, so it stays an input image (here one too many
    for the light file: an error that names it), never silently dropped."""
    folder = tmp_path / "roomPNG"
    _with_ambient(folder)
    (folder / "filenames.txt").unlink()
    (folder / "ambient.png").rename(folder / "ambient_room.png")
    with pytest.raises(PsctlError, match="12 light rows but 13 images"):
        open_capture(folder)


def test_ambient_and_encoding_reach_eval_and_depth(tmp_path):
    root = tmp_path / "bench"
    _with_ambient(root / "room")
    runner = CliRunner()
    r = runner.invoke(app, ["eval", "--benchmark", "folder", "--root", str(root), "-m", "l2", "--json"])
    assert r.exit_code == 0, r.output
    notes = json.loads(r.stdout)["objects"][0]["notes"]
    assert any(n.startswith("ambient: ambient.png subtracted") for n in notes)
    r = runner.invoke(app, ["eval", "--benchmark", "folder", "--root", str(root), "-m", "l2"])
    assert "room: ambient: ambient.png subtracted" in r.output
    r = runner.invoke(app, ["depth", str(root / "room"), "-o", str(tmp_path / "d"), "--encoding", "LINEAR", "--json"])
    assert r.exit_code == 0, r.output
    assert any(n.startswith("ambient:") for n in json.loads(r.stdout)["notes"])
    r = runner.invoke(app, ["info", str(root), "--encoding", "SRGB"], env={"COLUMNS": "200"})  # any case, as --method
    assert r.exit_code == 0 and "srgb" in r.output and "ambient.png" in r.output  # the columns shown


def test_an_out_folder_with_an_ambient_image_of_any_case_is_a_capture(tmp_path):
    from psctl.io.capture import holds_capture

    out = tmp_path / "out"
    out.mkdir()
    assert not holds_capture(out)
    write_image(out / "Ambient.PNG", np.zeros((4, 4, 3), np.float32), "uint8")
    assert holds_capture(out)


def test_later_passes_take_the_ambient_image_from_the_memo(tmp_path, monkeypatch):
    """Passes that share a DecodeMemo (sdps: LCNet, the light fit, the second stage) decode the
    ambient image once, as they do the images, with the same values; one changed since is read
    again."""
    import os

    import psctl.io.capture as capture_mod
    from psctl.arrays import bounding_box
    from psctl.io.capture import DecodeMemo, iter_images

    folder = tmp_path / "roomPNG"
    data = _with_ambient(folder)
    cap = open_capture(folder)
    box = bounding_box(data["mask"])
    plain = [im.copy() for im in iter_images(cap, box)]
    reads = []
    real = capture_mod.read_image
    monkeypatch.setattr(capture_mod, "read_image", lambda p, *a, **k: reads.append(p.name) or real(p, *a, **k))
    memo = DecodeMemo(1 << 26)
    for _ in range(3):
        assert all(np.array_equal(a, b) for a, b in zip(plain, iter_images(cap, box, memo=memo), strict=True))
    assert reads.count("ambient.png") == 1 and len(reads) == 13
    st = os.stat(folder / "ambient.png")
    os.utime(folder / "ambient.png", ns=(st.st_atime_ns, st.st_mtime_ns + 5 * 10**9))
    list(iter_images(cap, box, memo=memo))
    assert reads.count("ambient.png") == 2 and len(reads) == 14

"""sRGB-encoded images (camera JPEGs): read as linear radiance, by default for JPEGs, on request
for other files; a note says so; info shows it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from psctl.api import run_normals
from psctl.cli import app
from psctl.errors import PsctlError
from psctl.io.capture import load_images, open_capture
from psctl.io.images import srgb_to_linear, write_image
from tests.conftest import write_capture


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve (written here from the standard, independently of psctl)."""
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_srgb_curve_known_values():
    v = np.array([0.0, 0.04045, 0.5, 1.0, 2.0, -0.1])
    out = srgb_to_linear(v)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[:4], [0.0, 0.04045 / 12.92, 0.21404, 1.0], rtol=1e-4, atol=1e-7)
    assert out[4] > 1.0 and np.isfinite(out).all() and out[5] < 0
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=2e-6)
    assert (np.diff(srgb_to_linear(np.linspace(-1, 2, 3001))) > 0).all()


def _write_jpegs(folder: Path) -> dict:
    """The conftest sphere, its images stored sRGB-encoded as 8-bit JPEGs (quality 100)."""
    import OpenImageIO as oiio

    data = write_capture(folder, n=12, size=48, bits=8)
    names = []
    for k, img in enumerate(data["images"]):
        (folder / f"{k + 1:03d}.png").unlink()
        name = f"{k + 1:03d}.jpg"
        arr = np.round(linear_to_srgb(img) * 255).astype(np.uint8)
        spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], 3, oiio.UINT8)
        spec.attribute("Compression", "jpeg:100")
        out = oiio.ImageOutput.create(str(folder / name))
        assert out.open(str(folder / name), spec) and out.write_image(arr)
        out.close()
        names.append(name)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    return data


def test_jpegs_are_decoded_from_srgb_by_default(tmp_path):
    folder = tmp_path / "jpegPNG"
    data = _write_jpegs(folder)
    e = data["intensities"][:, None, None, :]
    truth = data["images"] / e
    m = data["mask"]
    auto = load_images(open_capture(folder))
    stored = load_images(open_capture(folder, "linear"))
    err_auto = np.abs(auto - truth)[:, m].mean()
    err_stored = np.abs(stored - truth)[:, m].mean()
    assert err_auto < 0.01 < err_stored  # JPEG's own loss is small next to the tone curve's

    r_auto = run_normals(folder, method="l2", write=False)
    r_lin = run_normals(folder, method="l2", write=False, encoding="linear")
    assert any("JPEG, decoded from sRGB" in n for n in r_auto["notes"])
    assert not any(n.startswith("encoding") for n in r_lin["notes"])
    assert r_auto["mae"] < 2.0 and r_lin["mae"] > r_auto["mae"] + 3.0


def test_jpeg_data_under_another_name_is_decoded_by_its_content(tmp_path):
    """A JPEG saved as .png (a renamed file, an export with the wrong extension) is still sRGB."""
    import shutil

    folder = tmp_path / "jpegPNG"
    _write_jpegs(folder)
    shutil.copytree(folder, tmp_path / "named")  # the same files under their JPEG names
    names = (folder / "filenames.txt").read_text().split()
    for name in names[:3]:  # three of them renamed
        (folder / name).rename(folder / name.replace(".jpg", ".png"))
    names[:3] = [n.replace(".jpg", ".png") for n in names[:3]]
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    cap = open_capture(folder)
    assert cap.srgb_images == 12 and cap.is_srgb(0)
    assert np.array_equal(load_images(cap), load_images(open_capture(tmp_path / "named")))
    note = next(n for n in run_normals(folder, method="l2", write=False)["notes"] if n.startswith("encoding"))
    assert "001.png, 002.png, 003.png: JPEG data, by their content" in note
    assert open_capture(folder, "linear").srgb_images == 0
    # psctl info: all twelve sRGB; one linear PNG among them makes the capture "mixed"
    from psctl.io.summary import describe_capture

    assert describe_capture(folder)["encoding"] == "srgb"
    from psctl.io.images import write_image

    (folder / names[3]).unlink()
    names[3] = "004.png"
    write_image(folder / "004.png", np.full((48, 48, 3), 0.3, np.float32), "uint16")
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    r = describe_capture(folder)
    assert r["encoding"] == "mixed" and r["srgb_images"] == 11


def test_other_data_under_a_jpeg_name_is_read_as_its_content(tmp_path):
    """The reverse (a QA helper's finding): 16-bit PNGs renamed .jpg were decoded from sRGB by
    their name (13.06 degrees instead of 0.89); their content decides, and a note says so."""
    png = tmp_path / "png"
    write_capture(png, n=12, size=40, intensities=False)
    folder = tmp_path / "named"
    folder.mkdir()
    names = []
    for p in sorted(png.iterdir()):
        if p.name[:3].isdigit():
            names.append(p.stem + ".jpg")
            (folder / names[-1]).write_bytes(p.read_bytes())
        elif p.name != "filenames.txt":
            (folder / p.name).write_bytes(p.read_bytes())
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    write_image(folder / "ambient.jpg.png", np.full((40, 40, 3), 0.01, np.float32), "uint16", kind="linear")
    (folder / "ambient.jpg.png").rename(folder / "ambient.jpg")  # an ambient image too
    cap = open_capture(folder)
    assert cap.srgb_images == 0 and not cap.is_srgb(cap.ambient_path)
    assert open_capture(folder, "srgb").srgb_images == 12  # on request, as before
    notes = [n for n in run_normals(folder, method="l2", write=False)["notes"] if n.startswith("encoding")]
    assert notes == ["encoding: 001.jpg, 002.jpg, 003.jpg ...: named JPEG but not JPEG data, read as linear as "
                     "their content's format is (--encoding srgb decodes them)"], notes
    (folder / "ambient.jpg").unlink()
    assert run_normals(folder, method="l2", write=False)["mae"] == run_normals(png, method="l2", write=False)["mae"]


def test_srgb_on_request_for_other_files(tmp_path):
    """A 16-bit PNG capture stored sRGB-encoded: right with --encoding srgb, wrong as read."""
    folder = tmp_path / "srgbPNG"
    data = write_capture(folder, n=12, size=40)
    for k, img in enumerate(data["images"]):
        write_image(folder / f"{k + 1:03d}.png", linear_to_srgb(img), "uint16")
    r_srgb = run_normals(folder, method="l2", write=False, encoding="srgb")
    r_auto = run_normals(folder, method="l2", write=False)
    # the same sphere stored linear (auto reads PNGs as stored): L2's error on it, rim included
    plain = tmp_path / "plainPNG"
    write_capture(plain, n=12, size=40)
    r_plain = run_normals(plain, method="l2", write=False)
    assert abs(r_srgb["mae"] - r_plain["mae"]) < 0.01 and r_auto["mae"] > r_plain["mae"] + 3.0
    assert any("decoded from sRGB to linear (--encoding srgb)" in n for n in r_srgb["notes"])
    assert not any(n.startswith("encoding") for n in r_plain["notes"])
    # written with OpenImageIO's sRGB chunk, as such files usually are: read as stored, and the note says
    # what --encoding srgb would do
    assert [n for n in r_auto["notes"] if n.startswith("encoding")] == [
        "encoding: all images say sRGB in PNG chunks but are read as stored, as linear (as DiLiGenT's PNGs, which "
        "say nothing; OpenImageIO, for one, tags a PNG sRGB unless told otherwise): if they came from a camera's "
        "JPEGs or an editor, --encoding srgb decodes every file from sRGB; --encoding linear reads every file as "
        "stored, without this note"]


def test_encoding_on_the_command_line(tmp_path):
    folder = tmp_path / "jpegPNG"
    _write_jpegs(folder)
    runner = CliRunner()
    r = runner.invoke(app, ["info", str(folder), "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["encoding"] == "srgb" and info["srgb_images"] == 12
    r = runner.invoke(app, ["info", str(folder), "--json", "--encoding", "linear"])
    assert json.loads(r.stdout)["encoding"] == "linear"
    r = runner.invoke(app, ["normals", str(folder), "-m", "l2", "-o", str(tmp_path / "out"), "--encoding", "gamma"])
    assert r.exit_code == 2 and "--encoding must be one of auto, linear, srgb" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "out").exists()
    with pytest.raises(PsctlError, match="--encoding must be one of"):
        open_capture(folder, "gamma")
    assert open_capture(folder, "sRGB").encoding == "srgb"  # any case, as --method

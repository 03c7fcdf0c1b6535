"""Images with an embedded ICC profile (TIFF or PNG exports of raw converters and editors): decoded
to linear through the profile's tone curves by default, read as stored when those are linear."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from typer.testing import CliRunner

from psctl.api import run_normals
from psctl.cli import app
from psctl.io.capture import load_images, open_capture
from psctl.io.icc import ToneCurve, read_profile
from psctl.io.images import image_info, read_image, write_image
from tests.conftest import write_capture


# --- ICC profiles, written here from the ICC.1 specification (independently of psctl's parser) ---
def _pad(body: bytes) -> bytes:
    return body + b"\0" * (-len(body) % 4)


def tone_curve(profile: bytes) -> ToneCurve | None:
    """read_profile's curves, or None where it gives a reason instead."""
    read = read_profile(profile)
    return read if isinstance(read, ToneCurve) else None


def curv_gamma(g: float) -> bytes:
    return b"curv\0\0\0\0" + struct.pack(">IH", 1, round(g * 256))


def curv_table(values) -> bytes:
    v = np.round(np.asarray(values) * 65535).astype(int)
    return b"curv\0\0\0\0" + struct.pack(f">I{len(v)}H", len(v), *v)


def para(ftype: int, *params: float) -> bytes:
    return b"para\0\0\0\0" + struct.pack(">HH", ftype, 0) + struct.pack(f">{len(params)}i",
                                                                       *(round(p * 65536) for p in params))


def desc(text: str) -> bytes:  # ICC v2 textDescriptionType
    t = text.encode() + b"\0"
    return b"desc\0\0\0\0" + struct.pack(">I", len(t)) + t + b"\0" * 79


def mluc(text: str) -> bytes:  # ICC v4 multiLocalizedUnicodeType, one record
    t = text.encode("utf-16-be")
    return b"mluc\0\0\0\0" + struct.pack(">II", 1, 12) + b"enUS" + struct.pack(">II", len(t), 28) + t


def profile(tags: dict[str, bytes], space: bytes = b"RGB ") -> bytes:
    offset, table, data = 128 + 4 + 12 * len(tags), b"", b""
    for sig, body in tags.items():
        table += sig.encode() + struct.pack(">II", offset + len(data), len(body))
        data += _pad(body)
    size = offset + len(data)
    header = struct.pack(">I", size) + b"none" + bytes([4, 0x20, 0, 0]) + b"mntr" + space + b"XYZ " + b"\0" * 12 + \
        b"acsp" + b"\0" * 88
    return header + struct.pack(">I", len(tags)) + table + data


def rgb_profile(name: str, curve: bytes) -> bytes:
    return profile({"desc": desc(name), "rTRC": curve, "gTRC": curve, "bTRC": curve})


SRGB_PARA = para(3, 2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045)


def srgb_decode(v):  # the sRGB standard's decoding curve
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def test_tone_curves_are_read_as_the_icc_specification_says():
    x = np.linspace(0, 1, 101)
    adobe = tone_curve(rgb_profile("Adobe RGB (1998)", curv_gamma(2.2)))
    assert adobe.name == "Adobe RGB (1998)" and not adobe.linear
    assert adobe.describe() == "'Adobe RGB (1998)', gamma 2.2"
    np.testing.assert_allclose(adobe.to_linear(np.stack([x] * 3, -1)), np.stack([x ** (563 / 256)] * 3, -1),
                               atol=2e-4)  # u8Fixed8: 2.2 is stored as 563/256
    srgb = tone_curve(profile({"desc": mluc("sRGB IEC61966-2.1"), "rTRC": SRGB_PARA, "gTRC": SRGB_PARA,
                               "bTRC": SRGB_PARA}))
    assert srgb.name == "sRGB IEC61966-2.1" and srgb.describe().startswith("'sRGB IEC61966-2.1', a parametric curve")
    np.testing.assert_allclose(srgb.to_linear(np.stack([x] * 3, -1))[:, 0], srgb_decode(x), atol=2e-4)
    table = tone_curve(rgb_profile("table", curv_table(srgb_decode(np.linspace(0, 1, 1024)))))
    np.testing.assert_allclose(table.to_linear(np.stack([x] * 3, -1))[:, 1], srgb_decode(x), atol=5e-4)
    for linear in (curv_gamma(1.0), b"curv\0\0\0\0" + struct.pack(">I", 0), para(0, 1.0)):
        assert tone_curve(rgb_profile("linear", linear)).linear
    grey = tone_curve(profile({"kTRC": curv_gamma(1.8)}, b"GRAY"))
    assert grey.name == "" and grey.describe() == "gamma 1.8" and not grey.linear
    mixed = tone_curve(profile({"rTRC": curv_gamma(1.8), "gTRC": curv_gamma(2.2), "bTRC": curv_gamma(2.2)}))
    assert mixed.describe() == "per-channel curves"
    assert (mixed.to_linear(np.full((1, 3), 0.5))[0, 0] > mixed.to_linear(np.full((1, 3), 0.5))[0, 1])
    # nothing psctl can read: no profile, CMYK, a lookup-table transform, damaged
    good = rgb_profile("x", curv_gamma(2.2))
    assert tone_curve(b"") is None and tone_curve(good[:150]) is None
    assert tone_curve(good.replace(b"acsp", b"xxxx")) is None
    assert tone_curve(profile({"rTRC": curv_gamma(2.2)}, b"CMYK")) is None
    assert tone_curve(profile({"rTRC": curv_gamma(2.2), "gTRC": curv_gamma(2.2)})) is None  # no bTRC
    assert tone_curve(rgb_profile("lut", b"mft2" + b"\0" * 60)) is None


def _write_profiled(folder, icc: bytes, encode, suffix: str = ".tif") -> dict:
    """The conftest sphere stored 16-bit through ``encode`` (the inverse of the profile's curve)
    with the profile embedded."""
    data = write_capture(folder, n=12, size=48)
    names = []
    for k, img in enumerate(data["images"]):
        (folder / f"{k + 1:03d}.png").unlink()
        names.append(f"{k + 1:03d}{suffix}")
        write_image(folder / names[-1], encode(np.clip(img, 0, 1)), "uint16", kind="data", icc=icc)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    return data


def test_a_capture_exported_with_a_tone_curve_is_decoded_through_its_profile(tmp_path):
    folder = tmp_path / "adobe"
    data = _write_profiled(folder, rgb_profile("Adobe RGB (1998)", curv_gamma(2.2)), lambda v: v ** (256 / 563))
    assert image_info(folder / "001.tif").tone.name == "Adobe RGB (1998)"
    truth = data["images"] / data["intensities"][:, None, None, :]
    cap = open_capture(folder)
    assert cap.profile_images == 12 and cap.srgb_images == 0
    assert np.abs(load_images(cap) - truth).max() < 2e-4
    decoded = run_normals(folder, method="l2", write=False)
    write_capture(tmp_path / "plain", n=12, size=48)  # the same capture stored linear, without a profile
    assert abs(decoded["mae"] - run_normals(tmp_path / "plain", method="l2", write=False)["mae"]) < 0.01
    assert [n for n in decoded["notes"] if n.startswith("encoding:")] == [
        "encoding: all images decoded to linear through their embedded ICC profile's tone curves "
        "('Adobe RGB (1998)', gamma 2.2) (--encoding linear reads them as stored)"]
    stored = run_normals(folder, method="l2", write=False, encoding="linear")
    assert stored["mae"] > decoded["mae"] + 3 and not any(n.startswith("encoding:") for n in stored["notes"])
    assert open_capture(folder, "srgb").profile_images == 0  # asked for: the sRGB curve for every file

    r = CliRunner().invoke(app, ["info", str(folder), "--json"])
    info = json.loads(r.stdout)
    assert (info["encoding"], info["profile_images"], info["profiles"]) == (
        "profile", 12, ["'Adobe RGB (1998)', gamma 2.2"])
    r = CliRunner().invoke(app, ["info", str(folder)])
    row = [line.split("│")[2].strip() for line in r.stdout.splitlines() if line.count("│") == 3]
    cells = " ".join(row[row.index(next(c for c in row if c.startswith("decoded"))):][:3])  # the wrapped encoding cell
    assert cells.startswith("decoded to linear through their ICC profiles ('Adobe RGB (1998)', gamma 2.2)"), cells


def test_a_linear_profile_reads_as_stored_and_a_jpeg_profile_wins_over_the_srgb_default(tmp_path):
    folder = tmp_path / "linear"
    data = _write_profiled(folder, rgb_profile("Linear Rec2020", curv_gamma(1.0)), lambda v: v, ".png")
    cap = open_capture(folder)
    assert cap.profile_images == 0 and cap.decoding(0) is None
    truth = data["images"] / data["intensities"][:, None, None, :]
    assert np.abs(load_images(cap) - truth).max() < 2e-4
    assert not any(n.startswith("encoding:") for n in run_normals(folder, method="l2", write=False)["notes"])

    jpegs = tmp_path / "jpegs"  # a phone JPEG's profile (sRGB's parametric curve): decoded through it
    data = write_capture(jpegs, n=12, size=48, bits=8)
    names = []
    for k, img in enumerate(data["images"]):
        (jpegs / f"{k + 1:03d}.png").unlink()
        names.append(f"{k + 1:03d}.jpg")
        v = np.clip(img, 0, 1)
        write_image(jpegs / names[-1], np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055), "uint8",
                    kind="data", icc=rgb_profile("Display P3", SRGB_PARA))
    (jpegs / "filenames.txt").write_text("\n".join(names) + "\n")
    cap = open_capture(jpegs)
    assert cap.profile_images == 12 and cap.srgb_images == 0 and cap.is_jpeg(0)
    lin = tmp_path / "linjpeg"  # a JPEG with a linear profile reads as stored, and says so (a review)
    lin.mkdir()
    write_image(lin / "a.jpg", np.full((8, 8, 3), 0.5, np.float32), "uint8", kind="data",
                icc=rgb_profile("linear", curv_gamma(1.0)))
    write_image(lin / "b.jpg", np.full((8, 8, 3), 0.5, np.float32), "uint8", kind="data")
    from psctl.io.capture import capture_notes

    assert "encoding: a.jpg: JPEG with a linear ICC profile, read as stored (--encoding srgb decodes them from " \
           "sRGB)" in capture_notes(open_capture(lin))
    assert open_capture(lin).decoding(1) == "srgb"
    write_capture(tmp_path / "plain8", n=12, size=48, bits=8)  # the same capture stored linear in 8 bits
    assert run_normals(jpegs, method="l2", write=False)["mae"] < \
        run_normals(tmp_path / "plain8", method="l2", write=False)["mae"] + 0.5


def test_ambient_image_and_undistort_keep_the_profile(tmp_path):
    icc = rgb_profile("ProPhoto RGB", curv_gamma(1.8))
    folder = tmp_path / "pro"
    data = _write_profiled(folder, icc, lambda v: v ** (256 / 461))
    ambient = np.full((48, 48, 3), 0.05, np.float32)
    for k, name in enumerate(sorted(p.name for p in folder.glob("*.tif"))):  # room light added, as recorded
        lit = np.clip(data["images"][k], 0, 1) + ambient
        write_image(folder / name, lit ** (256 / 461), "uint16", kind="data", icc=icc)
    write_image(folder / "ambient.tif", ambient ** (256 / 461), "uint16", kind="data", icc=icc)
    cap = open_capture(folder)
    assert cap.decoding(cap.ambient_path) is not None
    r = run_normals(folder, method="l2", write=False)
    write_capture(tmp_path / "plain", n=12, size=48)
    assert abs(r["mae"] - run_normals(tmp_path / "plain", method="l2", write=False)["mae"]) < 0.01  # both decoded
    assert any("ambient.tif (decoded through its ICC profile's tone curves: 'ProPhoto RGB', gamma 1.8)" in n
               for n in r["notes"])

    (tmp_path / "K.txt").write_text("40 0 23.5\n0 40 23.5\n0 0 1\n")
    out = CliRunner().invoke(app, ["undistort", str(folder), "-o", str(tmp_path / "flat"), "--K",
                                   str(tmp_path / "K.txt"), "-d", "0,0,0,0"])
    assert out.exit_code == 0, out.output
    assert image_info(tmp_path / "flat" / "001.tif").tone == image_info(folder / "001.tif").tone
    assert np.array_equal(read_image(tmp_path / "flat" / "001.tif")[0], read_image(folder / "001.tif")[0])
    assert abs(run_normals(tmp_path / "flat", method="l2", write=False)["mae"] - r["mae"]) < 1e-3


@pytest.mark.parametrize("suffix", [".tif", ".png"])
def test_write_image_embeds_a_profile(tmp_path, suffix):
    icc = rgb_profile("Adobe RGB (1998)", curv_gamma(2.2))
    write_image(tmp_path / f"a{suffix}", np.full((4, 5, 3), 0.5, np.float32), "uint16", icc=icc)
    assert image_info(tmp_path / f"a{suffix}").tone == tone_curve(icc)
    write_image(tmp_path / f"b{suffix}", np.full((4, 5, 3), 0.5, np.float32), "uint16")
    assert image_info(tmp_path / f"b{suffix}").tone is None


def test_parametric_curves_beyond_the_unit_range_and_odd_profiles():
    """A review: para types 1, 2 and 4 were never checked against values; a float file's values
    above 1 were clamped (a float TIFF with an sRGB profile: l2 5.07 degrees instead of 1.02);
    a decreasing table (an inverted picture) and a newline in a name were taken as they were."""
    x = np.linspace(0, 1, 201)
    g, a, b, c, d, e, f = 2.2, 0.9, 0.1, 0.05, 0.2, 0.01, 0.002
    cases = {
        1: ((g, a, b), np.where(x >= -b / a, (a * x + b) ** g, 0)),
        2: ((g, a, b, c), np.where(x >= -b / a, (a * x + b) ** g + c, c)),
        4: ((g, a, b, c, d, e, f), np.where(x >= d, (a * x + b) ** g + e, c * x + f)),
    }
    for ftype, (params, want) in cases.items():
        curve = tone_curve(rgb_profile(f"type {ftype}", para(ftype, *params)))
        np.testing.assert_allclose(curve.to_linear(np.stack([x] * 3, -1))[:, 2], np.clip(want, 0, 1), atol=1e-4,
                                   err_msg=f"para type {ftype}")
    # beyond [0, 1] (float files): the formula carried on, a table along its end slope, mirrored below 0
    v = np.array([[1.5, 2.0, -0.5]], np.float32)
    np.testing.assert_allclose(tone_curve(rgb_profile("g", curv_gamma(2.2))).to_linear(v)[0],
                               [1.5 ** (563 / 256), 2.0 ** (563 / 256), -(0.5 ** (563 / 256))], rtol=1e-4)
    srgb = tone_curve(profile({"rTRC": SRGB_PARA, "gTRC": SRGB_PARA, "bTRC": SRGB_PARA}))
    np.testing.assert_allclose(srgb.to_linear(v)[0], [srgb_decode(1.5), srgb_decode(2.0), -srgb_decode(0.5)],
                               rtol=1e-4)
    table = tone_curve(rgb_profile("t", curv_table(np.linspace(0, 1, 11) ** 2)))  # last step: 0.81 -> 1 over 0.1
    np.testing.assert_allclose(table.to_linear(np.array([[1.5, 1.0, 0.5]], np.float32))[0],
                               [1 + 0.5 * 1.9, 1.0, 0.25], rtol=1e-3)
    assert tone_curve(rgb_profile("down", curv_table(np.linspace(1, 0, 16)))) is None
    assert tone_curve(rgb_profile("bump", curv_table([0, 0.5, 0.4, 1.0]))) is None
    assert tone_curve(rgb_profile("two\nlines\x07", curv_gamma(2.2))).name == "two lines"


def test_float_files_above_one_and_jpeg_profiles_that_do_not_fit(tmp_path):
    folder = tmp_path / "float"  # linear values up to 2.5, sRGB-encoded unbounded, in float TIFFs
    data = write_capture(folder, n=12, size=48)
    icc = profile({"desc": desc("sRGB"), "rTRC": SRGB_PARA, "gTRC": SRGB_PARA, "bTRC": SRGB_PARA})
    names = []
    for k, img in enumerate(data["images"]):
        (folder / f"{k + 1:03d}.png").unlink()
        v = 2.5 * img
        names.append(f"{k + 1:03d}.tif")
        write_image(folder / names[-1], np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055), "float",
                    kind="data", icc=icc)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    assert max(read_image(folder / n)[0].max() for n in names) > 1.2
    truth = 2.5 * data["images"] / data["intensities"][:, None, None, :]
    assert np.abs(load_images(open_capture(folder)) - truth).max() < 1e-3 * truth.max()

    big = rgb_profile("big", curv_table(np.linspace(0, 1, 40_000) ** 1.8))  # over one JPEG segment
    assert len(big) > 65519
    with pytest.raises(Exception, match=r"a.jpg: cannot keep its ICC profile \([\d,]+ bytes; over 65,519"):
        write_image(tmp_path / "a.jpg", np.full((4, 4, 3), 0.5, np.float32), "uint8", icc=big)
    assert not (tmp_path / "a.jpg").exists()
    write_image(tmp_path / "a.tif", np.full((4, 4, 3), 0.5, np.float32), "uint16", icc=big)  # TIFF keeps it whole
    assert image_info(tmp_path / "a.tif").tone == tone_curve(big)


def test_notes_and_info_for_a_profile_under_a_jpeg_name_and_a_mixed_capture(tmp_path):
    """A review: a profiled PNG named .jpg was also noted as 'read as linear'; info's mixed row
    led with '0 of 12 images decoded from sRGB'; the ambient row did not say it was decoded."""
    folder = tmp_path / "mix"
    data = write_capture(folder, n=6, size=32)
    icc = rgb_profile("ProPhoto RGB", curv_gamma(1.8))
    names = [f"{k + 1:03d}.png" for k in range(6)]
    for k in (1, 3):  # two profiled PNGs, one of them named .jpg
        write_image(folder / names[k], np.clip(data["images"][k], 0, 1) ** (256 / 461), "uint16", kind="data", icc=icc)
    (folder / names[1]).rename(folder / "002.jpg")
    names[1] = "002.jpg"
    write_image(folder / "ambient.png", np.zeros((32, 32, 3), np.float32), "uint16", kind="data", icc=icc)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    cap = open_capture(folder)
    assert not cap.is_jpeg(1) and cap.decoding(1) is not None  # PNG data, by its content
    from psctl.io.capture import capture_notes

    notes = capture_notes(cap)
    assert not any("named JPEG" in n for n in notes)
    assert "encoding: 2 of 6 images (002.jpg, 004.png) decoded to linear through their embedded ICC profile's " \
           "tone curves ('ProPhoto RGB', gamma 1.8) (--encoding linear reads them as stored)" in notes
    r = CliRunner().invoke(app, ["info", str(folder), "--json"])
    info = json.loads(r.stdout)
    assert (info["encoding"], info["profile_images"], info["ambient_profile"]) == ("mixed", 2, True)
    r = CliRunner().invoke(app, ["info", str(folder)], env={"COLUMNS": "200"})
    assert "mixed: 2 of 6 through their ICC profiles ('ProPhoto RGB', gamma 1.8), 4 read as stored" in r.stdout
    assert "ambient.png, decoded through its ICC profile, subtracted from every image" in r.stdout

"""What image files say of their own encoding and psctl does not follow: a PNG's sRGB or gAMA
chunk (read as stored, with a note: many programs write one into every PNG), and an ICC profile
without tone curves psctl can read (read as a file without one, with a note)."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
from typer.testing import CliRunner

from psctl.api import run_normals
from psctl.cli import app
from psctl.io.capture import capture_notes, load_images, open_capture
from psctl.io.icc import ToneCurve, read_profile
from psctl.io.images import image_info, png_colour_tag, read_image, write_image
from tests.conftest import write_capture
from tests.test_icc import curv_gamma, desc, profile, rgb_profile


# --- PNGs written byte by byte from the PNG specification, with the chunks asked for ---
def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def tone_curve(profile: bytes) -> ToneCurve | None:
    """read_profile's curves, or None where it gives a reason instead."""
    read = read_profile(profile)
    return read if isinstance(read, ToneCurve) else None


def png_bytes(pixels: np.ndarray, chunks=()) -> bytes:
    """An 8-bit RGB PNG of ``pixels`` ([H, W, 3] uint8) with ``chunks`` ((kind, body), ...) before its data."""
    h, w, _ = pixels.shape
    raw = b"".join(b"\0" + pixels[y].tobytes() for y in range(h))
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + b"".join(_chunk(k, b) for k, b in chunks) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))


SRGB = (b"sRGB", b"\0")


def gama(g: float) -> tuple[bytes, bytes]:
    return (b"gAMA", struct.pack(">I", round(g * 100000)))


def test_png_colour_chunks_are_read(tmp_path):
    px = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    cases = {"none": ((), ""), "srgb": ((SRGB,), "sRGB"), "g45": ((gama(0.45455),), "gamma 2.2"),
             "g55": ((gama(1 / 1.8),), "gamma 1.8"), "g100": ((gama(1.0),), ""), "both": ((gama(0.45455), SRGB), "sRGB"),
             "cHRM": (((b"cHRM", b"\0" * 32), gama(0.45455)), "gamma 2.2"),  # other chunks between are skipped
             "bad": (((b"sRGB", b"\0\0"), (b"gAMA", b"\0\0")), ""),  # wrong lengths: no tag
             "big": (((b"sRGB", b"\0" * 9),), ""),  # longer than an sRGB chunk: skipped, not misread
             "g0": ((gama(0.0),), ""), "gmax": (((b"gAMA", b"\xff" * 4),), ""),  # out of range: ignored
             "pq": (((b"cICP", bytes([9, 16, 0, 1])), SRGB), "the PQ curve (HDR)"),  # cICP outranks sRGB
             "cicp_lin": (((b"cICP", bytes([1, 8, 0, 1])), SRGB), ""), "cicp_srgb": (((b"cICP", bytes([1, 13, 0, 1])),), "sRGB"),
             "cicp_odd": (((b"cICP", bytes([1, 7, 0, 1])),), "transfer characteristics 7 (cICP)")}
    for name, (chunks, tag) in cases.items():
        (tmp_path / f"{name}.png").write_bytes(png_bytes(px, chunks))
        assert png_colour_tag(tmp_path / f"{name}.png") == tag, name
        assert image_info(tmp_path / f"{name}.png").png_tag == tag, name
        assert np.array_equal(np.round(read_image(tmp_path / f"{name}.png")[0] * 255), px)  # pixels as stored
    # chunks after the pixels are not the file's colour chunks (the standard puts them before)
    after = png_bytes(px)
    (tmp_path / "after.png").write_bytes(after[:-12] + _chunk(b"sRGB", b"\0") + after[-12:])
    assert png_colour_tag(tmp_path / "after.png") == ""
    # a file cut short after the tag still says it (the header is read as far as it goes)
    (tmp_path / "cut.png").write_bytes(png_bytes(px, (SRGB,))[:60])
    assert png_colour_tag(tmp_path / "cut.png") == "sRGB"
    assert png_colour_tag(tmp_path / "missing.png") == ""
    # psctl's own kinds: pictures say sRGB (OpenImageIO's default), linear data gAMA 1, data nothing
    for kind, tag in (("picture", "sRGB"), ("linear", ""), ("data", "")):
        write_image(tmp_path / f"w_{kind}.png", np.full((3, 3, 3), 0.5, np.float32), "uint8", kind=kind)
        assert png_colour_tag(tmp_path / f"w_{kind}.png") == tag, kind
    write_image(tmp_path / "w.tif", np.full((3, 3, 3), 0.5, np.float32), "uint8")
    assert image_info(tmp_path / "w.tif").png_tag == ""


def _retag(folder, kind: str = "picture", gamma: float | None = None) -> None:
    """Rewrite a write_capture folder's images with other colour chunks, pixels unchanged."""
    for p in sorted(folder.glob("0*.png")):
        pixels = read_image(p)[0]
        if gamma is None:
            write_image(p, pixels, image_info(p).dtype, kind=kind)
        else:
            codes = np.round(pixels * 255).astype(np.uint8)
            p.write_bytes(png_bytes(codes, (gama(1 / gamma),)))


def test_a_png_tagged_srgb_is_read_as_stored_with_a_note(tmp_path):
    folder = tmp_path / "tagged"
    write_capture(folder, n=12, size=48, bits=8)
    plain = run_normals(folder, method="l2", write=False)
    before = load_images(open_capture(folder))
    assert not any(n.startswith("encoding:") for n in plain["notes"])  # gAMA 1 (conftest's): no note
    _retag(folder)
    cap = open_capture(folder)
    assert cap.png_tags == ("sRGB",) * 12 and cap.srgb_images == 0
    assert np.array_equal(load_images(cap), before)  # as stored
    r = run_normals(folder, method="l2", write=False)
    assert r["mae"] == plain["mae"]
    assert [n for n in r["notes"] if n.startswith("encoding:")] == [
        "encoding: all images say sRGB in PNG chunks but are read as stored, as linear (as DiLiGenT's PNGs, which "
        "say nothing; OpenImageIO, for one, tags a PNG sRGB unless told otherwise): if they came from a camera's "
        "JPEGs or an editor, --encoding srgb decodes every file from sRGB; --encoding linear reads every file as "
        "stored, without this note"]
    assert not any(n.startswith("encoding:") for n in run_normals(folder, method="l2", write=False,
                                                                     encoding="linear")["notes"])
    assert open_capture(folder, "srgb").srgb_images == 12  # what the note offers

    # some images only, and the ambient image, named; gamma 1.8 gets its own note
    _retag(folder, kind="linear")
    write_image(folder / "003.png", read_image(folder / "003.png")[0], "uint8", kind="picture")
    write_image(folder / "ambient.png", np.zeros((48, 48, 3), np.float32), "uint8", kind="picture")
    notes = [n for n in capture_notes(open_capture(folder)) if n.startswith("encoding:")]
    assert len(notes) == 1 and notes[0].startswith("encoding: 1 of 12 images (003.png) and ambient.png say sRGB"), notes
    assert open_capture(folder).png_tags.count("sRGB") == 1
    some = open_capture(folder).subset([2, 0])  # (psctl normals --images): the tags follow their images
    assert some.png_tags == ("sRGB", "") and some.profile_problems == ("", "")
    assert capture_notes(some)[-1].startswith("encoding: 1 of 2 images (003.png) and ambient.png say sRGB")
    _retag(folder, kind="linear")  # the ambient image alone: named, in the singular
    notes = [n for n in capture_notes(open_capture(folder)) if n.startswith("encoding:")]
    assert len(notes) == 1 and notes[0].startswith("encoding: ambient.png says sRGB in PNG chunks but is read as "
                                                   "stored"), notes
    assert "if it came from" in notes[0]
    (folder / "ambient.png").unlink()
    _retag(folder, gamma=2.22)  # a gamma near sRGB's: the sRGB note
    assert open_capture(folder).png_tags[0] == "gamma 2.22"
    assert capture_notes(open_capture(folder))[-1].startswith("encoding: all images say sRGB in PNG chunks")
    _retag(folder, gamma=1.8)
    notes = [n for n in capture_notes(open_capture(folder)) if n.startswith("encoding:")]
    assert notes == ["encoding: all images say gamma 1.8 in PNG chunks but are read as stored, as linear (psctl "
                     "decodes sRGB, --encoding srgb, and ICC profiles' curves, but no other curve): if so encoded, "
                     "convert them to linear first; --encoding linear reads every file as stored, without this note"]

    # psctl info shows the note (its encoding row says only how the images are decoded)
    out = CliRunner().invoke(app, ["info", str(folder)])
    assert out.exit_code == 0 and "say gamma 1.8 in PNG chunks" in out.stdout, out.stdout
    info = json.loads(CliRunner().invoke(app, ["info", str(folder), "--json"]).stdout)
    assert "say gamma 1.8" in " ".join(info["notes"]) and info["png_tags"] == {"gamma 1.8": 12}
    assert info["unreadable_profiles"] == 0


def test_a_readable_profile_outranks_the_png_chunks(tmp_path):
    folder = tmp_path / "profiled"
    write_capture(folder, n=12, size=48, bits=8)
    for p in sorted(folder.glob("0*.png")):  # a linear profile and OpenImageIO's sRGB chunks beside it
        write_image(p, read_image(p)[0], "uint8", kind="picture", icc=rgb_profile("Linear", curv_gamma(1.0)))
    write_image(folder / "ambient.png", np.zeros((48, 48, 3), np.float32), "uint8", kind="picture",
                icc=rgb_profile("Linear", curv_gamma(1.0)))
    cap = open_capture(folder)
    assert cap.png_tags[0] == cap.ambient_png_tag == "sRGB" and cap.decoding(0) is None
    assert not any(n.startswith("encoding:") for n in capture_notes(cap))


def test_a_profile_without_readable_curves_is_named_in_a_note(tmp_path):
    assert read_profile(b"") == "not an ICC profile, or damaged"
    cmyk = profile({"desc": desc("U.S. Web Coated (SWOP) v2"), "rTRC": curv_gamma(2.2)}, b"CMYK")
    assert read_profile(cmyk) == "'U.S. Web Coated (SWOP) v2': a profile of colour space 'CMYK', not RGB or grey"
    lut = profile({"desc": desc("Camera LUT"), "A2B0": b"mft2" + b"\0" * 60})
    assert read_profile(lut) == "'Camera LUT': no tone curves (a lookup-table profile)"
    odd = rgb_profile("odd", b"sf32" + b"\0" * 20)
    assert read_profile(odd) == "'odd': a tone curve of a kind psctl does not read, or damaged"
    falling = rgb_profile("inverted", b"curv\0\0\0\0" + struct.pack(">I3H", 3, 65535, 30000, 0))
    assert read_profile(falling) == "'inverted': a tone curve that falls or stays black"
    adobe = rgb_profile("Adobe RGB (1998)", curv_gamma(2.2))
    assert read_profile(adobe[:len(adobe) - 4]) == read_profile(adobe[:200]) == "damaged (cut short)"
    damaged = profile({"desc": desc("x"), "rTRC": curv_gamma(2.2)}, b" RGB")
    assert read_profile(damaged) == "'x': a profile of colour space ' RGB', not RGB or grey"
    assert tone_curve(lut) is None and read_profile(rgb_profile("ok", curv_gamma(2.2))) == tone_curve(
        rgb_profile("ok", curv_gamma(2.2)))

    folder = tmp_path / "lut"
    write_capture(folder, n=12, size=48)
    before = load_images(open_capture(folder))
    for p in sorted(folder.glob("0*.png")):
        write_image(p, read_image(p)[0], "uint16", kind="linear", icc=lut)
    assert image_info(folder / "001.png").profile_problem == "'Camera LUT': no tone curves (a lookup-table profile)"
    cap = open_capture(folder)
    assert cap.profile_images == 0 and cap.decoding(0) is None
    assert np.array_equal(load_images(cap), before)
    note = ("encoding: all images embed an ICC profile that psctl cannot take tone curves from ('Camera LUT': no "
            "tone curves (a lookup-table profile)): read as a file without one is (JPEG data decoded from sRGB, "
            "other data as stored); --encoding linear or --encoding srgb sets how every file is read")
    assert [n for n in capture_notes(cap) if n.startswith("encoding:")] == [note]
    assert not any(n.startswith("encoding:") for n in capture_notes(open_capture(folder, "linear")))
    out = CliRunner().invoke(app, ["info", str(folder)])
    assert "cannot take tone curves from" in out.stdout, out.stdout
    assert json.loads(CliRunner().invoke(app, ["info", str(folder), "--json"]).stdout)["unreadable_profiles"] == 12

    p = folder / "001.png"  # beside an sRGB chunk, both are named: the chunk is what is left to go by
    write_image(p, read_image(p)[0], "uint16", kind="picture", icc=lut)
    notes = [n for n in capture_notes(open_capture(folder)) if n.startswith("encoding:")]
    assert notes[0] == note and \
        notes[1].startswith("encoding: 1 of 12 images (001.png) says sRGB in PNG chunks"), notes

    jpg = tmp_path / "jpg"  # a JPEG with such a profile: decoded from sRGB, as without one, and both notes say so
    jpg.mkdir()
    write_image(jpg / "a.jpg", np.full((8, 8, 3), 0.5, np.float32), "uint8", kind="data", icc=lut)
    cap = open_capture(jpg)
    assert cap.decoding(0) == "srgb"
    notes = capture_notes(cap)
    assert any("cannot take tone curves" in n for n in notes) and any("decoded from sRGB" in n for n in notes)


def test_a_png_named_jpeg_gets_one_note(tmp_path):
    folder = tmp_path / "named"
    folder.mkdir()
    for k in range(3):  # PNG data tagged sRGB under .jpg names: the misnamed note says how they are read
        write_image(folder / f"{k}.jpg.png", np.full((8, 8, 3), 0.5, np.float32), "uint8", kind="picture")
        (folder / f"{k}.jpg.png").rename(folder / f"{k}.jpg")
    notes = [n for n in capture_notes(open_capture(folder)) if n.startswith("encoding:")]
    assert len(notes) == 1 and "named JPEG but not JPEG data" in notes[0], notes


def test_undistort_keeps_a_png_srgb_tag(tmp_path):
    folder = tmp_path / "cap"
    write_capture(folder, n=6, size=32)
    _retag(folder)
    write_image(folder / "002.png", read_image(folder / "002.png")[0], "uint16", kind="linear")
    (tmp_path / "K.txt").write_text("30 0 15.5\n0 30 15.5\n0 0 1\n")
    out = CliRunner().invoke(app, ["undistort", str(folder), "-o", str(tmp_path / "flat"), "--K",
                                   str(tmp_path / "K.txt"), "-d", "0,0,0,0"])
    assert out.exit_code == 0, out.output
    assert image_info(tmp_path / "flat" / "001.png").png_tag == "sRGB"
    for name, gamma in (("003.png", 1.8), ("004.png", 2.22)):  # a gamma's gAMA chunk too (a review)
        codes = np.round(read_image(folder / name)[0] * 255).astype(np.uint8)
        (folder / name).write_bytes(png_bytes(codes, (gama(1 / gamma),)))
    out = CliRunner().invoke(app, ["undistort", str(folder), "-o", str(tmp_path / "flat2"), "--K",
                                   str(tmp_path / "K.txt"), "-d", "0,0,0,0"])
    assert out.exit_code == 0, out.output
    assert [image_info(tmp_path / "flat2" / n).png_tag for n in ("003.png", "004.png")] == ["gamma 1.8", "gamma 2.22"]
    assert np.array_equal(read_image(tmp_path / "flat2" / "003.png")[0], read_image(folder / "003.png")[0])
    assert image_info(tmp_path / "flat" / "002.png").png_tag == "" and \
        "lin" in image_info(tmp_path / "flat" / "002.png").color_space

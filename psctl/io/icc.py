"""The tone curve of an image's embedded ICC profile.

Photometric stereo needs pixel values proportional to radiance. A TIFF or PNG exported by a raw
converter or an image editor usually carries an ICC profile that says how its values were
encoded: its tone reproduction curves (the rTRC, gTRC and bTRC tags, or kTRC for grey) map each
stored value to linear light. Adobe RGB's is a gamma of 2.2, ProPhoto's 1.8, sRGB's the sRGB
curve; a linear export (darktable's or RawTherapee's linear profiles) has a gamma of 1. psctl
decodes an image through its profile's curves (``encoding="auto"``) and reads one whose curves
are linear as stored. Only the curves matter here: the profile's primaries mix the channels
linearly, which keeps each channel proportional to radiance.

The parser reads the ICC.1 tag table and the two curve types, ``curv`` (identity, a gamma, or a
sampled table) and ``para`` (the five parametric functions). Anything else (a profile whose TRC
is a lookup-table transform, a CMYK or Lab profile, a damaged one) gives the reason instead
(``read_profile``), which a note repeats, and the image is read as it would be without a profile.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

import numpy as np

# a curve within this of the identity over [0, 1] is linear (an 8-bit step is 0.0039)
LINEAR_TOLERANCE = 1e-3
_CODES = 65535  # values in [0, 1] are looked up at this many steps: exact for 8- and 16-bit files


@dataclass(frozen=True)
class ToneCurve:
    """An ICC profile's tone curves, one per channel (three; grey: the same one three times).

    ``curves``: each channel's curve as the profile stores it: ``("identity",)``, ``("gamma", g)``,
    ``("table", bytes)`` (the profile's big-endian 16-bit samples, uniform over [0, 1]) or
    ``("para", type, (g, a, b, ...))``. ``name``: the profile's description ("Adobe RGB (1998)";
    "" when it has none)."""

    name: str
    curves: tuple[tuple, tuple, tuple]

    @functools.cached_property
    def linear(self) -> bool:
        """Whether every curve is the identity within LINEAR_TOLERANCE (values read as stored)."""
        x = np.linspace(0.0, 1.0, 257)
        return all(float(np.abs(_evaluate(c, x) - x).max()) <= LINEAR_TOLERANCE for c in self.curves)

    @functools.cached_property
    def _tables(self) -> np.ndarray:
        """[3, _CODES + 1] float32: each channel's curve at k / _CODES."""
        x = np.linspace(0.0, 1.0, _CODES + 1)
        return np.stack([_evaluate(c, x) for c in self.curves]).astype(np.float32)

    def describe(self) -> str:
        """A few words for notes: the profile's name and its curve ("'Adobe RGB (1998)', gamma 2.2")."""
        kinds = {_describe(c) for c in self.curves}
        curve = kinds.pop() if len(kinds) == 1 else "per-channel curves"
        return f"'{self.name}', {curve}" if self.name else curve

    def to_linear(self, values: np.ndarray) -> np.ndarray:
        """Stored values (any shape [..., C], C <= 3; integer files' in [0, 1]) -> linear values,
        float32. Values in [0, 1] are looked up at 1/65535 steps (exact for 8- and 16-bit
        files); a float file's values outside it follow the curve beyond (a gamma or parametric
        curve's formula, a table's end slope; below 0, mirrored), not clipped (as
        ``srgb_to_linear`` does not clip, though it carries its linear segment on below 0)."""
        values = np.asarray(values, np.float32)
        out = np.empty(values.shape, np.float32)
        tables = self._tables
        for ch in range(values.shape[-1]):
            v = values[..., ch]
            inside = np.isfinite(v) & (v >= 0) & (v <= 1)
            if inside.all():
                out[..., ch] = tables[min(ch, 2)][np.rint(v * _CODES).astype(np.int32)]
                continue
            lookup = tables[min(ch, 2)][np.rint(np.where(inside, v, 0) * _CODES).astype(np.int32)]
            far = np.abs(v[~inside].astype(np.float64))
            beyond = np.sign(v[~inside]) * _evaluate(self.curves[min(ch, 2)], far, extend=True)
            lookup[~inside] = beyond
            out[..., ch] = lookup
        return out


def _describe(curve: tuple) -> str:
    if curve[0] == "identity":
        return "linear"
    if curve[0] == "gamma":
        return f"gamma {curve[1]:.3g}"
    if curve[0] == "table":
        return f"a {len(curve[1]) // 2}-point curve"
    return f"a parametric curve (gamma {curve[2][0]:.3g})"


def _table(curve: tuple) -> np.ndarray:
    return np.frombuffer(curve[1], ">u2").astype(np.float64) / 65535.0


def _evaluate(curve: tuple, x: np.ndarray, extend: bool = False) -> np.ndarray:
    """The curve at ``x`` (float64): in [0, 1], clipped to [0, 1]; with ``extend``, ``x`` >= 0
    beyond 1 as well (a formula carried on, a table along its last step's slope), unclipped
    above."""
    kind = curve[0]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if kind == "identity":
            y = x.copy()
        elif kind == "gamma":
            y = x ** curve[1]
        elif kind == "table":
            table = _table(curve)
            grid = np.linspace(0.0, 1.0, len(table))
            y = np.interp(x, grid, table)
            if extend:
                slope = (table[-1] - table[-2]) * (len(table) - 1)
                y = np.where(x > 1, table[-1] + (x - 1) * slope, y)
        else:  # ICC.1 parametricCurveType, functions 0-4
            ftype, p = curve[1], curve[2]
            g, a, b, c, d, e, f = (*p, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)[:7] if ftype != 0 else (p[0], 1, 0, 0, 0, 0, 0)
            if ftype == 0:
                y = x ** g
            elif ftype == 1:
                y = np.where(x >= -b / a, np.maximum(a * x + b, 0.0) ** g, 0.0)
            elif ftype == 2:
                y = np.where(x >= -b / a, np.maximum(a * x + b, 0.0) ** g + c, c)
            elif ftype == 3:
                y = np.where(x >= d, np.maximum(a * x + b, 0.0) ** g, c * x)
            else:
                y = np.where(x >= d, np.maximum(a * x + b, 0.0) ** g + e, c * x + f)
    y = np.nan_to_num(y, posinf=np.finfo(np.float32).max)
    return np.maximum(y, 0.0) if extend else np.clip(y, 0.0, 1.0)


def _s15f16(data: bytes, at: int, n: int) -> tuple[float, ...]:
    return tuple(v / 65536.0 for v in struct.unpack_from(f">{n}i", data, at))


def _curve(data: bytes, at: int, size: int) -> tuple | None:
    """A curv or para tag at offset ``at``, or None when it is neither or is damaged."""
    kind = data[at:at + 4]
    if kind == b"curv":
        (count,) = struct.unpack_from(">I", data, at + 8)
        if 12 + 2 * count > size:
            return None
        if count == 0:
            return ("identity",)
        if count == 1:
            (g,) = struct.unpack_from(">H", data, at + 12)
            return ("gamma", g / 256.0) if g else None  # u8Fixed8Number
        return ("table", bytes(data[at + 12:at + 12 + 2 * count]))
    if kind == b"para":
        (ftype,) = struct.unpack_from(">H", data, at + 8)
        n = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}.get(ftype)
        if n is None or 12 + 4 * n > size:
            return None
        params = _s15f16(data, at + 12, n)
        if params[0] <= 0 or (ftype in (1, 2) and params[1] == 0):
            return None
        return ("para", ftype, params)
    return None


def _description(data: bytes, at: int, size: int) -> str:
    """The profile's description: a v2 ``desc`` (ASCII) or a v4 ``mluc`` (UTF-16, first record)."""
    kind = data[at:at + 4]
    if kind == b"desc":
        (count,) = struct.unpack_from(">I", data, at + 8)
        text = data[at + 12:at + 12 + min(count, size - 12)]
        return text.split(b"\0", 1)[0].decode("latin-1").strip()
    if kind == b"mluc":
        records, _ = struct.unpack_from(">II", data, at + 8)
        if records:
            length, offset = struct.unpack_from(">II", data, at + 16 + 4)
            return data[at + offset:at + offset + length].decode("utf-16-be", "replace").strip("\0 ").strip()
    return ""


@functools.lru_cache(maxsize=64)  # a capture's images share one profile: parsed once, one table kept
def read_profile(profile: bytes) -> ToneCurve | str:
    """The tone curves of an ICC profile (its bytes, as an image file embeds them), or a few words
    on why psctl cannot take them from it: not an RGB or grey profile, no curv/para curves (a
    lookup-table profile), a curve that decreases, damaged."""
    data = bytes(profile)
    try:
        if len(data) < 132 or data[36:40] != b"acsp":
            return "not an ICC profile, or damaged"
        if struct.unpack_from(">I", data, 0)[0] > len(data):  # the header's size: tags past the end are lost
            return "damaged (cut short)"
        space = data[16:20]
        (count,) = struct.unpack_from(">I", data, 128)
        tags = {}
        for i in range(min(count, 1000)):
            sig, offset, size = struct.unpack_from(">4sII", data, 132 + 12 * i)
            if offset + size <= len(data):
                tags[sig] = (offset, size)
        name = _description(data, *tags[b"desc"]) if b"desc" in tags else ""
        name = " ".join("".join(ch if ch.isprintable() else " " for ch in name).split())  # one line in notes
        named = f"'{name}': " if name else ""
        wanted = (b"rTRC", b"gTRC", b"bTRC") if space == b"RGB " else (b"kTRC",) * 3 if space == b"GRAY" else None
        if wanted is None:
            return f"{named}a profile of colour space {space.decode('latin-1')!r}, not RGB or grey"
        if any(t not in tags for t in wanted):
            return f"{named}no tone curves (a lookup-table profile)"
        curves = tuple(_curve(data, *tags[t]) for t in wanted)
        if any(c is None for c in curves):
            return f"{named}a tone curve of a kind psctl does not read, or damaged"
        x = np.linspace(0.0, 1.0, 257)
        if any((np.diff(_evaluate(c, x)) < -1e-6).any() or _evaluate(c, x)[-1] <= 0 for c in curves):
            # no camera's or editor's: an inverted picture's, or one that stays black
            return f"{named}a tone curve that falls or stays black"
        return ToneCurve(name, curves)
    except (struct.error, UnicodeDecodeError, IndexError):
        return "damaged"

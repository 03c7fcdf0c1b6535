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
is a lookup-table transform, a CMYK or Lab profile, a damaged one) gives None, and the image is
read as it would be without a profile.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

# a curve within this of the identity over [0, 1] is linear (an 8-bit step is 0.0039)
LINEAR_TOLERANCE = 1e-3
_SAMPLES = 4096  # the curves are applied through a table of this many samples, interpolated


@dataclass(frozen=True)
class ToneCurve:
    """An ICC profile's tone curves, one per channel (three; grey: the same one three times).

    ``curves``: each channel's curve as the profile stores it: ``("identity",)``, ``("gamma", g)``,
    ``("table", (v0, v1, ...))`` (values in [0, 1], sampled uniformly over [0, 1]) or
    ``("para", type, (g, a, b, ...))``. ``name``: the profile's description ("Adobe RGB (1998)";
    "" when it has none)."""

    name: str
    curves: tuple[tuple, tuple, tuple]

    @property
    def linear(self) -> bool:
        """Whether every curve is the identity within LINEAR_TOLERANCE (values read as stored)."""
        x = np.linspace(0.0, 1.0, 257)
        return all(float(np.abs(_evaluate(c, x) - x).max()) <= LINEAR_TOLERANCE for c in self.curves)

    def describe(self) -> str:
        """A few words for notes: the profile's name and its curve ("'Adobe RGB (1998)', gamma 2.2")."""
        kinds = {_describe(c) for c in self.curves}
        curve = kinds.pop() if len(kinds) == 1 else "per-channel curves"
        return f"'{self.name}', {curve}" if self.name else curve

    def to_linear(self, values: np.ndarray) -> np.ndarray:
        """Stored values in [0, 1] (any shape [..., 3]) -> linear values, float32; values outside
        [0, 1] are clamped to it (the curves are defined there)."""
        x = np.linspace(0.0, 1.0, _SAMPLES)
        out = np.empty(values.shape, np.float32)
        for ch in range(values.shape[-1]):
            curve = self.curves[min(ch, 2)]
            out[..., ch] = np.interp(values[..., ch], x, _evaluate(curve, x))
        return out


def _describe(curve: tuple) -> str:
    if curve[0] == "identity":
        return "linear"
    if curve[0] == "gamma":
        return f"gamma {curve[1]:.3g}"
    if curve[0] == "table":
        return f"a {len(curve[1])}-point curve"
    return f"a parametric curve (gamma {curve[2][0]:.3g})"


def _evaluate(curve: tuple, x: np.ndarray) -> np.ndarray:
    """The curve at ``x`` in [0, 1] (float64), clipped to [0, 1]."""
    kind = curve[0]
    if kind == "identity":
        y = x.copy()
    elif kind == "gamma":
        y = x ** curve[1]
    elif kind == "table":
        table = np.asarray(curve[1], np.float64)
        y = np.interp(x, np.linspace(0.0, 1.0, len(table)), table)
    else:  # ICC.1 parametricCurveType, functions 0-4
        ftype, p = curve[1], curve[2]
        g, a, b, c, d, e, f = (*p, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)[:7] if ftype != 0 else (p[0], 1, 0, 0, 0, 0, 0)
        with np.errstate(invalid="ignore", divide="ignore"):
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
    return np.clip(np.nan_to_num(y), 0.0, 1.0)


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
        values = struct.unpack_from(f">{count}H", data, at + 12)
        if count == 1:
            return ("gamma", values[0] / 256.0) if values[0] else None  # u8Fixed8Number
        return ("table", tuple(v / 65535.0 for v in values))
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


def tone_curve(profile: bytes) -> ToneCurve | None:
    """The tone curves of an ICC profile (its bytes, as an image file embeds them); None when the
    profile is not an RGB or grey one with curv/para curves, or cannot be parsed."""
    data = bytes(profile)
    try:
        if len(data) < 132 or data[36:40] != b"acsp":
            return None
        space = data[16:20]
        (count,) = struct.unpack_from(">I", data, 128)
        tags = {}
        for i in range(min(count, 1000)):
            sig, offset, size = struct.unpack_from(">4sII", data, 132 + 12 * i)
            if offset + size <= len(data):
                tags[sig] = (offset, size)
        wanted = (b"rTRC", b"gTRC", b"bTRC") if space == b"RGB " else (b"kTRC",) * 3 if space == b"GRAY" else None
        if wanted is None or any(t not in tags for t in wanted):
            return None
        curves = tuple(_curve(data, *tags[t]) for t in wanted)
        if any(c is None for c in curves):
            return None
        name = _description(data, *tags[b"desc"]) if b"desc" in tags else ""
        return ToneCurve(name, curves)
    except (struct.error, UnicodeDecodeError, IndexError):
        return None

"""Pictures for people: the angular-error heat map with a colour bar and its numbers.

Drawn with NumPy and a built-in 5 x 7 pixel font, so no plotting library is needed.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from psctl.io.atomic import write_text_atomic
from psctl.io.images import write_image

_FONT = {  # 5 x 7 glyphs, '#' = ink
    "0": [" ### ", "#   #", "#  ##", "# # #", "##  #", "#   #", " ### "],
    "1": ["  #  ", " ##  ", "  #  ", "  #  ", "  #  ", "  #  ", " ### "],
    "2": [" ### ", "#   #", "    #", "   # ", "  #  ", " #   ", "#####"],
    "3": ["#####", "   # ", "  #  ", "   # ", "    #", "#   #", " ### "],
    "4": ["   # ", "  ## ", " # # ", "#  # ", "#####", "   # ", "   # "],
    "5": ["#####", "#    ", "#### ", "    #", "    #", "#   #", " ### "],
    "6": ["  ## ", " #   ", "#    ", "#### ", "#   #", "#   #", " ### "],
    "7": ["#####", "    #", "   # ", "  #  ", " #   ", " #   ", " #   "],
    "8": [" ### ", "#   #", "#   #", " ### ", "#   #", "#   #", " ### "],
    "9": [" ### ", "#   #", "#   #", " ####", "    #", "   # ", " ##  "],
    ".": ["     ", "     ", "     ", "     ", "     ", " ##  ", " ##  "],
    ":": ["     ", " ##  ", " ##  ", "     ", " ##  ", " ##  ", "     "],
    "°": [" ##  ", "#  # ", "#  # ", " ##  ", "     ", "     ", "     "],
    ">": ["#    ", " #   ", "  #  ", "   # ", "  #  ", " #   ", "#    "],
    "-": ["     ", "     ", "     ", "#####", "     ", "     ", "     "],
    " ": ["     "] * 7,
    "A": [" ### ", "#   #", "#   #", "#####", "#   #", "#   #", "#   #"],
    "D": ["#### ", "#   #", "#   #", "#   #", "#   #", "#   #", "#### "],
    "E": ["#####", "#    ", "#    ", "#### ", "#    ", "#    ", "#####"],
    "I": [" ### ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", " ### "],
    "M": ["#   #", "## ##", "# # #", "# # #", "#   #", "#   #", "#   #"],
    "N": ["#   #", "##  #", "# # #", "#  ##", "#   #", "#   #", "#   #"],
}


def text_bitmap(text: str, scale: int = 1) -> np.ndarray:
    """Render ``text`` (digits, '.', ':', '°', '>', '-', and A D E I M N) as a bool bitmap."""
    glyphs = [np.array([[c == "#" for c in row] for row in _FONT.get(ch, _FONT[" "])]) for ch in text.upper()]
    gap = np.zeros((7, 1), bool)
    parts = []
    for g in glyphs:
        parts += [g, gap]
    bm = np.concatenate(parts[:-1], axis=1) if parts else np.zeros((7, 0), bool)
    return np.kron(bm, np.ones((scale, scale), bool))


def jet(x: np.ndarray) -> np.ndarray:
    """The 'jet' colour map, [..] in [0, 1] -> [.., 3]; the convention of PS error figures."""
    x = np.clip(x, 0.0, 1.0)[..., None]
    centres = np.array([0.75, 0.5, 0.25])
    return np.clip(1.5 - np.abs(4.0 * x - 4.0 * centres), 0.0, 1.0).astype(np.float32)


def _stamp(canvas: np.ndarray, bitmap: np.ndarray, y: int, x: int, colour=(1.0, 1.0, 1.0)) -> None:
    h, w = bitmap.shape
    y2, x2 = min(y + h, canvas.shape[0]), min(x + w, canvas.shape[1])
    if y2 <= y or x2 <= x:
        return
    canvas[y:y2, x:x2][bitmap[: y2 - y, : x2 - x]] = colour


def error_heatmap(error: np.ndarray, mask: np.ndarray, vmax: float = 45.0,
                  title: str | None = None) -> np.ndarray:
    """Angular-error picture [H', W', 3] in [0, 1]: the map in jet over 0..vmax degrees on a
    dark background, a colour bar with tick labels on the right, ``title`` on top."""
    h, w = error.shape
    s = max(1, min(h, w) // 200)
    top, bar_w, right = 12 * s, 10 * s, 44 * s
    canvas = np.full((h + top + 4 * s, max(w + right, 8 + 6 * s * len(title or ""), 1), 3), 0.12, np.float32)
    img = np.where(mask[..., None], jet(error / vmax), 0.0)
    canvas[top:top + h, :w] = img
    # colour bar: high values on top
    bx, bh = w + 4 * s, h
    ramp = np.linspace(1.0, 0.0, bh)[:, None].repeat(bar_w, axis=1)
    canvas[top:top + bh, bx:bx + bar_w] = jet(ramp)
    for frac in (0.0, 1 / 3, 2 / 3, 1.0):
        y = top + int(round((1 - frac) * (bh - 1)))
        label = f"{vmax * frac:.0f}°" if frac < 1 else f">{vmax:.0f}°"
        bm = text_bitmap(label, s)
        _stamp(canvas, bm, min(max(y - bm.shape[0] // 2, top), top + bh - bm.shape[0]), bx + bar_w + 2 * s)
    if title:
        _stamp(canvas, text_bitmap(title, s), 2 * s, 2 * s)
    return canvas


def write_error_map(path: str | os.PathLike, error: np.ndarray, mask: np.ndarray,
                    mae: float | None = None, median: float | None = None, vmax: float = 45.0) -> None:
    """error: [H, W] degrees (any value outside the mask). Writes an 8-bit RGB PNG."""
    title = None
    if mae is not None:
        title = f"MAE {mae:.2f}°" + (f"  MEDIAN {median:.2f}°" if median is not None else "")
    write_image(path, error_heatmap(error, mask, vmax, title), "uint8")


def write_json(path: str | os.PathLike, obj: dict) -> None:
    write_text_atomic(Path(path), json.dumps(obj, indent=2) + "\n")

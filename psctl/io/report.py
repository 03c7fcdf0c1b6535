"""Pictures for people: the angular-error heat map with a colour bar and its numbers, and the
sheet of a whole benchmark run (normal and error maps of every object).

Drawn with NumPy and a built-in 5 x 7 pixel font (g, j, p, q and y 2 rows longer, below the
line), so no plotting library is needed.
"""

from __future__ import annotations

import collections
import json
import math
import os
from pathlib import Path

import numpy as np

from psctl.io.atomic import write_text_atomic
from psctl.io.images import write_image

_FONT = {  # 5 x 7 glyphs (5 x 9 with a tail), '#' = ink
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
    "B": ["#### ", "#   #", "#   #", "#### ", "#   #", "#   #", "#### "],
    "C": [" ### ", "#   #", "#    ", "#    ", "#    ", "#   #", " ### "],
    "F": ["#####", "#    ", "#    ", "#### ", "#    ", "#    ", "#    "],
    "G": [" ### ", "#   #", "#    ", "# ###", "#   #", "#   #", " ####"],
    "H": ["#   #", "#   #", "#   #", "#####", "#   #", "#   #", "#   #"],
    "J": ["  ###", "   # ", "   # ", "   # ", "   # ", "#  # ", " ##  "],
    "K": ["#   #", "#  # ", "# #  ", "##   ", "# #  ", "#  # ", "#   #"],
    "L": ["#    ", "#    ", "#    ", "#    ", "#    ", "#    ", "#####"],
    "O": [" ### ", "#   #", "#   #", "#   #", "#   #", "#   #", " ### "],
    "P": ["#### ", "#   #", "#   #", "#### ", "#    ", "#    ", "#    "],
    "Q": [" ### ", "#   #", "#   #", "#   #", "# # #", "#  # ", " ## #"],
    "R": ["#### ", "#   #", "#   #", "#### ", "# #  ", "#  # ", "#   #"],
    "S": [" ####", "#    ", "#    ", " ### ", "    #", "    #", "#### "],
    "T": ["#####", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  "],
    "U": ["#   #", "#   #", "#   #", "#   #", "#   #", "#   #", " ### "],
    "V": ["#   #", "#   #", "#   #", "#   #", "#   #", " # # ", "  #  "],
    "W": ["#   #", "#   #", "#   #", "# # #", "# # #", "# # #", " # # "],
    "X": ["#   #", "#   #", " # # ", "  #  ", " # # ", "#   #", "#   #"],
    "Y": ["#   #", "#   #", " # # ", "  #  ", "  #  ", "  #  ", "  #  "],
    "Z": ["#####", "    #", "   # ", "  #  ", " #   ", "#    ", "#####"],
    "_": ["     ", "     ", "     ", "     ", "     ", "     ", "#####"],
    "+": ["     ", "  #  ", "  #  ", "#####", "  #  ", "  #  ", "     "],
    "/": ["    #", "    #", "   # ", "  #  ", " #   ", "#    ", "#    "],
    "(": ["   # ", "  #  ", " #   ", " #   ", " #   ", "  #  ", "   # "],
    ")": [" #   ", "  #  ", "   # ", "   # ", "   # ", "  #  ", " #   "],
    ",": ["     ", "     ", "     ", "     ", " ##  ", "  #  ", " #   "],
    "=": ["     ", "     ", "#####", "     ", "#####", "     ", "     "],
    "?": [" ### ", "#   #", "    #", "   # ", "  #  ", "     ", "  #  "],
    # the rest of printable ASCII, so that an object's or a folder's name is drawn as it is spelt
    "!": ["  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "     ", "  #  "],
    '"': [" # # ", " # # ", "     ", "     ", "     ", "     ", "     "],
    "#": [" # # ", " # # ", "#####", " # # ", "#####", " # # ", " # # "],
    "$": ["  #  ", " ####", "# #  ", " ### ", "  # #", "#### ", "  #  "],
    "%": ["##   ", "##  #", "   # ", "  #  ", " #   ", "#  ##", "   ##"],
    "&": [" ##  ", "#  # ", "# #  ", " #   ", "# # #", "#  # ", " ## #"],
    "'": ["  #  ", "  #  ", "     ", "     ", "     ", "     ", "     "],
    "*": ["     ", "  #  ", "# # #", " ### ", "# # #", "  #  ", "     "],
    ";": ["     ", " ##  ", " ##  ", "     ", " ##  ", "  #  ", " #   "],
    "<": ["    #", "   # ", "  #  ", " #   ", "  #  ", "   # ", "    #"],
    "@": [" ### ", "#   #", "# ###", "# # #", "# ###", "#    ", " ####"],
    "[": [" ### ", " #   ", " #   ", " #   ", " #   ", " #   ", " ### "],
    "\\": ["#    ", "#    ", " #   ", "  #  ", "   # ", "    #", "    #"],
    "]": [" ### ", "   # ", "   # ", "   # ", "   # ", "   # ", " ### "],
    "^": ["  #  ", " # # ", "#   #", "     ", "     ", "     ", "     "],
    "`": [" #   ", "  #  ", "     ", "     ", "     ", "     ", "     "],
    "{": ["   ##", "  #  ", "  #  ", " #   ", "  #  ", "  #  ", "   ##"],
    "|": ["  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  "],
    "}": ["##   ", "  #  ", "  #  ", "   # ", "  #  ", "  #  ", "##   "],
    "~": ["     ", "     ", " #   ", "# # #", "   # ", "     ", "     "],
    # small letters, so that names are drawn as spelt (catPNG, not CATPNG); those with a tail (g, j,
    # p, q, y) take 2 rows below the line (in 7 rows their squeezed bodies read as 9, P and a: helper-162)
    "a": ["     ", "     ", " ### ", "    #", " ####", "#   #", " ####"],
    "b": ["#    ", "#    ", "# ## ", "##  #", "#   #", "#   #", "#### "],
    "c": ["     ", "     ", " ### ", "#    ", "#    ", "#   #", " ### "],
    "d": ["    #", "    #", " ## #", "#  ##", "#   #", "#   #", " ####"],
    "e": ["     ", "     ", " ### ", "#   #", "#####", "#    ", " ### "],
    "f": ["  ## ", " #  #", " #   ", "###  ", " #   ", " #   ", " #   "],
    "g": ["     ", "     ", " ####", "#   #", "#   #", "#   #", " ####", "    #", " ### "],
    "h": ["#    ", "#    ", "# ## ", "##  #", "#   #", "#   #", "#   #"],
    "i": ["  #  ", "     ", " ##  ", "  #  ", "  #  ", "  #  ", " ### "],
    "j": ["   # ", "     ", "  ## ", "   # ", "   # ", "   # ", "   # ", "#  # ", " ##  "],
    "k": ["#    ", "#    ", "#  # ", "# #  ", "##   ", "# #  ", "#  # "],
    "l": ["  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "   ##"],  # (with a serif on top it read as 1: "12" for l2)
    "m": ["     ", "     ", "## # ", "# # #", "# # #", "#   #", "#   #"],
    "n": ["     ", "     ", "# ## ", "##  #", "#   #", "#   #", "#   #"],
    "o": ["     ", "     ", " ### ", "#   #", "#   #", "#   #", " ### "],
    "p": ["     ", "     ", "#### ", "#   #", "#   #", "#   #", "#### ", "#    ", "#    "],
    "q": ["     ", "     ", " ## #", "#  ##", "#   #", "#  ##", " ## #", "    #", "    #"],  # a straight stem (it read as 9)
    "r": ["     ", "     ", "# ## ", "##  #", "#    ", "#    ", "#    "],
    "s": ["     ", "     ", " ####", "#    ", " ### ", "    #", "#### "],
    "t": [" #   ", " #   ", "###  ", " #   ", " #   ", " #  #", "  ## "],
    "u": ["     ", "     ", "#   #", "#   #", "#   #", "#  ##", " ## #"],
    "v": ["     ", "     ", "#   #", "#   #", "#   #", " # # ", "  #  "],
    "w": ["     ", "     ", "#   #", "#   #", "# # #", "# # #", " # # "],
    "x": ["     ", "     ", "#   #", " # # ", "  #  ", " # # ", "#   #"],
    "y": ["     ", "     ", "#   #", "#   #", "#   #", "#   #", " ####", "    #", " ### "],
    "z": ["     ", "     ", "#####", "   # ", "  #  ", " #   ", "#####"],
}


def drawable(text: str) -> str:
    """``text`` in the letters ``text_bitmap`` draws: printable ASCII as spelt, accents dropped
    (été -> ete, ß -> ss), and "?" for a character it cannot spell (猫), rather than a blank that
    would turn a name into another one."""
    import unicodedata

    out = []
    for ch in text:
        if ch in _FONT:
            out.append(ch)
            continue
        for form in (ch, ch.casefold(), ch.upper()):  # (ß: no accent to drop, but casefolds to ss)
            parts = [c for c in unicodedata.normalize("NFKD", form) if not unicodedata.combining(c)]
            if parts and all(c in _FONT for c in parts):
                out.append("".join(parts))
                break
        else:
            out.append("?")
    return "".join(out)


def text_bitmap(text: str, scale: int = 1) -> np.ndarray:
    """Render ``text`` (printable ASCII and ``°``; other letters as ``drawable`` spells them) as a
    bool bitmap [7 * scale, (6 * n - 1) * scale] for its n >= 1 characters, [9 * scale, ...] where
    a letter has a tail below the line (g, j, p, q, y): the text's top row where it is stamped is
    the same either way, the tails reach into the space below."""
    chars = drawable(text)
    rows = max((len(_FONT[ch]) for ch in chars), default=7)
    glyphs = [np.array([[c == "#" for c in row] for row in _FONT[ch] + ["     "] * (rows - len(_FONT[ch]))])
              for ch in chars]
    gap = np.zeros((rows, 1), bool)
    parts = []
    for g in glyphs:
        parts += [g, gap]
    bm = np.concatenate(parts[:-1], axis=1) if parts else np.zeros((rows, 0), bool)
    return np.kron(bm, np.ones((scale, scale), bool))


def jet(x: np.ndarray) -> np.ndarray:
    """The 'jet' colour map, [..] in [0, 1] -> [.., 3]; the convention of PS error figures."""
    x = np.clip(x, 0.0, 1.0)[..., None]
    centres = np.array([0.75, 0.5, 0.25])
    return np.clip(1.5 - np.abs(4.0 * x - 4.0 * centres), 0.0, 1.0).astype(np.float32)


def _stamp(canvas: np.ndarray, bitmap: np.ndarray, y: int, x: int, colour=(1.0, 1.0, 1.0)) -> None:
    """Ink ``bitmap``'s True pixels at (y, x); what falls outside the canvas (either side) is cut."""
    y, x = int(y), int(x)  # (callers pass pixel positions computed in floats too)
    if y < 0 or x < 0:
        bitmap, y, x = bitmap[max(0, -y):, max(0, -x):], max(0, y), max(0, x)
    h, w = bitmap.shape
    y2, x2 = min(y + h, canvas.shape[0]), min(x + w, canvas.shape[1])
    if y2 <= y or x2 <= x:
        return
    canvas[y:y2, x:x2][bitmap[: y2 - y, : x2 - x]] = colour


def colour_bar(canvas: np.ndarray, y: int, x: int, h: int, width: int, labels: dict[float, str], s: int) -> None:
    """Draw a jet colour bar [h, width] at (y, x) on ``canvas``, high values on top, and each label
    (fraction of the range -> text, at text scale ``s``) beside it at its height, kept within the bar."""
    canvas[y:y + h, x:x + width] = jet(np.linspace(1.0, 0.0, h)[:, None].repeat(width, axis=1))
    for frac, text in labels.items():
        ty = y + int(round((1 - frac) * (h - 1)))
        bm = text_bitmap(text, s)
        body = 7 * s  # centred on the letters' body, not on a tail below it
        _stamp(canvas, bm, min(max(ty - body // 2, y), y + h - body), x + width + 2 * s)


def _degree_labels(vmax: float) -> dict[float, str]:
    return {frac: f"{vmax * frac:.0f}°" if frac < 1 else f">{vmax:.0f}°" for frac in (0.0, 1 / 3, 2 / 3, 1.0)}


BACKGROUND = 0.12  # dark grey behind the maps and text of the report pictures
MIN_BAR = 64  # pixels: the shortest colour bar of a benchmark sheet's maps
# the shortest colour bar of error.png and spread.png: four labels 14 px tall about 32 px apart
# (at 64 px they touched, ">45" on "30": a QA helper's finding on a 64 px capture)
LABELLED_BAR = 96
UNSCORED = 0.5  # grey: a mask pixel without a value (no ground truth there), apart from jet's 0 (dark blue)


def heat(values: np.ndarray, mask: np.ndarray, vmax: float) -> np.ndarray:
    """[H, W] values -> [H, W, 3]: jet over 0..vmax inside ``mask``, black outside, grey where NaN."""
    v = np.asarray(values, np.float32)
    img = np.where(np.isnan(v)[..., None], np.float32(UNSCORED), jet(np.nan_to_num(v) / vmax))
    return np.where(np.asarray(mask, bool)[..., None], img, 0.0).astype(np.float32)


UNSCORED_KEY = "NO GROUND TRUTH"  # beside a grey swatch


def _key_unscored(canvas: np.ndarray | None, y: int, x: int, s: int) -> int:
    """Draw the grey swatch and UNSCORED_KEY at (y, x) (None: draw nothing); return their width."""
    text = text_bitmap(UNSCORED_KEY, s)
    if canvas is not None:
        canvas[y:y + 7 * s, x:x + 7 * s] = UNSCORED
        _stamp(canvas, text, y, x + 9 * s)
    return 9 * s + text.shape[1]


def error_heatmap(error: np.ndarray, mask: np.ndarray, vmax: float = 45.0,
                  title: str | None = None, labels: dict[float, str] | None = None) -> np.ndarray:
    """Angular-error picture [H', W', 3] in [0, 1]: the map in jet over 0..vmax degrees on a
    dark background, its left edge in line with the title (grey: NaN, a mask pixel without
    ground truth, keyed under the map when there is any), a colour bar with tick labels on the
    right, ``title`` on top (one line per "\\n"). ``labels``: the colour bar's (fraction of
    vmax -> text; default degrees)."""
    img = heat(error, mask, vmax)
    unscored = bool((np.isnan(np.asarray(error, np.float32)) & np.asarray(mask, bool)).any())
    # a small map is shown k times larger (whole pixels) and the colour bar is at least LABELLED_BAR
    # tall, so that its four labels do not run into each other (a 24 x 24 capture)
    k = max(1, min(-(-LABELLED_BAR // max(img.shape[0], 1)), 2048 // max(img.shape[1], 1)))
    img = img.repeat(k, axis=0).repeat(k, axis=1)
    h, w = img.shape[:2]
    s = max(2, min(h, w) // 200)  # text 14 px tall at least: legible at 100 % on DiLiGenT-sized maps
    lines = [text_bitmap(t, s) if t else None for t in title.split("\n")] if title else []
    line = 10 * s  # a line with tails (g, p, y) is 9 s tall: s of space under it
    labels = labels or _degree_labels(vmax)
    # room right of the map for the bar (at 4 s, 10 s wide) and its labels (2 s beyond it)
    top, bar_w = len(lines) * line + 3 * s, 10 * s
    right = max(44 * s, 18 * s + max(text_bitmap(t, s).shape[1] for t in labels.values()))
    bar = max(h, LABELLED_BAR)
    left = 2 * s  # the map off the picture's edge, in line with the title
    widths = [left + w + right, 1, *(4 * s + bm.shape[1] for bm in lines if bm is not None)]
    if unscored:
        widths.append(2 * s + _key_unscored(None, 0, 0, s))
    canvas = np.full((top + bar + 4 * s + (line if unscored else 0), max(widths), 3), BACKGROUND, np.float32)
    canvas[top:top + h, left:left + w] = img
    colour_bar(canvas, top, left + w + 4 * s, bar, bar_w, labels, s)
    for i, bm in enumerate(lines):
        if bm is not None:
            _stamp(canvas, bm, 2 * s + i * line, 2 * s)
    if unscored:
        _key_unscored(canvas, top + bar + 3 * s, 2 * s, s)
    return canvas


def write_error_map(path: str | os.PathLike, error: np.ndarray, mask: np.ndarray,
                    mae: float | None = None, median: float | None = None, vmax: float = 45.0,
                    label: str | None = None) -> None:
    """error: [H, W] degrees (any value outside the mask; NaN inside: no ground truth there,
    drawn grey). ``label`` (the object and method, say) is the title's first line, so that
    pictures of several runs side by side say which is which. Writes an 8-bit RGB PNG."""
    title = None
    if mae is not None:
        title = f"MAE {mae:.2f}°" + (f"  MEDIAN {median:.2f}°" if median is not None else "")
    title = "\n".join(t for t in (label, title) if t) or None
    write_image(path, error_heatmap(error, mask, vmax, title), "uint8")


SPREAD_VMAX = 12.0  # degrees at the top of the spread maps' colour scale (most pixels are under 4)


def write_spread_map(path: str | os.PathLike, spread: np.ndarray, mask: np.ndarray,
                     mean: float | None = None, p90: float | None = None, vmax: float = SPREAD_VMAX,
                     label: str | None = None) -> None:
    """spread: [H, W] degrees, the ensemble's members' disagreement (``psctl.infer.member_spread``).
    Writes an 8-bit RGB PNG drawn as the error map, over 0..vmax degrees, ``label`` as there."""
    title = None
    if mean is not None:
        title = f"SPREAD MEAN {mean:.2f}°" + (f"  P90 {p90:.2f}°" if p90 is not None else "")
    title = "\n".join(t for t in (label, title) if t) or None
    write_image(path, error_heatmap(spread, mask, vmax, title), "uint8")


def _resize_nearest(img: np.ndarray, h: int, w: int) -> np.ndarray:
    rows = np.minimum(((np.arange(h) + 0.5) * img.shape[0] / h).astype(int), img.shape[0] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * img.shape[1] / w).astype(int), img.shape[1] - 1)
    return img[rows][:, cols]


def object_panel(name: str, mae: float | None, normals: np.ndarray, error: np.ndarray | None, mask: np.ndarray,
                 vmax: float = 45.0, height: int = 160, spread: np.ndarray | None = None) -> dict:
    """One object's column of ``benchmark_sheet``, small enough to keep for many objects: its
    normal map ((n + 1) / 2), error map (jet over 0..vmax degrees; None: no ground truth) and
    spread map (the ensemble's, jet over 0..SPREAD_VMAX degrees; None: not an ensemble),
    black outside the mask, cropped to the mask's bounding box (4 px margin) and scaled (nearest
    pixel) to ``height`` rows and as many columns as keep its aspect; an object wider than 3:1 gets
    3 x ``height`` columns and fewer rows instead (its aspect kept: ``benchmark_sheet`` centres it),
    and one taller than 1:3 more rows, as many as make it ``height`` / 3 wide, at most 3 x
    ``height`` (its row is as tall: a 25:1 object was a 6 px sliver in a 160 px row).

    normals [H, W, 3], error and spread [H, W] degrees, mask [H, W] bool
    -> {"name", "mae", "normals", "error", "spread", "unscored", "height"} (unscored: grey in its
    error map; height: the nominal one, its row's)."""
    from psctl.arrays import bounding_box

    mask = np.asarray(mask, bool)
    box = bounding_box(mask, margin=4) if mask.any() else (slice(None), slice(None))
    m = mask[box][..., None]
    h, w = height, max(1, round(m.shape[1] * height / m.shape[0]))
    if w > 3 * height:  # a wide strip: narrower than its aspect would make it, and as much lower
        w, h = 3 * height, max(1, round(3 * height * m.shape[0] / m.shape[1]))
    elif 3 * w < height:  # a tall one: a third of height wide, as tall as that makes it, to 3 x height
        h = min(3 * height, round(height / 3 * m.shape[0] / m.shape[1]))
        w = max(1, round(h * m.shape[1] / m.shape[0]))
    nmap = np.where(m, (np.clip(np.asarray(normals[box], np.float32), -1, 1) + 1) / 2, 0.0)
    maps = {key: None if a is None else
            _resize_nearest(heat(a[box], m[..., 0], top), h, w)
            for key, a, top in (("error", error, vmax), ("spread", spread, SPREAD_VMAX))}
    unscored = error is not None and bool((np.isnan(np.asarray(error[box], np.float32)) & m[..., 0]).any())
    return {"name": name, "mae": mae, "normals": _resize_nearest(nmap, h, w).astype(np.float32), **maps,
            "unscored": unscored, "height": height}


def sheet_layout(n: int) -> tuple[int, int]:
    """(objects per row, panel height) for a sheet of ``n`` objects: DiLiGenT-sized runs get rows
    of 5 at 160 px; larger ones about sqrt(2 n) to a row (each object is two maps stacked, so a
    sheet of hundreds stays roughly square instead of a strip tens of thousands of pixels tall)
    and, past 50 objects, 96 px panels."""
    return max(5, math.ceil(math.sqrt(2 * n))), (160 if n <= 50 else 96)


def benchmark_sheet(panels: list[dict], title: str, vmax: float = 45.0, per_row: int | None = None) -> np.ndarray:
    """The picture of a benchmark run (``psctl eval --out``: eval.png): ``title`` on top, then
    the objects (``object_panel``) in rows of ``per_row`` (None: ``sheet_layout``'s): each its
    name (wider than its maps, at least 12 characters: on two lines, split after the shape, each
    cut in the middle; names cut alike written whole) and MAE above its normal map, its
    error map below, and its spread map below that in rows where any panel has one; one colour
    bar for each kind of map on the right of each row.
    -> [H', W', 3] float32 in [0, 1]."""
    if not panels:  # psctl eval always has an object; a caller of the function may not
        raise ValueError("benchmark_sheet needs at least one panel")
    if per_row is None:
        per_row = sheet_layout(len(panels))[0]
    s, gap = 2, 12  # text scale, space between columns and rows
    line = 7 * s + 6  # one line of text
    char = 6 * s  # one character's advance

    def fit(text: str, n: int) -> str:
        # cut in the middle: names of a set differ at the end too (armadillo_gold, armadillo_steel)
        if len(text) <= n:
            return text
        head = (n - 2 + 1) // 2
        return text[:head] + ".." + text[len(text) - (n - 2 - head):]

    def name_lines(text: str, n: int) -> tuple[str, ...]:
        # a name wider than its maps: two lines, split after the shape (psctl synth's
        # shape_material names) where it can be, each cut in the middle to n characters
        if len(text) <= n:
            return (text,)
        cut = text.find("_") + 1
        cut = cut if 0 < cut <= n else n
        return fit(text[:cut], n), fit(text[cut:], n)

    names = [name_lines(p["name"], max(12, (p["normals"].shape[1] + s) // char)) for p in panels]
    # names that still read alike (MERL's materials end alike: 15 in "paint", 12 in "phenolic")
    # are written out whole, their panels widened: no two objects share a label (a helper read
    # "sphere..paint" under both sphere_dark-red-paint and sphere_gold-paint)
    def whole(text: str) -> tuple[str, ...]:
        cut = text.find("_") + 1
        return name_lines(text, max(cut, len(text) - cut) if cut else len(text))

    alike = collections.Counter(names)
    names = [whole(p["name"]) if alike[nm] > 1 else nm for p, nm in zip(panels, names)]
    n_lines = max(len(nm) for nm in names)  # name lines above each row's maps, then the MAE
    labels = [(*nm, *[""] * (n_lines - len(nm)), "" if p["mae"] is None else f"MAE {p['mae']:.2f}°")
              for p, nm in zip(panels, names)]
    widths = [max(p["normals"].shape[1], *(text_bitmap(t, s).shape[1] for t in lab)) for p, lab in zip(panels, labels)]
    bar_w = 10  # and beside it its labels, or above it its name (SPREAD), whichever is wider
    bar_text = max(text_bitmap(f">{vmax:.0f}°", s).shape[1], text_bitmap("SPREAD", s).shape[1] - bar_w) + 4
    rows = [list(range(i, min(i + per_row, len(panels)))) for i in range(0, len(panels), per_row)]
    # a row is as tall as its panels' nominal height: a row of wide strips (lower than that) keeps
    # room for its colour bars' labels
    heights = [max(max(panels[i].get("height", 0), panels[i]["normals"].shape[0]) for i in r) for r in rows]
    row_w = [gap + sum(widths[i] + gap for i in r) + bar_w + bar_text + gap for r in rows]
    W = max(*row_w, text_bitmap(title, s).shape[1] + 2 * gap)
    # normals, error (, spread): a row gets the third map, and its colour bar, where one of its
    # objects has a spread map (a run that mixes methods has rows without)
    n_maps = [3 if any(panels[i].get("spread") is not None for i in r) else 2 for r in rows]
    keyed = any(p.get("unscored") for p in panels)  # grey pixels (no ground truth) keyed at the bottom
    H = gap + line + sum(gap + (n_lines + 1) * line + k * (h + 4) - 4 for h, k in zip(heights, n_maps)) + gap + \
        (line if keyed else 0)
    W = max(W, 2 * gap + _key_unscored(None, 0, 0, s)) if keyed else W
    canvas = np.full((H, W, 3), BACKGROUND, np.float32)
    _stamp(canvas, text_bitmap(title, s), gap, gap)
    y = gap + line
    for r, h, k_maps in zip(rows, heights, n_maps):
        y += gap
        x = gap
        y_maps = y + (n_lines + 1) * line
        for i in r:
            p = panels[i]
            for j, text in enumerate(labels[i]):  # the name's lines, then the MAE
                _stamp(canvas, text_bitmap(text, s), y + j * line, x)
            ph, pw = p["normals"].shape[:2]
            dy = (h - ph) // 2  # a panel lower than the row (a wide strip): centred in its slot
            canvas[y_maps + dy:y_maps + dy + ph, x:x + pw] = p["normals"]
            for k, key in enumerate(("error", "spread"), 1):
                if p.get(key) is not None:
                    y0 = y_maps + k * (h + 4) + dy
                    canvas[y0:y0 + ph, x:x + pw] = p[key]
            x += widths[i] + gap
        by = y_maps + h + 4  # the colour bars beside the error (and spread) maps
        for k, (name, top) in enumerate((("ERROR", vmax), ("SPREAD", SPREAD_VMAX))[:k_maps - 1]):
            y0, bh = by + k * (h + 4), h
            if h - line >= MIN_BAR:  # each bar named above it (two bars one above the other read as two),
                # where the rest still holds its four labels apart
                _stamp(canvas, text_bitmap(name, s), y0, x)
                y0, bh = y0 + line, h - line
            colour_bar(canvas, y0, x, bh, bar_w, _degree_labels(top), s)
        y = y_maps + k_maps * (h + 4) - 4
    if keyed:
        _key_unscored(canvas, y + gap, gap, s)
    return canvas


def stack_sheets(sheets: list[np.ndarray], gap: int = 12) -> np.ndarray:
    """Pictures ([H, W, 3] in [0, 1]: each method's eval.png) one above the other on eval.png's
    background, ``gap`` pixels apart, each as wide as the widest (padded on the right).
    -> [sum H + gaps, max W, 3] float32."""
    width = max(s.shape[1] for s in sheets)
    rows = []
    for i, s in enumerate(sheets):
        row = np.full((s.shape[0], width, 3), BACKGROUND, np.float32)
        row[:, :s.shape[1]] = s[..., :3]
        rows += [row] if i == 0 else [np.full((gap, width, 3), BACKGROUND, np.float32), row]
    return np.concatenate(rows)


def write_json(path: str | os.PathLike, obj: dict) -> None:
    """``obj`` as indented JSON into ``path``, atomically."""
    write_text_atomic(Path(path), json.dumps(obj, indent=2) + "\n")

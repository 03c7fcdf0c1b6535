"""Symmetric views: the 8 symmetries of the square, applied to a capture about the view axis.

Under an orthographic camera, turning an object and its lights together about the view axis by
a multiple of 90 degrees, or mirroring both, gives another valid capture (for isotropic
materials). A network trained on turned and mirrored data should answer each such view the same
way once its answer is turned back; where it does not, averaging the turned-back answers cancels
the part of its error that depends on the orientation. psctl.lights (LCNet) and psctl.infer
(PS-FCN) use this as test-time augmentation (``views``).

A symmetry is (transpose, flip x, flip y), applied to an image in that order. Images are
[..., H, W] (row 0 at the top; NumPy arrays or torch tensors, ``axes`` to pick the two spatial
axes); directions are [..., 3] with x right, y up, z toward the camera. ``SYMMETRIES[:k]`` is a
subgroup for k = 1, 2, 4 and 8.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

from psctl.errors import PsctlError

Sym = tuple[bool, bool, bool]
SYMMETRIES: tuple[Sym, ...] = tuple((bool(t & 4), bool(t & 1), bool(t & 2)) for t in range(8))
VIEW_COUNTS = (1, 2, 4, 8)

A = TypeVar("A")  # np.ndarray or torch.Tensor


def _flip(x: A, axes: list[int]) -> A:
    if not axes:
        return x
    return np.flip(x, tuple(axes)) if isinstance(x, np.ndarray) else x.flip(axes)


def transform_images(x: A, sym: Sym, axes: tuple[int, int] = (-2, -1)) -> A:
    """Images seen after symmetry ``sym``; ``axes`` = (rows, columns)."""
    transpose, flip_x, flip_y = sym
    ay, ax = axes
    if transpose:
        x = x.swapaxes(ay, ax)
    return _flip(x, [d for d, f in ((ax, flip_x), (ay, flip_y)) if f])


def untransform_images(x: A, sym: Sym, axes: tuple[int, int] = (-2, -1)) -> A:
    """The inverse of ``transform_images``: an image of the transformed view back in the capture's frame."""
    transpose, flip_x, flip_y = sym
    ay, ax = axes
    x = _flip(x, [d for d, f in ((ax, flip_x), (ay, flip_y)) if f])
    return x.swapaxes(ay, ax) if transpose else x


def _stack(x: A, parts: list) -> A:
    return np.stack(parts, -1) if isinstance(x, np.ndarray) else __import__("torch").stack(parts, -1)


def transform_dirs(dirs: A, sym: Sym) -> A:
    """Directions [..., 3] after symmetry ``sym``: what a light (or normal) becomes when the
    images are changed by ``transform_images(x, sym)``. Transposing rows and columns maps
    (x, y) to (-y, -x) because rows run downward."""
    transpose, flip_x, flip_y = sym
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    if transpose:
        x, y = -y, -x
    return _stack(dirs, [-x if flip_x else x, -y if flip_y else y, z])


def untransform_dirs(dirs: A, sym: Sym) -> A:
    """The inverse of ``transform_dirs``: directions estimated on a transformed view, back in the
    capture's frame."""
    transpose, flip_x, flip_y = sym
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    x, y = (-x if flip_x else x), (-y if flip_y else y)
    if transpose:
        x, y = -y, -x
    return _stack(dirs, [x, y, z])


def box_in_capture(box: tuple[slice, slice], sym: Sym, shape: tuple[int, int]) -> tuple[slice, slice]:
    """The region of the capture that a (rows, columns) box of the view after ``sym`` shows;
    ``shape`` is the view's (H, W). ``transform_images(capture[region], sym) == view[box]``."""
    transpose, flip_x, flip_y = sym
    h, w = shape
    ys, xs = slice(*box[0].indices(h)[:2]), slice(*box[1].indices(w)[:2])
    if flip_y:
        ys = slice(h - ys.stop, h - ys.start)
    if flip_x:
        xs = slice(w - xs.stop, w - xs.start)
    return (xs, ys) if transpose else (ys, xs)


def check_views(views: object) -> int:
    """``views`` if it is one of VIEW_COUNTS (the subgroups), else PsctlError (a ValueError)."""
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or int(views) not in VIEW_COUNTS:
        raise PsctlError(None, f"--views must be 1, 2, 4 or 8, got {views!r}")
    return int(views)

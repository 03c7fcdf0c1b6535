"""A reader for the plain case of MATLAB's level-5 MAT-file: real numeric arrays, compressed or not.

Why: ground truth comes as ``Normal_gt.mat`` (DiLiGenT), and ``import scipy.io`` alone took
0.10-0.20 s per run on the 2-core development VM (it imports scipy.sparse), which is more than
reading the file. This module handles what MATLAB's ``save`` and ``scipy.io.savemat`` write for
real numeric arrays and answers ``None`` for anything else; the caller then asks scipy, so files
outside the plain case (version 4 or 7.3, cell arrays, structs, strings, sparse, complex or
logical arrays, a damaged file) keep scipy's behaviour and its messages.

Format (MathWorks, "MAT-File Format", level 5): a 128-byte header (text, subsystem offset,
version 0x0100, endian indicator "IM" or "MI"), then data elements, each an 8-byte tag (type,
byte count) and its bytes. A variable is a miMATRIX (14) element, or a miCOMPRESSED (15) element
holding one zlib-compressed miMATRIX. A miMATRIX holds sub-elements, each padded to 8 bytes: array
flags, dimensions, name, real part (and an imaginary part when complex). A sub-element of at most
4 bytes may sit inside its tag (the "small data element": byte count in the tag's upper 16 bits).
Values are stored column-major, and in any numeric type that holds them (MATLAB writes a double
array of small integers as miUINT8, for example); like ``scipy.io.loadmat``'s default, the
stored type is returned (in native byte order, where scipy keeps a big-endian file's).
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

_MATRIX, _COMPRESSED = 14, 15
_UINT32, _INT32, _INT8 = 6, 5, 1
_NUMERIC = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
_NUMERIC_CLASSES = range(6, 16)  # mxDOUBLE_CLASS .. mxUINT64_CLASS
_COMPLEX, _LOGICAL = 0x800, 0x200
_HEAD = 4096  # bytes of a variable enough for its flags, dimensions and name


class _NotPlain(Exception):
    """The file is outside the plain case: scipy decides."""


def variable_shapes(path: str | os.PathLike) -> dict[str, tuple[int, ...]] | None:
    """Each variable's name and shape, as ``scipy.io.whosmat`` lists them; None when the file is
    not a level-5 MAT-file of real numeric arrays only (ask scipy then)."""
    try:
        return {name: shape for name, shape, _ in _variables(Path(path), None)}
    except (_NotPlain, OSError):
        return None


def load_variable(path: str | os.PathLike, name: str) -> np.ndarray | None:
    """The variable ``name`` as ``scipy.io.loadmat(path)[name]`` gives it for a real numeric
    array; None when the file is not plain (see ``variable_shapes``) or has no such variable."""
    try:
        for found, _, array in _variables(Path(path), name):
            if found == name:
                return array
    except (_NotPlain, OSError):
        pass
    return None


def _variables(path: Path, load: str | None):
    """(name, shape, array or None) of every variable, after checking the whole file's layout;
    the values are decoded for the variable named ``load`` only."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        header = f.read(128)
        if len(header) < 128 or 0 in header[:4]:  # level 4 files start with a zero byte or more
            raise _NotPlain
        order = {b"IM": "<", b"MI": ">"}.get(header[126:128])
        if order is None or struct.unpack(order + "H", header[124:126])[0] != 0x0100:  # 7.3 is 0x0200 (HDF5)
            raise _NotPlain
        found, pos = [], 128
        while pos < size:
            tag = f.read(8)
            if len(tag) < 8:
                raise _NotPlain
            kind, count = struct.unpack(order + "II", tag)
            if kind >> 16 or pos + 8 + count > size or count == 0:
                raise _NotPlain
            head = f.read(min(count, _HEAD))
            if kind == _COMPRESSED:
                inflate = zlib.decompressobj()
                try:
                    head = inflate.decompress(head, _HEAD)
                except zlib.error:
                    raise _NotPlain from None
                if len(head) < 8 or struct.unpack(order + "I", head[:4])[0] != _MATRIX:
                    raise _NotPlain
            elif kind != _MATRIX:
                raise _NotPlain
            else:
                head = tag + head  # the same layout as a decompressed element: tag, then contents
            name, shape = _matrix_head(head, order)
            found.append((name, shape))
            if name == load:
                f.seek(pos + 8)
                body = f.read(count)
                if kind == _COMPRESSED:
                    try:
                        body = zlib.decompress(body)
                    except zlib.error:
                        raise _NotPlain from None
                else:
                    body = tag + body
                array = _matrix_values(body, order)
            pos += 8 + count
            f.seek(pos)
        if len({n for n, _ in found}) != len(found):  # a repeated name: scipy's rules
            raise _NotPlain
    return [(n, s, array if n == load else None) for n, s in found]


def _element(buf: bytes, at: int, order: str) -> tuple[int, bytes, int]:
    """(type, data, offset of the next sub-element) of the sub-element at ``at``."""
    if at + 8 > len(buf):
        raise _NotPlain
    word, count = struct.unpack_from(order + "II", buf, at)
    if word >> 16:  # small data element: type in the low half, byte count in the high, data in the next 4
        kind, count = word & 0xFFFF, word >> 16
        if count > 4:
            raise _NotPlain
        return kind, buf[at + 4:at + 4 + count], at + 8
    end = at + 8 + count
    if end > len(buf):
        raise _NotPlain
    return word, buf[at + 8:end], at + 8 + (count + 7) // 8 * 8


def _matrix_head(buf: bytes, order: str) -> tuple[str, tuple[int, ...]]:
    """A miMATRIX element's name and shape, after checking that it is a real numeric array."""
    kind, count = struct.unpack_from(order + "II", buf, 0)
    if kind != _MATRIX or count == 0:  # count 0: an empty matrix without sub-elements
        raise _NotPlain
    kind, flags, at = _element(buf, 8, order)
    if kind != _UINT32 or len(flags) != 8:
        raise _NotPlain
    word = struct.unpack(order + "I", flags[:4])[0]
    if word & 0xFF not in _NUMERIC_CLASSES or word & (_COMPLEX | _LOGICAL):
        raise _NotPlain
    kind, dims, at = _element(buf, at, order)
    if kind != _INT32 or len(dims) < 8 or len(dims) % 4:
        raise _NotPlain
    shape = struct.unpack(order + f"{len(dims) // 4}i", dims)
    if min(shape) < 0:
        raise _NotPlain
    kind, name, at = _element(buf, at, order)
    if kind != _INT8 or not name:
        raise _NotPlain
    return name.decode("latin1"), tuple(shape)


def _matrix_values(buf: bytes, order: str) -> np.ndarray:
    """The real part of a whole miMATRIX element (tag included), in its stored type."""
    _, shape = _matrix_head(buf, order)
    end = 8 + struct.unpack_from(order + "I", buf, 4)[0]
    if end != len(buf):  # trailing bytes after the matrix: not what MATLAB or scipy writes
        raise _NotPlain
    at = 8
    for _ in range(3):  # flags, dimensions, name
        at = _element(buf, at, order)[2]
    kind, data, at = _element(buf, at, order)
    if kind not in _NUMERIC or at != end:  # at != end: an imaginary part or more
        raise _NotPlain
    dtype = np.dtype(order + _NUMERIC[kind])
    if len(data) != dtype.itemsize * int(np.prod(shape, dtype=np.int64)):
        raise _NotPlain
    return np.frombuffer(data, dtype).reshape(shape, order="F").astype(dtype.newbyteorder("="))

"""A reader for the plain case of MATLAB's level-5 MAT-file: real numeric arrays, compressed or not.

Why: ground truth comes as ``Normal_gt.mat`` (DiLiGenT), and ``import scipy.io`` alone took
0.13-0.21 s per run on the 2-core development VM (it imports scipy.sparse), more than reading
the file. This module reads what MATLAB's ``save`` and ``scipy.io.savemat`` write for real
numeric arrays and answers ``None`` for anything else; the caller then asks scipy, so files
outside the plain case (version 4 or 7.3, cell arrays, structs, strings, sparse, complex or
logical arrays) keep scipy's behaviour and its messages. So do damaged files: a file counts as
plain only when every variable decodes whole (each compressed stream to its checksum), which is
stricter than scipy, never looser.

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

import math
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
_MAX_DIMS = 32  # scipy refuses more


class _NotPlain(Exception):
    """The file is outside the plain case: scipy decides."""


def variable_shapes(path: str | os.PathLike) -> dict[str, tuple[int, ...]] | None:
    """Each variable's name and shape, as ``scipy.io.whosmat`` lists them; None when the file is
    not a level-5 MAT-file of real numeric arrays only, all of them whole (ask scipy then)."""
    parsed = _read(path, None)
    return None if parsed is None else parsed[0]


def load_variable(path: str | os.PathLike, name: str) -> np.ndarray | None:
    """The variable ``name`` as ``scipy.io.loadmat(path)[name]`` gives it; None when the file is
    not plain (see ``variable_shapes``) or has no such variable (scipy then says which)."""
    parsed = _read(path, name)
    return None if parsed is None else parsed[1].get(name)


def _read(path: str | os.PathLike, keep: str | None) -> tuple[dict[str, tuple[int, ...]], dict[str, np.ndarray]] | None:
    """Every variable's shape and the values of ``keep``, every variable checked; None on anything
    outside the plain case.

    Every compressed stream is inflated to its checksum and every variable's size checked, also
    for a list of names: scipy reads only the headers for ``whosmat`` but stops at a damaged
    stream's first block, and ``loadmat`` refuses a file with any damaged variable, so a file is
    only called plain when it is whole. Being stricter than scipy costs nothing but time: such a
    file goes to scipy, which answers as it always did. Only ``keep``'s values are kept: the
    others are inflated a block at a time and dropped (a 1 MB file holding a compressed 1 GB
    array beside Normal_gt took 3 GB of memory, a hostile-input audit)."""
    try:
        return _parse(Path(path).read_bytes(), keep)
    except Exception:  # _NotPlain, or a check missed (struct.error, ...): whatever this reader cannot read, scipy reads or refuses
        return None


_HEAD = 4096  # a variable's header (flags, up to 32 dimensions, its name, its data's tag) fits, but
# for a name over about 4,000 characters, whose file then goes to scipy


def _parse(raw: bytes, keep: str | None = None) -> tuple[dict[str, tuple[int, ...]], dict[str, np.ndarray]]:
    """(each variable's shape, the values of the variable named ``keep``)."""
    if len(raw) < 128 or 0 in raw[:4]:  # scipy takes a zero byte among the first four for level 4
        raise _NotPlain
    order = {b"IM": "<", b"MI": ">"}.get(raw[126:128])
    if order is None or struct.unpack(order + "H", raw[124:126])[0] != 0x0100:  # 7.3 is 0x0200 (HDF5)
        raise _NotPlain
    shapes: dict[str, tuple[int, ...]] = {}
    kept: dict[str, np.ndarray] = {}
    pos = 128
    while pos < len(raw):
        if pos + 8 > len(raw):
            raise _NotPlain
        kind, count = struct.unpack_from(order + "II", raw, pos)
        end = pos + 8 + count  # top-level elements are not padded
        if end > len(raw):
            raise _NotPlain
        if kind == _COMPRESSED:
            inflate = zlib.decompressobj()
            try:
                head = inflate.decompress(raw[pos + 8:end], _HEAD)
                name, shape, dtype, size, start = _header(head, order)
                if name == keep:  # its values: the whole element, no more than its tag says
                    element = head + inflate.decompress(inflate.unconsumed_tail, size - len(head) + 1)
                    length = len(element)
                else:  # checked to its end a block at a time, its values dropped
                    element, length = head, len(head)
                    while not inflate.eof:
                        block = inflate.decompress(inflate.unconsumed_tail, 1 << 20)
                        length += len(block)
                        if not block and not inflate.unconsumed_tail:
                            break
            except zlib.error:
                raise _NotPlain from None
            if not inflate.eof or inflate.unused_data or inflate.unconsumed_tail or length != size:
                raise _NotPlain  # cut short, more after the stream, or not the size its tag says
        elif kind == _MATRIX:
            element = raw[pos:end]
            name, shape, dtype, size, start = _header(element, order)
            if len(element) != size:
                raise _NotPlain
        else:
            raise _NotPlain
        if name in shapes:  # a repeated name: scipy's rules
            raise _NotPlain
        shapes[name] = shape
        if name == keep:
            data = element[start:start + dtype.itemsize * math.prod(shape)]
            kept[name] = np.frombuffer(data, dtype).reshape(shape, order="F").astype(dtype.newbyteorder("="))
        pos = end
    return shapes, kept


def _element(buf: bytes, at: int, order: str) -> tuple[int, bytes, int, int]:
    """(type, data, its declared byte count, offset of the next sub-element) of the sub-element
    at ``at``; the data may be cut short by the end of ``buf`` (a header read alone)."""
    if at + 8 > len(buf):
        raise _NotPlain
    word, count = struct.unpack_from(order + "II", buf, at)
    if word >> 16:  # small data element: type in the low half, byte count in the high, data in the next 4
        kind, count = word & 0xFFFF, word >> 16
        if count > 4:
            raise _NotPlain
        return kind, buf[at + 4:at + 4 + count], count, at + 8
    return word, buf[at + 8:at + 8 + count], count, at + 8 + (count + 7) // 8 * 8


def _header(buf: bytes, order: str) -> tuple[str, tuple[int, ...], np.dtype, int, int]:
    """A miMATRIX element's (tag first) name, shape, stored type, whole size in bytes and the
    offset of its values, read from its first bytes and checked: a real numeric array whose
    values end the element."""
    if len(buf) < 8:
        raise _NotPlain
    kind, count = struct.unpack_from(order + "II", buf, 0)
    if kind != _MATRIX:
        raise _NotPlain
    kind, flags, _, at = _element(buf, 8, order)
    if kind != _UINT32 or len(flags) != 8:
        raise _NotPlain
    word = struct.unpack(order + "I", flags[:4])[0]
    if word & 0xFF not in _NUMERIC_CLASSES or word & (_COMPLEX | _LOGICAL):
        raise _NotPlain
    kind, dims, _, at = _element(buf, at, order)
    if kind != _INT32 or not 8 <= len(dims) <= 4 * _MAX_DIMS or len(dims) % 4:
        raise _NotPlain
    shape = struct.unpack(order + f"{len(dims) // 4}i", dims)
    if min(shape) < 0:
        raise _NotPlain
    kind, name, size, at = _element(buf, at, order)
    if kind != _INT8 or not name or len(name) != size:
        raise _NotPlain
    start = at + (4 if struct.unpack_from(order + "I", buf, at)[0] >> 16 else 8) if at + 8 <= len(buf) else -1
    kind, _, size, at = _element(buf, at, order)  # the values themselves may lie beyond ``buf``
    if kind not in _NUMERIC:
        raise _NotPlain
    dtype = np.dtype(order + _NUMERIC[kind])
    if size != dtype.itemsize * math.prod(shape):  # math.prod: Python integers, no wrapping
        raise _NotPlain
    if at != 8 + count:  # the values end the element: anything after them (an imaginary part) is refused
        raise _NotPlain
    return name.decode("latin1"), tuple(shape), dtype, 8 + count, start

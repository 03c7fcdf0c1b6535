"""PLY triangle meshes: a writer (binary little-endian or ASCII) and a small reader.

Vertices carry float32 positions, optional float32 normals (nx, ny, nz) and optional uint8
colours (red, green, blue); faces are triangles stored as ``list uchar int vertex_indices``,
the layout MeshLab, Blender and Open3D read. The reader understands what the writer writes
(and other PLYs with scalar vertex properties and triangle faces); it exists for tests and for
users who want the mesh back as arrays.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psctl.errors import PsctlError
from psctl.io.atomic import atomic_path

_PLY_TYPES = {  # PLY scalar type -> little-endian NumPy type
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}


@dataclass
class Mesh:
    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] int32, counter-clockwise seen from the side the normals point to
    normals: np.ndarray | None = None  # [V, 3] float32
    colors: np.ndarray | None = None  # [V, 3] uint8


def write_ply(path: str | os.PathLike, mesh: Mesh, binary: bool = True, comment: str | None = None) -> None:
    """Write ``mesh`` atomically as PLY (binary little-endian by default, else ASCII)."""
    v = np.asarray(mesh.vertices, np.float32)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"vertices must be [V, 3] and faces [F, 3], got {v.shape} and {f.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("face indices out of range")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if mesh.normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if mesh.colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vert = np.empty(len(v), dtype=np.dtype(fields))
    vert["x"], vert["y"], vert["z"] = v.T
    if mesh.normals is not None:
        nrm = np.asarray(mesh.normals, np.float32)
        vert["nx"], vert["ny"], vert["nz"] = nrm.T
    if mesh.colors is not None:
        col = np.asarray(mesh.colors, np.uint8)
        vert["red"], vert["green"], vert["blue"] = col.T
    names = {"<f4": "float", "u1": "uchar"}
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    if comment:
        # a PLY header is ASCII: other characters (an object named "café") and control characters
        # are written as Python escapes (\xe9), one comment line per line
        header += [f"comment {line.encode('unicode_escape').decode('ascii')}" for line in comment.splitlines()]
    header += [f"element vertex {len(v)}"]
    header += [f"property {names[t]} {name}" for name, t in fields]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")
    with atomic_path(path) as tmp, open(tmp, "wb") as out:
        out.write(head)
        if binary:
            out.write(vert.tobytes())
            face = np.empty(len(f), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
            face["n"] = 3
            face["v"] = f
            out.write(face.tobytes())
        else:
            fmt = " ".join("%.9g" if t == "<f4" else "%d" for _, t in fields)
            np.savetxt(out, np.column_stack([vert[name].astype(np.float64) for name, _ in fields]), fmt=fmt)
            np.savetxt(out, np.column_stack([np.full(len(f), 3), f]), fmt="%d")


def read_ply(path: str | os.PathLike) -> Mesh:
    """Read a PLY with scalar vertex properties (x y z, optional nx ny nz, red green blue) and
    triangle faces, binary little-endian or ASCII."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise PsctlError(path, f"cannot read mesh ({e.strerror or e})") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PsctlError(path, "not a PLY file")
    body_start = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            elements[-1][2].append(parts[1:])
    if fmt not in ("binary_little_endian", "ascii"):
        raise PsctlError(path, f"unsupported PLY format {fmt!r}")
    out: dict[str, np.ndarray] = {}
    if fmt == "ascii":
        rows = data[body_start:].decode("ascii").split("\n")
        pos = 0
        for name, count, props in elements:
            block = rows[pos:pos + count]
            pos += count
            if props and props[0][0] == "list":
                table = np.array([[int(t) for t in r.split()] for r in block], np.int64).reshape(count, -1)
                if count and (table[:, 0] != 3).any():
                    raise PsctlError(path, f"element {name}: only triangles are supported")
                out[name] = table[:, 1:4].astype(np.int32)
            else:
                table = np.loadtxt(block, ndmin=2) if count else np.zeros((0, len(props)))
                out[name] = np.rec.fromarrays(table.T, names=[p[1] for p in props])
    else:
        pos = body_start
        for name, count, props in elements:
            if props and props[0][0] == "list":
                _, count_t, index_t, _ = props[0]
                dt = np.dtype([("n", _PLY_TYPES[count_t]), ("v", _PLY_TYPES[index_t], (3,))])
                table = np.frombuffer(data, dt, count, pos)
                if count and (table["n"] != 3).any():
                    raise PsctlError(path, f"element {name}: only triangles are supported")
                out[name] = table["v"].astype(np.int32)
            else:
                dt = np.dtype([(p[1], _PLY_TYPES[p[0]]) for p in props])
                table = np.frombuffer(data, dt, count, pos)
                out[name] = table
            pos += dt.itemsize * count
    if "vertex" not in out:
        raise PsctlError(path, "PLY has no vertex element")
    vert = out["vertex"]
    names = vert.dtype.names or ()

    def stack(*cols: str, dtype) -> np.ndarray | None:
        return np.column_stack([vert[c] for c in cols]).astype(dtype) if all(c in names for c in cols) else None

    return Mesh(vertices=stack("x", "y", "z", dtype=np.float32),
                faces=out.get("face", np.zeros((0, 3), np.int32)),
                normals=stack("nx", "ny", "nz", dtype=np.float32),
                colors=stack("red", "green", "blue", dtype=np.uint8))

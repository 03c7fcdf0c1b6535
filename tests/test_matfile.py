"""psctl.io.matfile: the plain case of a level-5 MAT-file read as scipy.io reads it, and None
(scipy decides) for everything else."""

import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest
import scipy.io
import scipy.sparse

from psctl.io.matfile import load_variable, variable_shapes

DTYPES = ["f8", "f4", "i1", "u1", "i2", "u2", "i4", "u4", "i8", "u8"]


def _scipy(path):
    whos = {name: tuple(shape) for name, shape, _ in scipy.io.whosmat(str(path))}
    return whos, scipy.io.loadmat(str(path))


def _same(ours: np.ndarray, theirs: np.ndarray) -> None:
    assert ours.dtype == theirs.dtype.newbyteorder("=") and ours.dtype.isnative  # scipy keeps a big-endian file's order
    assert ours.shape == theirs.shape
    assert np.array_equal(ours, theirs, equal_nan=ours.dtype.kind == "f")
    assert ours.flags.writeable


@pytest.mark.parametrize("compress", [False, True])
def test_scipy_files_read_as_scipy_reads_them(tmp_path, compress):
    rng = np.random.default_rng(3)
    variables = {}
    for i, dt in enumerate(DTYPES):
        shape = [(5, 7, 3), (1, 1), (2, 3), (0, 3), (4, 1, 2, 2)][i % 5]
        if np.dtype(dt).kind == "f":
            value = rng.normal(0, 1e3, shape).astype(dt)
            if value.size:
                value.flat[0] = np.nan
        else:
            info = np.iinfo(dt)
            value = rng.integers(info.min, info.max, shape, dtype=dt, endpoint=True)
        variables[("v" if i % 2 else "long_name_") + str(i)] = value  # short names sit inside their tag
    variables["Normal_gt"] = rng.normal(size=(9, 11, 3))
    path = tmp_path / "a.mat"
    scipy.io.savemat(path, variables, do_compression=compress)
    whos, loaded = _scipy(path)
    assert variable_shapes(path) == whos
    for name in variables:
        _same(load_variable(path, name), loaded[name])
    assert load_variable(path, "missing") is None


def _element(kind: int, data: bytes, order: str, small: bool = False) -> bytes:
    if small:
        assert len(data) <= 4
        return struct.pack(order + "I", kind | len(data) << 16) + data.ljust(4, b"\0")  # count in the upper half
    return struct.pack(order + "II", kind, len(data)) + data + bytes(-len(data) % 8)


def _matrix(name: str, cls: int, dims, kind: int, data: bytes, order: str, flags: int = 0,
            imag: bytes | None = None) -> bytes:
    body = (_element(6, struct.pack(order + "II", cls | flags, 0), order)
            + _element(5, struct.pack(order + f"{len(dims)}i", *dims), order)
            + _element(1, name.encode(), order, small=len(name) <= 4)
            + _element(kind, data, order, small=len(data) <= 4))
    if imag is not None:
        body += _element(kind, imag, order)
    return struct.pack(order + "II", 14, len(body)) + body


def _file(elements, order: str = "<", version: int = 0x0100) -> bytes:
    text = b"MATLAB 5.0 MAT-file, written by psctl's tests".ljust(116)
    return text + bytes(8) + struct.pack(order + "H", version) + (b"IM" if order == "<" else b"MI") + b"".join(elements)


def _compressed(matrix: bytes, order: str) -> bytes:
    z = zlib.compress(matrix)
    return struct.pack(order + "II", 15, len(z)) + z


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("compress", [False, True])
def test_hand_written_files_as_matlab_writes_them(tmp_path, order, compress):
    """Big-endian files, a double array stored as miUINT8 (MATLAB's own saving of small integers)
    and values inside the tag: scipy's values and dtypes, and the stored type as scipy gives it."""
    gt = np.arange(24, dtype=np.float64).reshape(2, 4, 3) / 7
    small = np.array([[3, 250]], np.uint8)  # a double array of small integers, stored as uint8
    one = np.array([[-5]], np.int16)
    wrap = (lambda m: _compressed(m, order)) if compress else (lambda m: m)
    raw = _file([wrap(_matrix("Normal_gt", 6, gt.shape, 9, gt.astype(order + "f8").tobytes("F"), order)),
                 wrap(_matrix("s", 6, small.shape, 2, small.tobytes("F"), order)),
                 wrap(_matrix("one", 10, one.shape, 3, one.astype(order + "i2").tobytes("F"), order))], order)
    path = tmp_path / "h.mat"
    path.write_bytes(raw)
    whos, loaded = _scipy(path)
    assert variable_shapes(path) == whos == {"Normal_gt": (2, 4, 3), "s": (1, 2), "one": (1, 1)}
    for name in ("Normal_gt", "s", "one"):
        _same(load_variable(path, name), loaded[name])
    np.testing.assert_array_equal(load_variable(path, "Normal_gt"), gt)
    assert load_variable(path, "s").dtype == np.uint8  # the stored type, as scipy.io.loadmat's default


def _not_plain_cases(tmp_path):
    """Files psctl's reader leaves to scipy, each with its reason."""
    good = _matrix("Normal_gt", 6, (2, 2, 3), 9, np.ones(12).tobytes(), "<")
    for name, value in {"cell": np.array([[np.zeros(3), "a"]], dtype=object),
                        "struct": {"a": np.zeros(3)}, "string": "abc",
                        "complex": np.ones((2, 2)) * 1j, "bool": np.ones((2, 2), bool)}.items():
        path = tmp_path / f"{name}.mat"
        scipy.io.savemat(path, {"Normal_gt": np.zeros((2, 2, 3)), "other": value})
        yield name, path
    path = tmp_path / "sparse.mat"
    scipy.io.savemat(path, {"Normal_gt": scipy.sparse.eye(3).tocsc()})
    yield "sparse", path
    path = tmp_path / "v4.mat"
    scipy.io.savemat(path, {"Normal_gt": np.zeros((2, 2))}, format="4")
    yield "v4", path
    cases = {
        "v73": _file([], version=0x0200) + bytes(512),
        "empty": b"",
        "short": _file([])[:100],
        "truncated": _file([good])[:-9],
        "truncated_zlib": _file([_compressed(good, "<")])[:-4],
        "trailing": _file([good]) + b"\0\0\0",
        "repeated": _file([good, good]),
        "imaginary": _file([_matrix("Normal_gt", 6, (2, 2, 3), 9, np.ones(12).tobytes(), "<", flags=0x800,
                                    imag=np.ones(12).tobytes())]),
        "extra_part": _file([_matrix("Normal_gt", 6, (2, 2, 3), 9, np.ones(12).tobytes(), "<",
                                     imag=np.ones(12).tobytes())]),  # an imaginary part without the flag
        "zlib_extra": _file([_compressed(good + bytes(8), "<")]),  # bytes after the matrix in its stream
        "zero_text": bytes(4) + _file([good])[4:],  # scipy takes it for a level-4 file
        "wrong_size": _file([_matrix("Normal_gt", 6, (2, 2, 3), 9, np.ones(11).tobytes(), "<")]),
        "junk": b"not a mat file at all" * 10,
    }
    for name, raw in cases.items():
        path = tmp_path / f"{name}.mat"
        path.write_bytes(raw)
        yield name, path
    yield "missing", tmp_path / "no such file.mat"


def test_other_files_are_left_to_scipy(tmp_path):
    cases = dict(_not_plain_cases(tmp_path))
    for name, path in cases.items():
        if name in ("wrong_size", "extra_part", "zlib_extra"):  # only the values are odd: the list is scipy.io.whosmat's
            assert variable_shapes(path) == {n: tuple(s) for n, s, _ in scipy.io.whosmat(path)} == {"Normal_gt": (2, 2, 3)}
        else:
            assert variable_shapes(path) is None, name
        assert load_variable(path, "Normal_gt") is None, name
    assert len(cases) == 21


def test_ground_truth_without_scipy(tmp_path):
    """open_capture's check and load_ground_truth on a plain Normal_gt.mat import no scipy.io (the
    reason for the reader), and give the values scipy gives."""
    from tests.conftest import write_capture

    folder = tmp_path / "cap"
    write_capture(folder)
    code = ("import sys; from psctl.io.capture import open_capture, load_ground_truth; "
            f"c = open_capture({str(folder)!r}); g = load_ground_truth(c); "
            "import numpy as np; np.save(sys.argv[1], g); print('scipy.io' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "g.npy")], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False", out.stderr
    gt = scipy.io.loadmat(folder / "Normal_gt.mat")["Normal_gt"]
    norm = np.linalg.norm(gt, axis=-1, keepdims=True)
    expected = np.where(norm > 1e-6, gt / np.maximum(norm, 1e-6), 0).astype(np.float32)
    np.testing.assert_array_equal(np.load(tmp_path / "g.npy"), expected)

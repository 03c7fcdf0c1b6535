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

from psctl.io import matfile
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
    variables["dims32"] = np.arange(6.0).reshape((2,) + (1,) * 30 + (3,))  # scipy's most dimensions
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
    rng = np.random.default_rng(5)
    big = _compressed(_matrix("Normal_gt", 6, (64, 64, 3), 9, rng.normal(size=64 * 64 * 3).tobytes(), "<"), "<")
    deep = bytearray(_file([big]))
    deep[-40] ^= 0x55  # deep in the stream, far past the variable's header
    def raw(*parts: bytes, count: int | None = None) -> bytes:  # a miMATRIX of the given sub-elements
        body = b"".join(parts)
        return struct.pack("<II", 14, len(body) if count is None else count) + body

    def dims(*d: int) -> bytes:
        return _element(5, struct.pack(f"<{len(d)}i", *d), "<")

    def z(stream: bytes) -> bytes:
        return struct.pack("<II", 15, len(stream)) + stream

    flags, name = _element(6, struct.pack("<II", 6, 0), "<"), _element(1, b"Normal_gt", "<")
    real = _element(9, np.ones(12).tobytes(), "<")
    cases = {
        "negative_dims": _file([raw(flags, dims(-2, -3), name, _element(9, np.ones(6).tobytes(), "<"))]),
        "count_mismatch_z": _file([_compressed(raw(flags, dims(2, 2, 3), name, real, count=len(flags + real) * 9), "<")]),
        "small_count": _file([raw(flags, dims(2, 2, 3), struct.pack("<I", 1 | 6 << 16) + b"Norm", real)]),
        "empty_name": _file([raw(flags, dims(2, 2, 3), _element(1, b"", "<"), real)]),
        "dims_9_bytes": _file([raw(flags, _element(5, bytes(9), "<"), name, real)]),
        "one_dim": _file([raw(flags, _element(5, struct.pack("<i", 12), "<", small=True), name, real)]),
        "flags_small": _file([raw(_element(6, struct.pack("<I", 6), "<", small=True), dims(2, 2, 3), name, real)]),
        "flags_type": _file([raw(_element(5, struct.pack("<II", 6, 0), "<"), dims(2, 2, 3), name, real)]),
        "short_z": _file([z(zlib.compress(struct.pack("<I", 14)))]),
        "no_checksum": _file([z(zlib.compress(good)[:-4])]),
        "after_stream": _file([z(zlib.compress(good) + b"junk")]),
        "no_real_part": _file([raw(flags, dims(2, 2, 3), name)]),
        "overrun": _file([raw(flags, dims(2, 3), name, struct.pack("<II", 9, 96) + np.ones(6).tobytes())]),
        "huge_dims": _file([raw(flags, dims(2**22, 2**21, 2**21), name, _element(9, b"", "<"))]),  # no int64 wrap
        "char_class": _file([raw(_element(6, struct.pack("<II", 4, 0), "<"), dims(1, 3), name,
                                 _element(4, "abc".encode("utf-16-le"), "<"))]),  # scipy gives text
        "z_not_matrix": _file([_compressed(struct.pack("<I", 1) + good[4:], "<")]),  # a matrix's bytes, typed miINT8
        "top_int8": _file([_element(1, b"Normal_gt", "<")]),
        "name_type": _file([raw(flags, dims(2, 2, 3), _element(16, b"Normal_gt", "<"), real)]),  # miUTF8
        "deep_zlib": bytes(deep),
        "second_bad": _file([good, _matrix("x", 6, (2, 2), 9, np.ones(3).tobytes(), "<")]),  # loadmat refuses it
        "dims33": _file([_matrix("Normal_gt", 6, (2, 2, 3) + (1,) * 30, 9, np.ones(12).tobytes(), "<")]),
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
        assert variable_shapes(path) is None, name  # also where only values are wrong: a file is plain when whole
        assert load_variable(path, "Normal_gt") is None, name
        if path.exists():  # refused by a check, not by an error the reader's catch-all hides
            with pytest.raises(matfile._NotPlain):
                matfile._parse(path.read_bytes())
    assert len(cases) == 42
    for name in ("deep_zlib", "second_bad", "dims33", "wrong_size"):  # and scipy refuses them
        with pytest.raises(Exception):
            scipy.io.loadmat(cases[name])


def test_damaged_files_never_read_where_scipy_fails_or_differs(tmp_path):
    """A differential fuzz: 600 files damaged at random (cut short, a byte flipped, a word
    overwritten, bytes appended). Wherever psctl's reader answers, scipy reads the same names,
    shapes and values; everywhere else scipy decides (it may then read the file, or fail)."""
    rng = np.random.default_rng(11)
    bases = []
    for compress in (False, True):
        path = tmp_path / f"base{compress}.mat"
        scipy.io.savemat(path, {"Normal_gt": rng.normal(size=(6, 5, 3)), "x": np.array([[1, -2], [3, 4]], np.int16)},
                         do_compression=compress)
        bases.append(path.read_bytes())
    gt = rng.normal(size=(4, 3, 3))
    bases.append(_file([_compressed(_matrix("Normal_gt", 6, gt.shape, 9, gt.astype(">f8").tobytes("F"), ">"), ">")],
                       ">"))
    answered = 0
    for i in range(600):
        raw = bytearray(bases[i % len(bases)])
        how = rng.integers(4)
        if how == 0:
            raw = raw[:rng.integers(len(raw))]
        elif how == 1:
            raw[rng.integers(len(raw))] ^= int(rng.integers(1, 256))
        elif how == 2:
            at = rng.integers(len(raw) - 4)
            raw[at:at + 4] = rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
        else:
            raw += rng.integers(0, 256, rng.integers(1, 16), dtype=np.uint8).tobytes()
        path = tmp_path / "damaged.mat"
        path.write_bytes(bytes(raw))
        shapes = variable_shapes(path)
        if shapes is None:
            assert load_variable(path, "Normal_gt") is None
            continue  # scipy is not called: on some damaged files it crashes the process
        answered += 1
        whos, loaded = _scipy(path)
        assert shapes == whos, i
        for name in shapes:
            _same(load_variable(path, name), loaded[name])
    assert 50 < answered < 550, answered  # both branches taken: flips in the values keep a file whole


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


def test_other_variables_are_checked_but_not_kept(tmp_path):
    """A small compressed file can hold a huge array beside Normal_gt (a 1 MB file took 3 GB, a
    hostile-input audit): only the variable asked for is kept; the others are inflated a block at
    a time to check them and dropped. Their shapes are still listed."""
    import tracemalloc

    gt = np.random.default_rng(0).normal(size=(20, 30, 3))
    path = tmp_path / "Normal_gt.mat"
    scipy.io.savemat(path, {"junk": np.zeros((5_000_000, 1)), "Normal_gt": gt}, do_compression=True)
    assert path.stat().st_size < 1 << 20  # 40 MB of zeros, compressed
    tracemalloc.start()
    try:
        got = load_variable(path, "Normal_gt")
        shapes = variable_shapes(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(got, gt)
    assert shapes == {"junk": (5_000_000, 1), "Normal_gt": (20, 30, 3)}
    assert peak < 12 << 20, peak  # a few blocks of 1 MB, not the 40 MB array
    assert load_variable(path, "junk").shape == (5_000_000, 1)  # asked for, it is read whole


def test_ground_truth_beyond_float32_is_still_directions(tmp_path):
    """Normal_gt.mat of finite doubles too large for float32 (1e300 times the unit normals) scores
    as the unit normals do; an infinite value is still refused, by its pixel (a QA helper found
    the first refused as "infinite values", session 58)."""
    from psctl.api import run_normals
    from psctl.errors import PsctlError
    from tests.conftest import write_capture

    data = write_capture(tmp_path / "c", n=6)
    for f in (tmp_path / "c").glob("Normal_gt.*"):
        f.unlink()
    gt = np.where(data["mask"][..., None], data["normals"], 0.0).astype(np.float64)
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": gt})
    unit = run_normals(tmp_path / "c", "l2", write=False)
    for scale in (1e300, 1e-7, 1e-300):  # tiny ones were "no normal" (an absolute 1e-6 floor)
        scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": gt * scale})
        scaled = run_normals(tmp_path / "c", "l2", write=False)
        assert scaled["n_evaluated_pixels"] == unit["n_evaluated_pixels"] > 0, scale
        assert abs(scaled["mae"] - unit["mae"]) < 1e-6, scale
    gt[3, 4] = [np.inf, 0.0, 1.0]
    scipy.io.savemat(tmp_path / "c" / "Normal_gt.mat", {"Normal_gt": gt})
    with pytest.raises(PsctlError, match=r"infinite values \(first at row 3, column 4\)"):
        run_normals(tmp_path / "c", "l2", write=False)

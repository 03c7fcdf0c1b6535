"""psctl.io.prefetch: a helper process decodes a capture's images while psctl imports torch.

What it hands over must be what reading in-process gives, bit for bit; whatever it cannot do
(a broken file, another region, a call out of order) must leave the reading, and its one-line
error, to psctl itself; and the helper must not outlive its use."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from psctl.errors import PsctlError
from psctl.io.capture import iter_images, open_capture
from psctl.io.images import read_image, to_rgb
from psctl.io.prefetch import Prefetch
from tests.conftest import write_capture

pytestmark = pytest.mark.skipif(not hasattr(os, "memfd_create"), reason="the helper needs os.memfd_create (Linux)")

BOX = (slice(4, 36), slice(8, 30))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _expected(path):
    pixels, info = read_image(path)
    return to_rgb(pixels)[BOX], info


@pytest.mark.parametrize("slots", [None, 2])
def test_what_the_helper_hands_over_is_what_reading_gives(tmp_path, slots):
    """Every image, cut to the box, equal bit for bit with its header info; with a ring of two
    slots for ten images too (the helper waits for the slots to be taken)."""
    write_capture(tmp_path / "cap", n=10, size=40)
    cap = open_capture(tmp_path / "cap")
    slot = -(-32 * 22 * 3 * 4 // 4096) * 4096
    budget = 1 << 30 if slots is None else slots * slot
    with Prefetch(cap.image_paths, BOX, (40, 40), budget) as pf:
        assert pf.proc is not None and pf.slots == (10 if slots is None else 2)
        pid = pf.proc.pid
        for p in cap.image_paths:
            got = pf.take(p, BOX)
            assert got is not None
            want = _expected(p)
            assert got[0].dtype == np.float32 and np.array_equal(got[0], want[0]) and got[1] == want[1]
        assert pf.served == 10
        assert pf.take(cap.image_paths[0], BOX) is None  # all handed over: the caller reads again
    assert pf.proc is None and not _alive(pid)


def test_a_broken_image_is_left_to_the_reader_and_its_error(tmp_path):
    """The helper stops at a truncated PNG; the images before it are handed over, and
    iter_images then reads that one itself: the same error, naming the file, as without the helper."""
    write_capture(tmp_path / "cap", n=8, size=40)
    cap = open_capture(tmp_path / "cap")
    bad = cap.image_paths[3]
    bad.write_bytes(bad.read_bytes()[:300])
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        for p in cap.image_paths[:3]:
            assert pf.take(p, BOX) is not None
        assert pf.take(bad, BOX) is None and pf.proc is None
    with pytest.raises(PsctlError) as plain:
        list(iter_images(cap, BOX))
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        with pytest.raises(PsctlError) as helped:
            list(iter_images(cap, BOX, decoded=pf))
        assert pf.served == 3
    assert str(helped.value) == str(plain.value) and bad.name in str(helped.value)


def test_another_region_or_order_is_read_here(tmp_path):
    write_capture(tmp_path / "cap", n=4, size=40)
    cap = open_capture(tmp_path / "cap")
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        assert pf.take(cap.image_paths[1], BOX) is None and pf.proc is None  # out of order
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        assert pf.take(cap.image_paths[0], (slice(0, 40), slice(0, 40))) is None and pf.proc is None
    # iter_images with the helper gives the same arrays as without, for a box the helper has
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        helped = list(iter_images(cap, BOX, decoded=pf))
        assert pf.served == 4
    assert all(np.array_equal(a, b) for a, b in zip(helped, iter_images(cap, BOX), strict=True))


def test_an_image_larger_than_the_budget_starts_nothing(tmp_path):
    write_capture(tmp_path / "cap", n=3, size=40)
    cap = open_capture(tmp_path / "cap")
    with Prefetch(cap.image_paths, BOX, (40, 40), 1000) as pf:
        assert pf.proc is None and pf.take(cap.image_paths[0], BOX) is None


def test_close_stops_a_helper_that_is_still_working(tmp_path):
    """A run that fails (or is interrupted) after the first images: the helper is killed and
    reaped at once, not left to finish decoding for nobody."""
    write_capture(tmp_path / "cap", n=12, size=40)
    cap = open_capture(tmp_path / "cap")
    pf = Prefetch(cap.image_paths, BOX, (40, 40), 2 * 4096 * 3)  # 2 slots: it waits for the caller
    pid = pf.proc.pid
    assert pf.take(cap.image_paths[0], BOX) is not None
    assert _alive(pid)
    pf.close()
    assert pf.proc is None and not _alive(pid)
    pf.close()  # twice is fine


def _fresh(code: str, tmp_path) -> dict:
    """Run ``code`` in a new interpreter (torch not imported yet, as in `psctl normals`), return its JSON."""
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_network_runs_get_the_same_normals_and_notes_with_the_helper(tmp_path):
    """In a fresh process the first network run has the helper decode every image (``prefetched``),
    and gives the normals and notes of the run that reads them itself (prefetch_mb 0), for one
    network and for the ensemble (one black image and one saturated one: the readers' notes)."""
    from psctl.io.images import write_image

    write_capture(tmp_path / "cap", n=10, size=48)
    cap = open_capture(tmp_path / "cap")
    write_image(cap.image_paths[2], np.zeros((48, 48, 3), np.float32), "uint16")
    write_image(cap.image_paths[5], np.ones((48, 48, 3), np.float32), "uint16")
    out = _fresh(f"""
        import json, sys
        import numpy as np
        from psctl.io.capture import open_capture, load_mask
        from psctl.infer import capture_normals
        assert "torch" not in sys.modules  # importing the engine must not import torch
        cap = open_capture({str(tmp_path / "cap")!r}); mask = load_mask(cap)
        res = {{}}
        for method in ("ensemble", "ps-fcn-n"):
            a = capture_normals(cap, mask, method)
            b = capture_normals(cap, mask, method, config={{"prefetch_mb": 0}})
            res[method] = [a.info["prefetched"], b.info["prefetched"], bool(np.array_equal(a.normals, b.normals)),
                           a.notes == b.notes, a.notes]
        print(json.dumps(res))
    """, tmp_path)
    # the first run (the ensemble's) had the helper; ps-fcn-n, with torch imported by then, does not
    assert out["ensemble"][:4] == [10, 0, True, True]
    assert any("black over the object" in n for n in out["ensemble"][4])
    assert any("saturated" in n for n in out["ensemble"][4])
    assert out["ps-fcn-n"][:4] == [0, 0, True, True]


def test_a_truncated_png_with_a_network_is_one_line(tmp_path):
    """`psctl normals` with the helper decoding: the broken file is still one line naming it,
    exit 2, no libpng line, no output folder."""
    write_capture(tmp_path / "cap", n=8, size=48)
    bad = sorted((tmp_path / "cap").glob("*.png"))[4]
    bad.write_bytes(bad.read_bytes()[:300])
    proc = subprocess.run([sys.executable, "-m", "psctl.cli", "normals", str(tmp_path / "cap"), "-m", "ps-fcn-n",
                           "-q", "-o", str(tmp_path / "o")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "libpng" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and bad.name in proc.stderr
    assert not (tmp_path / "o").exists()


def test_a_bad_prefetch_setting_is_one_line(tmp_path):
    from psctl.infer import capture_normals
    from psctl.io.capture import load_mask

    write_capture(tmp_path / "cap", n=4, size=40)
    cap = open_capture(tmp_path / "cap")
    for bad in (-1, 1.5, "64", True):
        with pytest.raises(PsctlError, match="prefetch_mb must be a whole number"):
            capture_normals(cap, load_mask(cap), "ps-fcn-n", config={"prefetch_mb": bad})


def test_the_helper_works_when_stderr_was_closed_at_start(tmp_path):
    """A process started with fd 2 closed (``2>&-``, a daemon) is handed fd 2 for the ring by the
    system; the child's stderr (/dev/null) would then replace it. The ring is moved above 2."""
    write_capture(tmp_path / "cap", n=6, size=40)
    code = textwrap.dedent(f"""
        import json, sys
        import numpy as np
        from psctl.io.capture import open_capture, load_mask
        from psctl.infer import capture_normals
        cap = open_capture({str(tmp_path / "cap")!r}); mask = load_mask(cap)
        a = capture_normals(cap, mask, "ps-fcn-n")
        b = capture_normals(cap, mask, "ps-fcn-n", config={{"prefetch_mb": 0}})
        print(json.dumps([a.info["prefetched"], bool(np.array_equal(a.normals, b.normals))]))
    """)
    proc = subprocess.run([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=tmp_path,
                          timeout=300, preexec_fn=lambda: os.close(2))
    assert proc.returncode == 0
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [6, True]

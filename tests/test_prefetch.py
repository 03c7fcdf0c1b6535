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
from psctl.io.images import read_image, to_rgb, write_image
from psctl.io.prefetch import Prefetch, _usable
from tests.conftest import write_capture

pytestmark = pytest.mark.skipif(not _usable(), reason="the helper is off here: it needs os.memfd_create (Linux), "
                                                      "two CPUs and file descriptors 0-2 open")

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


def test_a_memo_keeps_the_file_as_the_helper_found_it_before_decoding(tmp_path):
    """A file changed after the helper decoded it and before the parent took it: the memo keeps
    the helper's stamp, taken before its read, so a later pass reads the file again instead of
    taking the decoded image for the changed file's."""
    import time

    from psctl.io.capture import DecodeMemo

    write_capture(tmp_path / "cap", n=4, size=40)
    cap = open_capture(tmp_path / "cap")
    memo = DecodeMemo(1 << 30)
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        assert pf.proc is not None
        second = np.frombuffer(pf.mm, np.float32, 32 * 22 * 3, pf.slot)  # image 2's slot of the ring
        deadline = time.monotonic() + 60
        while not second.any():  # decoded (the helper stamps each file before it reads it)
            assert time.monotonic() < deadline, "the helper decoded nothing in 60 s"
            time.sleep(0.01)
        del second  # a view of the ring, which close() unmaps
        st = os.stat(cap.image_paths[1])
        os.utime(cap.image_paths[1], ns=(st.st_atime_ns, st.st_mtime_ns + 5 * 10**9))  # 'changed' since
        got = list(iter_images(cap, BOX, decoded=pf, memo=memo))
        assert pf.served == 4 and len(got) == 4
    assert memo.take(cap.image_paths[0], BOX) is not None
    assert memo.take(cap.image_paths[1], BOX) is None  # as found before the change: stale now


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


def _fresh(code: str, tmp_path, closed: tuple[int, ...] = (), timeout: float = 300):
    """Run ``code`` in a new interpreter (torch not imported yet, as in `psctl normals`), with the
    descriptors ``closed`` shut at start; it writes its JSON answer to the file named by
    ``sys.argv[1]`` (stdout may be one of the closed ones), returned here."""
    out = tmp_path / "out.json"
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code), str(out)], cwd=tmp_path, timeout=timeout,
                          stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          preexec_fn=lambda: [os.close(fd) for fd in closed])
    assert proc.returncode == 0, (proc.returncode, proc.stderr)
    return json.loads(out.read_text())


def test_the_network_runs_get_the_same_normals_and_notes_with_the_helper(tmp_path):
    """In a fresh process the first network run has the helper decode every image (``prefetched``),
    and gives the normals and notes of the run that reads them itself (prefetch_mb 0), for one
    network and for the ensemble (one black image and one saturated one: the readers' notes)."""
    from psctl.io.images import write_image

    write_capture(tmp_path / "cap", n=10, size=48)
    cap = open_capture(tmp_path / "cap")
    write_image(cap.image_paths[2], np.zeros((48, 48, 3), np.float32), "uint16", kind="linear")
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
        open(sys.argv[1], "w").write(json.dumps(res))
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
        for extra in ({}, {"downsample": 2}):  # also where the helper would be off anyway
            with pytest.raises(PsctlError, match="prefetch_mb must be a whole number"):
                capture_normals(cap, load_mask(cap), "ps-fcn-n", config={"prefetch_mb": bad, **extra})


_RING_OF_TWO = """
    import json, os, sys, time
    import numpy as np
    from psctl.io.capture import open_capture
    from psctl.io.images import read_image, to_rgb
    from psctl.io.prefetch import Prefetch
    BOX = (slice(4, 36), slice(8, 30))
    cap = open_capture({cap!r})
    pf = Prefetch(cap.image_paths, BOX, (40, 40), 2 * 3 * 4096)  # two slots for ten images
    got = [pf.take(cap.image_paths[0], BOX)]
    time.sleep(0.5)  # the helper writes image 2 into image 0's slot
    try:
        os.write(2, b"libgomp: Invalid value for environment variable OMP_NUM_THREADS\\n")  # a C library's line
    except OSError:
        pass
    time.sleep(0.5)  # and whatever the line set going is done
    got += [pf.take(p, BOX) for p in cap.image_paths[1:]]
    pf.close()
    same = [g is None or bool(np.array_equal(g[0], to_rgb(read_image(p)[0])[BOX])) for g, p in zip(got, cap.image_paths)]
    open(sys.argv[1], "w").write(json.dumps([sum(g is not None for g in got), same]))
"""


@pytest.mark.parametrize("closed", [(2,), (0, 1, 2)])
def test_closed_standard_descriptors_never_reach_the_ring(tmp_path, closed):
    """A process started with 2>&- (or 0-2 closed, a daemon) is handed those numbers for the next
    files it opens: had the ring or its credits got fd 2, a C library's line on stderr would land
    in the pixels. What is handed over equals what is read, and so do the normals."""
    write_capture(tmp_path / "cap", n=10, size=40)
    served, same = _fresh(_RING_OF_TWO.format(cap=str(tmp_path / "cap")), tmp_path, closed)
    assert all(same), same
    normals = _fresh(f"""
        import json, sys
        import numpy as np
        from psctl.io.capture import open_capture, load_mask
        from psctl.infer import capture_normals
        cap = open_capture({str(tmp_path / "cap")!r}); mask = load_mask(cap)
        a = capture_normals(cap, mask, "ps-fcn-n")
        b = capture_normals(cap, mask, "ps-fcn-n", config={{"prefetch_mb": 0}})
        open(sys.argv[1], "w").write(json.dumps(bool(np.array_equal(a.normals, b.normals))))
    """, tmp_path, closed)
    assert normals is True


def test_the_ring_is_right_with_every_descriptor_open(tmp_path):
    """The same script with 0-2 open: the helper serves all ten (the test above is not vacuous)."""
    write_capture(tmp_path / "cap", n=10, size=40)
    served, same = _fresh(_RING_OF_TWO.format(cap=str(tmp_path / "cap")), tmp_path)
    assert served == 10 and all(same)


def test_a_caller_with_sigpipe_at_its_default_is_not_killed(tmp_path):
    """Scripts that set SIGPIPE to SIG_DFL (``| head``) must not die when the helper has ended
    (after the last image, or at a broken one) and a slot is freed: exit 0, the error still raised."""
    write_capture(tmp_path / "cap", n=8, size=40)
    bad = sorted((tmp_path / "cap").glob("*.png"))[4]
    bad.write_bytes(bad.read_bytes()[:300])
    out = _fresh(f"""
        import json, signal, sys, time
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)
        from psctl.errors import PsctlError
        from psctl.io.capture import iter_images, open_capture
        from psctl.io.prefetch import Prefetch
        BOX = (slice(4, 36), slice(8, 30))
        cap = open_capture({str(tmp_path / "cap")!r})
        pf = Prefetch(cap.image_paths, BOX, (40, 40), 2 * 3 * 4096)
        got = []
        for k, p in enumerate(cap.image_paths[:4]):
            got.append(pf.take(p, BOX) is not None)
            if k == 2:
                time.sleep(0.5)  # the helper reaches the broken image and ends
        got.append(pf.take(cap.image_paths[4], BOX) is not None)
        pf.close()
        with Prefetch(cap.image_paths, BOX, (40, 40), 2 * 3 * 4096) as pf:
            try:
                list(iter_images(cap, BOX, decoded=pf))
                err = None
            except PsctlError as e:
                err = str(e)
        open(sys.argv[1], "w").write(json.dumps([got, err]))
    """, tmp_path)
    assert out[0] == [True, True, True, True, False]
    assert out[1] is not None and bad.name in out[1]


def test_a_larger_image_put_in_after_opening_is_left_to_the_reader(tmp_path):
    """An image replaced by a larger one after the folder was opened: the helper must not hand
    over its crop (which has the right shape); the reader then says the size differs."""
    from psctl.io.images import write_image

    write_capture(tmp_path / "cap", n=5, size=40)
    cap = open_capture(tmp_path / "cap")
    write_image(cap.image_paths[2], np.full((48, 48, 3), 0.5, np.float32), "uint16")
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        with pytest.raises(PsctlError, match="size 48x48 differs"):
            list(iter_images(cap, BOX, decoded=pf))
        assert pf.served == 2


def test_a_child_that_imports_another_psctl_hands_over_nothing(tmp_path, monkeypatch):
    """The child imports psctl by name; where that finds another copy than this process's (a
    changed sys.path, a notebook), its reading might differ: it stops, and the images are read here."""
    import psctl

    write_capture(tmp_path / "cap", n=3, size=40)
    cap = open_capture(tmp_path / "cap")
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:  # the control: this psctl
        assert pf.take(cap.image_paths[0], BOX) is not None
    monkeypatch.setattr(psctl, "__file__", str(tmp_path / "elsewhere" / "psctl" / "__init__.py"))
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        assert pf.proc is not None and pf.take(cap.image_paths[0], BOX) is None


def test_many_small_images_run_ahead_without_a_deadlock(tmp_path):
    """1,300 images with 1,000 slots: the freed slots pile up unread while the child decodes its
    first thousand, and its status lines fill the pipe. A blocking send for each freed slot filled
    the socket after about 280 and both sides waited for ever; here it must end, all handed over."""
    from psctl.io.images import write_image

    write_image(tmp_path / "one.png", np.full((8, 8, 3), 0.25, np.float32), "uint16")
    n = _fresh(f"""
        import json, sys
        from pathlib import Path
        from psctl.io.prefetch import Prefetch
        box = (slice(0, 8), slice(0, 8))
        paths = [Path({str(tmp_path / "one.png")!r})] * 1300
        with Prefetch(paths, box, (8, 8), 1000 * 4096) as pf:
            assert pf.slots == 1000
            served = sum(pf.take(p, box) is not None for p in paths)
        open(sys.argv[1], "w").write(json.dumps(served))
    """, tmp_path, timeout=120)
    assert n == 1300


def test_an_executable_that_is_not_python_is_given_up_quickly(tmp_path, monkeypatch):
    """An application embedding Python may name itself in sys.executable: the child then never
    starts. Without its "ready" line within START_TIMEOUT the images are read here, not after 120 s."""
    import time

    import psctl.io.prefetch as prefetch

    fake = tmp_path / "app"
    fake.write_text("#!/bin/sh\nexec sleep 1000\n")
    fake.chmod(0o755)
    write_capture(tmp_path / "cap", n=3, size=40)
    cap = open_capture(tmp_path / "cap")
    monkeypatch.setattr(sys, "executable", str(fake))
    monkeypatch.setattr(prefetch, "START_TIMEOUT", 1.0)
    t = time.perf_counter()
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        assert pf.proc is not None and pf.take(cap.image_paths[0], BOX) is None
    assert time.perf_counter() - t < 10


def test_a_broken_image_in_a_network_run_after_images_were_handed_over(tmp_path):
    """In a fresh process (torch not imported) the helper hands over the images before the broken
    one, then the network's own read gives the one-line error naming it."""
    write_capture(tmp_path / "cap", n=8, size=40)
    bad = sorted((tmp_path / "cap").glob("*.png"))[4]
    bad.write_bytes(bad.read_bytes()[:300])
    msg, served = _fresh(f"""
        import json, sys
        import psctl.infer as infer
        from psctl.errors import PsctlError
        from psctl.io.capture import open_capture, load_mask
        made = []
        start = infer._prefetch
        infer._prefetch = lambda *a: made.append(start(*a)) or made[-1]
        cap = open_capture({str(tmp_path / "cap")!r}); mask = load_mask(cap)
        try:
            infer.capture_normals(cap, mask, "ensemble")
            msg = None
        except PsctlError as e:
            msg = str(e)
        open(sys.argv[1], "w").write(json.dumps([msg, made[0].served]))
    """, tmp_path)
    assert served == 4 and msg is not None and bad.name in msg and "\n" not in msg


def test_lcnet_gets_the_same_lights_with_the_helper(tmp_path):
    """`psctl lights` and sdps: LCNet's first pass takes the images from the helper too (in a fresh
    process, before torch is imported), with the same directions, intensities and notes."""
    write_capture(tmp_path / "cap", n=10, size=48)
    out = _fresh(f"""
        import json, sys
        import numpy as np
        from psctl.io.capture import open_capture, load_mask
        from psctl.lights import capture_lights
        cap = open_capture({str(tmp_path / "cap")!r}); mask = load_mask(cap)
        a = capture_lights(cap, mask)
        b = capture_lights(cap, mask, config={{"prefetch_mb": 0}})
        same = bool(np.array_equal(a.directions, b.directions) and np.array_equal(a.intensities, b.intensities))
        open(sys.argv[1], "w").write(json.dumps([a.info["prefetched"], b.info["prefetched"], same, a.notes == b.notes]))
    """, tmp_path)
    assert out == [10, 0, True, True]


def test_the_helper_serves_images_with_an_icc_profile(tmp_path):
    """A review: the helper sent each header as JSON, which an ICC tone curve is not, so it died
    at the first profiled image and the parent read every image itself (slower, same values)."""
    from tests.test_icc import curv_gamma, rgb_profile

    data = write_capture(tmp_path / "cap", n=4, size=40)
    icc = rgb_profile("ProPhoto RGB", curv_gamma(1.8))
    for k, img in enumerate(data["images"]):
        write_image(tmp_path / "cap" / f"{k + 1:03d}.png", np.clip(img, 0, 1) ** (256 / 461), "uint16", kind="data",
                    icc=icc)
    cap = open_capture(tmp_path / "cap")
    assert cap.profile_images == 4
    with Prefetch(cap.image_paths, BOX, (40, 40), 1 << 30) as pf:
        helped = list(iter_images(cap, BOX, decoded=pf))
        assert pf.served == 4
    assert all(np.array_equal(a, b) for a, b in zip(helped, iter_images(cap, BOX), strict=True))

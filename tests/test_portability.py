"""What other platforms would break, simulated on Linux (a portability audit, session 53):
Windows' os module, consoles in legacy code pages, lists written on Windows, no home folder."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from psctl.errors import PsctlError
from tests.conftest import write_capture


def test_outputs_list_reads_without_o_nonblock(tmp_path, monkeypatch):
    """Windows' os has no O_NONBLOCK: every command that writes outputs read its list with it."""
    from psctl.io.atomic import read_outputs_list, write_outputs_list

    write_outputs_list(tmp_path, ["normal.png", "réport.json"], "normals")
    monkeypatch.delattr(os, "O_NONBLOCK")
    assert read_outputs_list(tmp_path, "normals") == ["normal.png", "réport.json"]


def test_no_liveness_probe_by_signal_on_windows(monkeypatch):
    """On Windows os.kill(pid, 0) sends Ctrl-C (CTRL_C_EVENT is 0) to the console's processes:
    the staging sweep must not call it there (it then sweeps nothing)."""
    from psctl.io import atomic

    def kill(pid, sig):
        raise AssertionError("os.kill called")

    monkeypatch.setattr(atomic.os, "kill", kill)
    monkeypatch.setattr(atomic.os, "name", "nt")
    try:
        alive = atomic._running(123456)
    finally:
        monkeypatch.undo()
    assert alive is True


def test_a_list_written_on_windows_reads_on_posix(tmp_path):
    from psctl.io.capture import open_capture

    write_capture(tmp_path / "cap", n=6)
    (tmp_path / "cap" / "imgs").mkdir()
    for k in range(6):
        os.replace(tmp_path / "cap" / f"{k + 1:03d}.png", tmp_path / "cap" / "imgs" / f"{k + 1:03d}.png")
    (tmp_path / "cap" / "filenames.txt").write_bytes(b"".join(b"imgs\\%03d.png\r\n" % (k + 1) for k in range(6)))
    cap = open_capture(tmp_path / "cap")
    assert [p.relative_to(tmp_path / "cap").as_posix() for p in cap.image_paths] == \
        [f"imgs/{k + 1:03d}.png" for k in range(6)]


def test_light_images_list_uses_forward_slashes_and_survives_other_drives(tmp_path, monkeypatch):
    from psctl.io.capture import open_capture
    from psctl.lights import image_list

    write_capture(tmp_path / "cap", n=4)
    cap = open_capture(tmp_path / "cap")
    assert image_list(cap) == "001.png\n002.png\n003.png\n004.png\n"

    def other_drive(path, start=None):
        raise ValueError("path is on mount 'D:', start on mount 'C:'")

    monkeypatch.setattr(os.path, "relpath", other_drive)
    assert image_list(cap).splitlines()[0] == (tmp_path / "cap" / "001.png").as_posix()


def test_signal_names_where_the_platform_lacks_the_signal():
    from psctl.cli import _signal_name

    assert _signal_name(15) == "SIGTERM"
    assert _signal_name(13) == "SIGPIPE"
    assert _signal_name(9999) == "signal 9999"


def test_a_console_that_cannot_spell_a_name_gets_escapes(tmp_path):
    """A folder name outside the console's code page (cp1252 on Windows, ASCII with LANG=C): the
    summary printed with escapes, exit 0, instead of a UnicodeEncodeError after the outputs."""
    write_capture(tmp_path / "写真", n=6)
    env = {**os.environ, "PYTHONIOENCODING": "ascii", "COLUMNS": "100"}
    for args in (["info", tmp_path / "写真"], ["normals", tmp_path / "写真", "-m", "l2", "-q"]):
        p = subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, args)], capture_output=True, env=env)
        assert p.returncode == 0, p.stderr.decode("ascii", "replace")
        assert b"\\u5199\\u771f" in p.stdout and b"Traceback" not in p.stderr
    p = subprocess.run([sys.executable, "-m", "psctl.cli", "info", str(tmp_path / "写真" / "none")],
                       capture_output=True, env=env)
    assert p.returncode == 2 and p.stderr.count(b"\n") == 1 and b"\\u5199" in p.stderr


def test_no_home_folder(monkeypatch):
    """No $HOME and no passwd entry (a container under an arbitrary user id): Path.home() raises
    RuntimeError, which was a traceback of psctl eval and of the weights lookup."""
    import pwd

    from psctl.eval import default_diligent_root
    from psctl.paths import user_data_dir

    monkeypatch.delenv("HOME", raising=False)
    monkeypatch.delenv("XDG_DATA_HOME", raising=False)
    monkeypatch.delenv("PSCTL_DATA", raising=False)

    def nobody(uid):
        raise KeyError(f"getpwuid(): uid not found: {uid}")

    monkeypatch.setattr(pwd, "getpwuid", nobody)
    with pytest.raises(RuntimeError):
        Path.home()  # the premise
    assert user_data_dir() == Path("~/.local/share/psctl")
    with pytest.raises(PsctlError, match="DiLiGenT not found"):
        default_diligent_root()


def test_text_inputs_are_read_as_utf8_whatever_the_locale(tmp_path):
    """A recipe with a non-ASCII character (the PS-FCN† configs have one) under LANG=C."""
    config = tmp_path / "tiny†.yaml"
    config.write_text("# PS-FCN† recipe\n" + (Path(__file__).parents[1] / "configs" / "tiny.yaml").read_text(),
                      encoding="utf-8")
    code = ("import sys; from psctl.train import load_config; "
            "c = load_config(sys.argv[1]); print(sorted(c)[:2])")
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    p = subprocess.run([sys.executable, "-c", code, str(config)], capture_output=True, env=env)
    assert p.returncode == 0, p.stderr.decode("utf-8", "replace")


def test_a_line_printed_into_a_pipe_stays_one_line(monkeypatch):
    """Into a pipe or a file a note stays on one line, for grep (Rich broke it at 80 columns); the
    summary's object notes too (a QA round: pot2's "scoring:" note in `psctl eval | cat`)."""
    import io

    from psctl.errors import console
    from psctl.io.summary import _object_notes, print_notes

    monkeypatch.delenv("COLUMNS", raising=False)
    monkeypatch.setenv("FORCE_COLOR", "1")  # (Rich then takes any file for a terminal: a review's case)
    con = console()
    con.file = io.StringIO()
    note = "scoring: " + " ".join(["word"] * 60)
    print_notes(con, [note])
    _object_notes(con, [{"objects": [{"name": "pot2", "notes": [note]}]}])
    con.print("a plain line " + "x " * 80, highlight=False)
    lines = con.file.getvalue().splitlines()
    assert len(lines) == 3 and lines[1] == f"  pot2: {note}", lines

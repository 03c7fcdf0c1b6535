"""The psctl command end to end: outputs, JSON, and one-line errors for every bad input."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from psctl.io.images import read_image, write_image
from psctl.io.normals import read_normal_map
from psctl.metrics import angular_error
from tests.conftest import weights_in, write_capture


def psctl(*args: str, check: bool = False, env: dict | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "100", **(env or {})}, cwd=cwd)
    if check and proc.returncode != 0:
        raise AssertionError(proc.stderr)
    return proc


def cli(*args: str, env: dict | None = None, check: bool = False) -> subprocess.CompletedProcess:
    """psctl in this process (typer's runner): as ``psctl`` without a Python start and a torch
    import per call; for the many one-line refusals. An exception that escapes the command
    (a traceback in a shell) is re-raised here."""
    from typer.testing import CliRunner

    from psctl.cli import app

    r = CliRunner().invoke(app, list(map(str, args)), env={"COLUMNS": "100", **(env or {})})
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception
    if check and r.exit_code != 0:
        raise AssertionError(r.stderr)
    return subprocess.CompletedProcess(args, r.exit_code, r.stdout, r.stderr)


def test_normals_writes_outputs_and_json(capture, tmp_path):
    out = tmp_path / "out"
    proc = cli("normals", capture, "--method", "l2", "--out", out, "--json", check=True)
    r = json.loads(proc.stdout)
    for key in ("object", "path", "method", "calibrated", "n_images", "height", "width", "seconds", "outputs",
                "mae", "median", "within"):
        assert key in r
    assert r["object"] == "sphere" and r["n_images"] == 12 and set(r["within"]) == {"11.25", "22.5", "30"}
    assert sorted(os.listdir(out)) == [".psctl-normals", "error.png", "normal.exr", "normal.png", "report.json"]
    pixels, info = read_image(out / "normal.png")
    assert info.bits == 16 and pixels.shape == (40, 40, 3)
    report = json.loads((out / "report.json").read_text())
    assert report["mae"] == pytest.approx(r["mae"]) and report["seconds"] == r["seconds"]
    # the PNG decodes to the same normals as the EXR, and both agree with the metric
    a, b = read_normal_map(out / "normal.png"), read_normal_map(out / "normal.exr")
    m = np.linalg.norm(b, axis=-1) > 0
    assert angular_error(a, b, m).max() < 0.01


def test_default_output_folder_and_formats(capture):
    proc = cli("normals", capture, "-m", "l2", "--format", "png8,npy", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert sorted(os.listdir(capture / "psctl")) == [".psctl-normals", "error.png", "normal.npy", "normal_8bit.png",
                                                     "report.json"]
    assert "ball" not in proc.stdout and "sphere" in proc.stdout
    # -f given more than once adds up (it kept only the last before)
    proc = cli("normals", capture, "-m", "l2", "-f", "png16", "-f", "npy,exr", "-o", capture.parent / "o2", "-q")
    assert proc.returncode == 0, proc.stderr
    assert {"normal.png", "normal.npy", "normal.exr"} <= set(os.listdir(capture.parent / "o2"))


def test_images_subset(capture, tmp_path):
    r = json.loads(cli("normals", capture, "-m", "l2", "--images", "5", "--seed", "3", "--out", tmp_path / "o",
                         "--json", check=True).stdout)
    assert r["n_images"] == 5


def test_auto_falls_back_to_l2_and_says_so(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "no-weights"))  # whatever weights/ holds
    proc = cli("normals", capture, "--out", tmp_path / "o", check=True)
    assert "l2" in proc.stdout and "auto" in proc.stdout
    # a mistyped $PSCTL_WEIGHTS is named, not mistaken for weights never installed
    assert "$PSCTL_WEIGHTS, which does not exist" in " ".join(proc.stdout.split())
    proc = cli("normals", capture, "-m", "ps-fcn", "--out", tmp_path / "o2")
    assert proc.returncode == 2 and "which does not exist" in proc.stderr and len(proc.stderr.splitlines()) == 1
    (tmp_path / "a-file").write_text("")  # $PSCTL_WEIGHTS naming a file: said so, not "does not exist"
    proc = cli("normals", capture, "-m", "ps-fcn", "--out", tmp_path / "o3", env={"PSCTL_WEIGHTS": str(tmp_path / "a-file")})
    assert proc.returncode == 2 and "which is a file, not a folder" in proc.stderr, proc.stderr
    # psctl eval's table says it too (the note was only in --json)
    write_capture(tmp_path / "root" / "aPNG", n=6, size=24)
    table = cli("eval", "-b", "folder", "--root", tmp_path / "root", check=True).stdout
    assert "auto: no trained network weights are installed" in " ".join(table.split())


def test_an_installed_wheel_keeps_its_weights_in_the_user_data_folder(capture, tmp_path, monkeypatch):
    """Run from a checkout, psctl reads weights/ beside its package; installed from a wheel (no
    pyproject.toml above the package) it reads ~/.local/share/psctl/weights, not a folder named
    weights in site-packages, and its messages say where the release weights are."""
    import psctl.paths
    from psctl.api import run_normals
    from psctl.errors import PsctlError
    from psctl.models.weights import weights_dir
    from psctl.synth.meshes import mesh_dir

    repo = Path(__file__).resolve().parents[1]
    assert psctl.paths.checkout_root() == repo and weights_dir() == repo / "weights"
    monkeypatch.setattr(psctl.paths, "checkout_root", lambda: None)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert weights_dir() == tmp_path / "data" / "psctl" / "weights"
    assert mesh_dir() == tmp_path / "data" / "psctl" / "meshes"
    r = run_normals(capture, write=False)
    assert r["method"] == "l2" and any("copy the .pt files into" in n for n in r["notes"])
    with pytest.raises(PsctlError, match="release weights are in the weights/ folder of its source checkout"):
        run_normals(capture, method="ps-fcn", write=False)
    with pytest.raises(PsctlError) as e:  # nor does a wheel hold the configs/ and docs/ the messages name
        run_normals(capture, method="sdps", write=False)
    assert "copy the .pt files into" in str(e.value) and "a clone of psctl ships" not in str(e.value)
    assert str(e.value).endswith("(configs/ and docs/ are in psctl's source checkout, not in the wheel)")
    weights_dir().mkdir(parents=True)
    shutil.copy(repo / "weights" / "ps_fcn.pt", weights_dir())
    assert run_normals(capture, write=False)["method"] == "ps-fcn"
    with pytest.raises(PsctlError, match=r"--config configs/lcnet.yaml .*not in the wheel\)$"):
        run_normals(capture, method="sdps", write=False)
    with weights_in(tmp_path / "mine"):  # $PSCTL_WEIGHTS still comes first, and then no hint
        with pytest.raises(PsctlError) as e:
            run_normals(capture, method="ps-fcn", write=False)
        assert "copy the .pt files" not in str(e.value)


def test_a_listed_image_that_is_not_a_file(capture, tmp_path):
    """A FIFO (or socket, device) under a listed name: said so, not "missing" (it is there)."""
    from psctl.errors import PsctlError
    from psctl.io.capture import open_capture

    name = (capture / "filenames.txt").read_text().split()[2]
    (capture / name).unlink()
    os.mkfifo(capture / name)
    with pytest.raises(PsctlError, match=f"{name}: listed in filenames.txt but is not a regular file$"):
        open_capture(capture)


def test_an_empty_argument_is_refused(capture, tmp_path):
    """An unset shell variable (-o "$OUT") would make the output folder "." without a word."""
    for args, says in ((("normals", capture, "-o", ""), "an empty value after -o"),
                       (("normals", capture, "--out=", "-m", "l2"), "an empty value after --out"),
                       (("normals", ""), "psctl normals: argument 1 is empty"),
                       (("", "normals"), "psctl: argument 1 is empty"),
                       (("depth", capture, "--normals", "", "-o", tmp_path / "d"), "an empty value after --normals")):
        proc = psctl(*args, cwd=tmp_path)
        assert proc.returncode == 2 and says in proc.stderr and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert os.listdir(tmp_path) == [capture.name]  # nothing written (the capture is the fixture's)
    import psctl as api

    with pytest.raises(api.PsctlError, match="out is an empty path"):
        api.run_normals(capture, method="l2", out="")
    with pytest.raises(api.PsctlError, match="arrays must be a dict"):
        api.run_normals(capture, method="l2", out=tmp_path / "x", arrays=[])



def test_an_option_given_twice_with_two_values_is_refused(capture, tmp_path):
    """click keeps the last of a one-value option without a word: -o a -o b wrote to b only, and
    psctl normals -m l2 -m ps-fcn (psctl eval's comparison) ran ps-fcn alone (helper-201)."""
    for args, says in ((("normals", capture, "-m", "l2", "-o", tmp_path / "a", "-o", tmp_path / "b"),
                        "--out/-o given twice"),
                       (("normals", capture, "-m", "l2", "-m", "ps-fcn", "-o", tmp_path / "a"), "--method/-m given twice"),
                       (("normals", capture, "-ml2", f"--out={tmp_path / 'a'}", "-n3", "--images", "4"),
                        "--images/-n given twice (-n 3, then --images 4)"),
                       (("normals", capture, "-m", "sdps", "--refine", "--no-refine", "-o", tmp_path / "a"),
                        "--refine/--no-refine given twice (--refine, then --no-refine)"),
                       (("synth", tmp_path / "s", "-p", "syntest", "-p", "blobby"), "--preset/-p given twice")):
        proc = psctl(*args, cwd=tmp_path)
        assert proc.returncode == 2 and says in proc.stderr and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert sorted(os.listdir(tmp_path)) == [capture.name]  # nothing written
    # the same value twice, and the options that take a list, are fine
    proc = psctl("normals", capture, "-q", "-m", "l2", "-q", "-o", tmp_path / "a", "-o", tmp_path / "a", "-f", "png16",
                 "-f", "npy", "--no-snap", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert sorted(os.listdir(tmp_path / "a")) == sorted(["normal.png", "normal.npy", "error.png", "report.json",
                                                         ".psctl-normals"])
    assert "--no-snap is unused" in proc.stdout  # an option the method ignores is said, not silent


def test_sphere_and_decode_take_any_case_as_the_other_choices_do():
    """--method L2, --encoding SRGB, --precision FP16, --preset BLOBBY were taken; -s CHROME and
    --decode ARGMAX were refused (helper-201)."""
    from psctl.calibrate import check_sphere
    from psctl.lights import check_decode

    assert check_sphere("CHROME") == "chrome" and check_decode("ARGMAX", "--decode") == "argmax"


def test_the_empty_check_reads_the_command_line_it_is_given(monkeypatch):
    """app(args=[...]) (a test runner, a script) is checked, not the host program's sys.argv."""
    from typer.testing import CliRunner

    from psctl.cli import app

    monkeypatch.setattr(sys, "argv", ["host", "--out="])
    assert CliRunner().invoke(app, ["--version"]).exit_code == 0
    r = CliRunner().invoke(app, ["info", ""])
    assert r.exit_code == 2


def test_network_methods_without_light_file_name_it(capture, tmp_path):
    (tmp_path / "nol").mkdir()
    for f in capture.iterdir():
        if f.name != "light_directions.txt":
            (tmp_path / "nol" / f.name).write_bytes(f.read_bytes())
    proc = cli("normals", tmp_path / "nol", "-m", "ps-fcn", "--out", tmp_path / "o")
    assert proc.returncode == 2 and str(tmp_path / "nol" / "light_directions.txt") in proc.stderr
    assert "--method sdps" in proc.stderr and len(proc.stderr.splitlines()) == 1
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    w = save_weights(tmp_path / "p.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})
    proc = cli("normals", tmp_path / "nol", "-w", w, "--out", tmp_path / "o")  # auto, from the file
    assert proc.returncode == 2 and str(tmp_path / "nol" / "light_directions.txt") in proc.stderr
    assert "--method sdps" in proc.stderr and not (tmp_path / "o").exists()


def test_info(capture):
    r = json.loads(cli("info", capture, "--json", check=True).stdout)
    assert r["n_images"] == 12 and r["bit_depth"] == 16 and r["calibrated"] and r["ground_truth"] == "Normal_gt.mat"
    assert 0 < r["mask_coverage"] < 1 and r["notes"] == []
    assert "sphere" in cli("info", capture, check=True).stdout
    (capture / "mask_obj.png").write_bytes((capture / "mask.png").read_bytes())  # looks like a mask, is not read
    assert json.loads(cli("info", capture, "--json", check=True).stdout)["notes"][0].startswith("files: not read: mask_obj.png")
    assert "note: files: not read: mask_obj.png" in cli("info", capture, check=True).stdout
    (capture / "mask.png").unlink()  # none: what the methods make of that (not "the whole image" for all)
    assert "the networks and psctl lights find the object" in " ".join(cli("info", capture, check=True).stdout.split())


def test_info_says_what_psctl_normals_would_run(tmp_path, capture, fake_weights):
    """info names the method --method auto would run with the weights installed, or why it would
    stop, and notes fewer than 3 images before a run does (helper-163)."""
    env = {"PSCTL_WEIGHTS": str(fake_weights)}  # lcnet and ps_fcn_dagger only: calibrated folders get l2
    r = json.loads(cli("info", capture, "--json", env=env, check=True).stdout)
    assert r["auto_method"] == "l2" and r["auto_note"].startswith("auto: no trained network weights are installed")
    assert "--method auto runs l2" in cli("info", capture, env=env, check=True).stdout
    (tmp_path / "none").mkdir()
    (capture / "light_directions.txt").unlink()
    assert json.loads(cli("info", capture, "--json", env=env, check=True).stdout)["auto_method"] == "sdps"
    r = json.loads(cli("info", capture, "--json", env={"PSCTL_WEIGHTS": str(tmp_path / "none")}, check=True).stdout)
    assert r["auto_method"] is None and "lcnet" in r["auto_note"]
    proc = cli("normals", capture, "-o", tmp_path / "o", env={"PSCTL_WEIGHTS": str(tmp_path / "none")})
    assert proc.returncode == 2 and r["auto_note"] in proc.stderr  # what normals then says
    write_capture(tmp_path / "two", n=2, size=16)
    notes = json.loads(cli("info", tmp_path / "two", "--json", check=True).stdout)["notes"]
    assert any(n.startswith("images: 2 of them: l2 needs at least 3") for n in notes), notes


def test_info_check_decodes_every_file(tmp_path):
    folder = tmp_path / "o"
    truth = write_capture(folder, n=6)
    r = json.loads(cli("info", folder, "--json").stdout)
    assert "check" not in r  # headers only unless asked
    img = truth["images"][2].copy()
    img[truth["mask"]] = 1.0  # every object pixel at 65535
    write_image(folder / "003.png", img, "uint16", kind="linear")
    write_image(folder / "005.png", np.zeros((40, 40, 3)), "uint16", kind="linear")  # a light that did not fire
    c = json.loads(cli("info", folder, "--check", "--json").stdout)["check"]
    assert [x["image"] for x in c["images"]] == [f"{k:03d}.png" for k in range(1, 7)]
    assert c["saturated_images"] == ["003.png"] and c["images"][2]["saturated"] == 1.0
    assert c["images"][0]["saturated"] == 0.0 and c["images"][4]["mean"] == 0.0
    m = truth["mask"]
    assert c["images"][0]["mean"] == pytest.approx(read_image(folder / "001.png")[0][m].mean(), rel=1e-5)
    assert c["mean_range"][0] == 0.0 and c["mean_range"][2] == c["images"][2]["mean"]
    assert c["mean_range"][1] == pytest.approx(np.median([x["mean"] for x in c["images"]]))  # the median, not the mean
    red = truth["images"][3].copy()
    red[truth["mask"], 0] = 1.0  # only the red channel clipped: saturated all the same
    write_image(folder / "004.png", red, "uint16", kind="linear")
    c = json.loads(cli("info", folder, "--check", "--json").stdout)["check"]
    assert c["images"][3]["saturated"] == 1.0 and c["saturated_images"] == ["003.png", "004.png"]
    write_image(folder / "004.png", truth["images"][3], "uint16", kind="linear")
    assert len(c["notes"]) == 1 and c["notes"][0].startswith("images: 1 of 6 black over the object (005.png)")
    out = cli("info", folder, "--check").stdout
    assert "saturated: 1 of 6 images" in out and "003.png, 100.0%" in out and "005.png" in out
    # damaged files: the first named, the others counted, exit 2, one line
    for name in ("002.png", "004.png", "006.png"):
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: len(data) // 2])
    assert cli("info", folder).returncode == 0  # headers still read
    proc = cli("info", folder, "--check")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith(f"error: {folder / '002.png'}: corrupt or truncated image")
    assert "(and 2 more damaged: 004.png, 006.png)" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_info_check_stops_where_normals_would(tmp_path):
    """--check judges the images as psctl normals reads them: every image black, or an ambient
    image that blacks one out, is the same one-line error (exit 2), not a pass."""
    dark = tmp_path / "dark"
    write_capture(dark, n=4)
    for k in range(1, 5):
        write_image(dark / f"{k:03d}.png", np.zeros((40, 40, 3)), "uint16", kind="linear")
    for args in (("info", dark, "--check"), ("normals", dark, "-m", "l2", "-o", tmp_path / "o1")):
        proc = cli(*args)
        assert proc.returncode == 2 and proc.stderr.strip() == f"error: {dark}: all images are black inside the mask"
    amb = tmp_path / "amb"
    write_capture(amb, n=4)
    (amb / "ambient.png").write_bytes((amb / "004.png").read_bytes())  # as bright as an image: blacks it out
    assert cli("info", amb).returncode == 0  # headers alone cannot tell
    for args in (("info", amb, "--check"), ("normals", amb, "-m", "l2", "-o", tmp_path / "o2")):
        proc = cli(*args)
        assert proc.returncode == 2 and proc.stderr.startswith(f"error: {amb / 'ambient.png'}: subtracting it leaves 004.png black")
    # an ambient image that blacks out the object only: the note normals gives, after the subtraction
    mask = write_capture(tmp_path / "ref", n=4)["mask"]
    img = read_image(amb / "004.png")[0]
    img[~mask] = 0.05  # lit around the object
    write_image(amb / "004.png", img, "uint16", kind="linear")
    img[~mask] = 0.0
    write_image(amb / "ambient.png", img, "uint16", kind="linear")  # the object as bright as in 004.png
    c = json.loads(cli("info", amb, "--check", "--json").stdout)["check"]
    assert c["notes"][0].startswith("images: 1 of 4 black over the object (004.png)")
    assert c["images"][3]["mean"] > 0  # the means are of the images as captured


def test_info_on_a_benchmark_root_shows_every_note_and_cuts_nothing(tmp_path):
    root = tmp_path / "root"
    for name in ("session_2026_11_27_object_left", "session_2026_11_27_object_right"):
        write_capture(root / name, n=4)
    lights = np.loadtxt(root / "session_2026_11_27_object_left" / "light_directions.txt")
    lights[2] = [0.9, 0.0, -0.1]
    np.savetxt(root / "session_2026_11_27_object_left" / "light_directions.txt", lights)
    (root / "session_2026_11_27_object_right" / "light_intensity.txt").write_text("1\n")  # misnamed
    wide = cli("info", root, "--check", env={"COLUMNS": "200"}).stdout
    assert "┃ object" in wide and "…" not in wide
    narrow = cli("info", root, "--check", env={"COLUMNS": "60"}).stdout
    assert "…" not in narrow and "┃" not in narrow  # one line per object instead of a cut table
    for out in (wide, narrow):
        assert "note: session_2026_11_27_object_left: light file: 1 of 4 light directions have z <= 0" in out
        assert "note: session_2026_11_27_object_right: files: not read: light_intensity.txt" in out
    assert "session_2026_11_27_object_right: images 4, size 40x40, bits 16, calibrated yes" in narrow
    one = tmp_path / "one"
    write_capture(one / "a", n=4)
    proc = cli("normals", one, "-m", "l2")
    assert proc.returncode == 2 and f"benchmark root with one object folder, not a capture: pass {one / 'a'}" in proc.stderr
    proc = cli("normals", root, "-m", "l2")
    assert proc.returncode == 2 and "holds 2 object folders (a benchmark root: session_2026_11_27_object_left," in proc.stderr


def test_info_names_mixed_channels_and_keeps_long_names_whole(tmp_path):
    folder = tmp_path / "o"
    write_capture(folder, n=4)
    grey = read_image(folder / "001.png")[0].mean(-1)
    write_image(folder / "001.png", grey, "uint16", kind="linear")
    r = json.loads(cli("info", folder, "--json").stdout)
    assert r["channels"] == 1 and r["channel_counts"] == [1, 3]
    out = cli("info", folder, env={"COLUMNS": "80"}).stdout
    assert "mixed: 1/3 channels" in out and "(all ones)" not in out
    long = "capture_session_2026_11_27_light_position_{:03d}_exposure_1over60.png"
    names = [long.format(k) for k in range(1, 5)]
    for k, name in enumerate(names, 1):
        (folder / f"{k:03d}.png").rename(folder / name)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    write_image(folder / names[0], np.repeat(grey[..., None], 3, -1), "uint16", kind="linear")
    out = cli("info", folder, env={"COLUMNS": "80"}).stdout
    flat = "".join(out.replace("│", " ").split())  # the table wraps the names; nothing is cut
    assert "…" not in out and names[0] in flat and names[-1] in flat
    assert "│ size         │ 40 x 40, 3 channels " in out


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM", "SIGHUP"])
@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGHUP"), reason="no SIGHUP on this platform")
def test_termination_while_writing_leaves_nothing(capture, tmp_path, monkeypatch, signame):
    """Ctrl-C, a scheduler's SIGTERM or a closed terminal's SIGHUP: the staged files are
    discarded, the output folder and the parents the run created are removed, and the exit
    status says which (130, 143, 129), never 0."""
    import signal

    import psctl.io.report

    sig = getattr(signal, signame)
    write = psctl.io.report.write_error_map

    def killed(*args, **kwargs):
        write(*args, **kwargs)
        signal.raise_signal(sig)  # the handler raises here, mid-way through the outputs

    monkeypatch.setattr(psctl.io.report, "write_error_map", killed)
    inherited = signal.getsignal(sig)
    # a test run started under nohup, or as a background job (SIGINT ignored), inherits ignored
    # signals, which psctl rightly leaves ignored: the first part wants a terminal's defaults
    before = signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL
    signal.signal(sig, before)
    try:
        proc = cli("normals", capture, "-m", "l2", "--out", tmp_path / "a" / "b" / "out")
        assert proc.returncode == 128 + sig
        assert proc.stderr.strip() == ("interrupted" if signame == "SIGINT" else "terminated")
        assert not (tmp_path / "a").exists() and signal.getsignal(sig) == before  # handler restored
        if signame == "SIGHUP":  # under nohup SIGHUP is ignored, and psctl leaves it so: the run completes
            signal.signal(sig, signal.SIG_IGN)
            proc = cli("normals", capture, "-m", "l2", "--out", tmp_path / "a" / "b" / "out")
            assert proc.returncode == 0 and (tmp_path / "a" / "b" / "out" / "error.png").is_file()
    finally:
        signal.signal(sig, inherited)


def test_reports_hold_absolute_paths(capture, tmp_path, monkeypatch):
    """A report.json read from another working directory still points at its files; and the
    saved reports are what the calls returned (seconds included)."""
    from psctl.api import run_normals
    from psctl.depth import run_depth

    monkeypatch.chdir(tmp_path)
    r = run_normals("spherePNG", method="l2", out="o")
    assert r["path"] == str(capture) and r["outputs"]["report"] == str(tmp_path / "o" / "report.json")
    assert all(Path(p).is_absolute() and Path(p).is_file() for p in r["outputs"].values())
    assert json.loads((tmp_path / "o" / "report.json").read_text()) == r
    d = run_depth("spherePNG", normals="o/normal.exr", out="d")
    assert d["normals"] == str(tmp_path / "o" / "normal.exr") and d["path"] == str(capture)
    assert all(Path(p).is_absolute() for p in d["outputs"].values())
    assert json.loads((tmp_path / "d" / "depth_report.json").read_text()) == d


def test_eval_on_a_folder_of_objects(tmp_path):
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=1)
    write_capture(tmp_path / "root" / "bPNG", n=6, seed=2)
    r = json.loads(cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--json",
                         check=True).stdout)
    assert [o["name"] for o in r["objects"]] == ["a", "b"]
    assert r["mean_mae"] == pytest.approx(np.mean([o["mae"] for o in r["objects"]]))
    from psctl.api import run_normals

    for o, name in zip(r["objects"], ("aPNG", "bPNG")):  # each row is its object's run, median too
        one = run_normals(tmp_path / "root" / name, "l2", write=False)
        assert (o["mae"], o["median"]) == pytest.approx((one["mae"], one["median"]))
        assert o["median"] != pytest.approx(o["mae"])
    table = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", check=True).stdout
    assert "avg" in table
    # options l2 ignores: said once for the table, as psctl normals says them (an audit: eval said nothing)
    r = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--views", "8",
            "--precision", "bf16", "--no-refine", "--json", check=True)
    assert json.loads(r.stdout)["notes"] == [
        "lights: --no-refine is unused (only sdps refines lights)",
        "views: l2 gives the same normals in every view; one pass",
        "precision: l2 solves in float64; --precision bf16 unused"]
    # auto running sdps on an object without lights uses --no-refine: no such note then (a review)
    (tmp_path / "root" / "bPNG" / "light_directions.txt").unlink()
    r = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "auto", "--no-refine", "--json",
            check=True)
    res = json.loads(r.stdout)
    assert res["method"] == "ensemble + sdps"
    assert not any("--no-refine is unused" in n for n in res["notes"])


def test_eval_scores_missing_ground_truth_as_the_paper_too(tmp_path):
    """An object whose ground truth has holes in the mask (DiLiGenT's pot2): its row carries the
    score as the authors' code counts it, the mean too, and the table shows both beside the paper's."""
    import scipy.io

    for name, seed in (("ballPNG", 1), ("catPNG", 2)):
        write_capture(tmp_path / "root" / name, n=6, seed=seed)
    mat = tmp_path / "root" / "catPNG" / "Normal_gt.mat"
    gt = scipy.io.loadmat(mat)["Normal_gt"]
    inside = np.argwhere(np.linalg.norm(gt, axis=-1) > 0.5)[::5]
    gt[inside[:, 0], inside[:, 1]] = 0
    scipy.io.savemat(mat, {"Normal_gt": gt})
    r = json.loads(psctl("eval", "--root", tmp_path / "root", "-m", "l2", "--json", check=True).stdout)
    ball, cat = r["objects"]
    assert ball["mae_missing_as_90"] == ball["mae"] and cat["mae_missing_as_90"] > cat["mae"] + 10
    assert r["mean_mae_missing_as_90"] == pytest.approx((ball["mae"] + cat["mae_missing_as_90"]) / 2)
    table = psctl("eval", "--root", tmp_path / "root", "-m", "l2", check=True).stdout
    row = next(line for line in table.splitlines() if "scored as the paper" in line)
    assert f"{cat['mae_missing_as_90']:.2f}" in row and f"{r['mean_mae_missing_as_90']:.2f}" in row
    assert "l2 (paper)" in table and " 4.10 " in table  # DiLiGenT's ball, as published
    assert "cat: scoring:" in " ".join(table.split())  # the note under the table names the object
    md = psctl("eval", "--root", tmp_path / "root", "-m", "l2", "--markdown", check=True)
    assert md.stdout.splitlines()[:2] == ["| method | ball | cat | avg |", "| --- | ---: | ---: | ---: |"]
    assert f"| l2, scored as the paper | {ball['mae']:.2f} | {cat['mae_missing_as_90']:.2f} | " \
           f"{r['mean_mae_missing_as_90']:.2f} |" in md.stdout.splitlines()
    assert "| l2 (paper) | 4.10 | 8.41 |" in md.stdout and "cat: scoring:" in " ".join(md.stderr.split())
    # a terminal too narrow for the paper's layout turns the table, the extra row a column of its own
    narrow = cli("eval", "--root", tmp_path / "root", "-m", "l2", env={"COLUMNS": "40"})
    assert narrow.returncode == 0, narrow.stderr
    cat_line = next(line for line in narrow.stdout.splitlines() if line.startswith("│ cat "))
    assert f"{cat['mae']:.2f}" in cat_line and f"{cat['mae_missing_as_90']:.2f}" in cat_line
    assert max(len(line) for line in narrow.stdout.splitlines() if line[:1] in "┏┃┡│├└") <= 40
    # without a mask file there is no mask to count over (it counted the background at 90 degrees)
    (tmp_path / "root" / "catPNG" / "mask.png").unlink()
    r = json.loads(psctl("eval", "--root", tmp_path / "root", "-m", "l2", "--json", check=True).stdout)
    ball, cat = r["objects"]
    assert ball["mae_missing_as_90"] == ball["mae"] and cat["mae_missing_as_90"] is None and cat["mae"] is not None
    assert r["mean_mae_missing_as_90"] is None and not any("scoring:" in n for n in cat["notes"])
    table = psctl("eval", "--root", tmp_path / "root", "-m", "l2", check=True).stdout
    assert "scored as the paper" not in table  # (ball's is its mae, cat's none)


def test_eval_light_means_and_paper_lights():
    """sdps rows: a mean light error only when every object has one (an average over some objects
    would sit beside the paper's over all); the paper's light numbers only on DiLiGenT."""
    from psctl.eval import PAPER_DILIGENT_LIGHTS, _table

    row = {"name": "ball", "mae": 3.0, "median": 2.0, "mae_missing_as_90": 3.0, "light_mae": 2.0, "intensity_re": 0.05,
           "lcnet_light_mae": 3.0, "lcnet_intensity_re": 0.06}
    r = _table("folder", Path("."), [dict(row), {**row, "name": "cat", "light_mae": None}], ["sdps"], None)
    assert r["mean_light_mae"] is None and r["mean_intensity_re"] == pytest.approx(0.05)
    assert r["paper_lights"] == {}  # an object named "ball" in a folder benchmark is not DiLiGenT's
    r = _table("diligent", Path("."), [dict(row)], ["sdps"], None)
    assert r["mean_light_mae"] == 2.0 and r["paper_lights"] == {"ball": PAPER_DILIGENT_LIGHTS["ball"]}


def test_eval_table_of_many_objects_turns_to_fit(tmp_path):
    """Objects as columns (the paper's layout) when they fit, as rows when not: every object's
    number and the average are printed at 80 columns."""
    names = [f"object_with_a_long_name_{k}" for k in range(9)]
    for k, name in enumerate(names):
        write_capture(tmp_path / "root" / f"{name}PNG", n=6, size=24, seed=k)
    r = json.loads(cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--json").stdout)
    out = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2").stdout
    lines = out.splitlines()
    assert max(map(len, lines)) <= 100  # cli() renders at 100 columns
    for o in r["objects"]:
        assert any(o["name"] in line and f"{o['mae']:.2f}" in line for line in lines), o["name"]
    assert any("avg" in line and f"{r['mean_mae']:.2f}" in line for line in lines)


def test_eval_table_of_sdps_fits_80_columns(capsys, monkeypatch):
    """sdps' eight rows of DiLiGenT's ten objects, as a pipe (80 columns) prints them: every
    number is there and no line is wider than the terminal."""
    from psctl.io.summary import render_benchmark

    monkeypatch.setenv("COLUMNS", "80")
    names = ["ball", "cat", "pot1", "bear", "pot2", "buddha", "goblet", "reading", "cow", "harvest"]
    objs = [dict(name=n, mae=5.0 + i, n_images=96, seconds=1.0, light_mae=3.0 + i / 10, intensity_re=0.05,
                 lcnet_light_mae=4.0, lcnet_intensity_re=0.07, lights_refined={"weight": 0.5})
            for i, n in enumerate(names)]
    render_benchmark(dict(benchmark="diligent", root="/x", method="sdps", objects=objs, mean_mae=9.5,
                          paper={n: 8.0 for n in names}, paper_method="sdps", mean_light_mae=3.45,
                          mean_intensity_re=0.05, mean_lcnet_light_mae=4.0, mean_lcnet_intensity_re=0.07,
                          paper_lights={n: {"light_mae": 3.0, "intensity_re": 0.05} for n in names}, notes=[]))
    lines = capsys.readouterr().out.splitlines()
    assert max(map(len, lines)) <= 80
    for i, n in enumerate(names):
        assert any(n in line and f"{5.0 + i:.2f}" in line and f"{3.0 + i / 10:.2f}" in line for line in lines), n
    assert any("avg" in line and "9.50" in line and "3.45" in line for line in lines)


def test_eval_table_names_whose_published_numbers_it_shows(capsys):
    """The paper has no ensemble: beside it the table shows the paper's PS-FCN+N, and says so."""
    from psctl.eval import PAPER_DILIGENT, _table
    from psctl.io.summary import render_benchmark

    objs = [{"name": n, "mae": 3.0, "mae_missing_as_90": 3.0 + k, "n_images": 96, "seconds": 1.0}
            for k, n in enumerate(("ball", "cat"))]
    r = _table("diligent", Path("root"), objs, ["ensemble", "ensemble"], None)
    assert r["mean_mae"] == 3.0 and r["mean_mae_missing_as_90"] == 3.5
    assert r["method"] == "ensemble" and r["paper_method"] == "ps-fcn-n"
    assert r["paper"] == {n: PAPER_DILIGENT["ps-fcn-n"][n] for n in ("ball", "cat")}
    render_benchmark(r)
    out = capsys.readouterr().out
    assert "ensemble (psctl)" in out and "ps-fcn-n (paper)" in out
    r = _table("diligent", Path("root"), objs, ["l2", "l2"], None)
    assert r["paper_method"] == "l2" and r["paper"]["cat"] == PAPER_DILIGENT["l2"]["cat"]
    # the published numbers with the decimals published: DiLiGenT's L2 4.10, the networks' 2.8
    render_benchmark(r)
    paper_row = next(line for line in capsys.readouterr().out.splitlines() if "l2 (paper)" in line)
    assert " 4.10 " in paper_row and " 8.41 " in paper_row
    render_benchmark(_table("diligent", Path("root"), objs, ["ps-fcn", "ps-fcn"], None))
    paper_row = next(line for line in capsys.readouterr().out.splitlines() if "ps-fcn (paper)" in line)
    assert " 2.8 " in paper_row and " 6.2 " in paper_row and "2.80" not in paper_row
    assert r["mean_paper"] == pytest.approx((4.10 + 8.41) / 2)  # the paper row's avg, in the JSON too (helper-213)
    r = _table("folder", Path("root"), objs, ["ensemble", "ensemble"], None)
    assert r["paper"] == {} and r["paper_method"] is None
    # the settings that change the numbers are named beside the method; the defaults are not
    render_benchmark(_table("folder", Path("root"), objs, ["ensemble"] * 2, None, 8, 2, "bf16"))
    assert "ensemble, 8 views, 1/2 size, bf16 (psctl)" in capsys.readouterr().out
    render_benchmark(_table("folder", Path("root"), objs, ["ensemble"] * 2, None, 1, 1, "float32"))
    assert "│ ensemble (psctl)" in capsys.readouterr().out


def test_eval_without_diligent_says_where_to_get_it(tmp_path):
    env = {**os.environ, "PSCTL_DATA": str(tmp_path), "HOME": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-m", "psctl.cli", "eval"], capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "--root" in proc.stderr and "DiLiGenT" in proc.stderr
    for where in (tmp_path / "DiLiGenT" / "pmsData", tmp_path / "diligent" / "pmsData",
                  tmp_path / ".cache" / "psctl" / "DiLiGenT" / "pmsData"):
        assert str(where) in proc.stderr, proc.stderr  # every place looked in
    assert len(proc.stderr.strip().splitlines()) == 1


def test_diligent_is_found_in_lower_case_too(tmp_path, monkeypatch):
    from psctl.eval import default_diligent_root

    (tmp_path / "diligent" / "pmsData").mkdir(parents=True)  # the development data's layout
    monkeypatch.setenv("PSCTL_DATA", str(tmp_path))
    assert default_diligent_root().samefile(tmp_path / "diligent" / "pmsData")  # case-blind file systems too


@pytest.mark.parametrize("argv", [["--help"], ["normals", "--help"], ["eval", "--help"], ["train", "--help"],
                                  ["-h"], ["lights", "-h"]])  # -h as well, as most tools take it
def test_help_imports_nothing_heavy(argv):
    """`psctl --help` must stay instant: no torch, OpenImageIO or scipy behind it."""
    code = ("import sys\nfrom psctl.cli import main\nsys.argv = ['psctl'] + sys.argv[1:]\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('torch', 'OpenImageIO', 'scipy') if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "Usage" in proc.stdout
    assert "<bool>" not in proc.stdout  # flags take no value, --help included


def test_submodules_are_found_by_name_after_import_psctl():
    """After a plain `import psctl`, psctl.infer.array_normals, psctl.io.capture.iter_images and
    the other names the docs write resolve (their modules imported then: an AttributeError before
    unless another call had imported them, a docs check); `import psctl` itself imports nothing
    heavy, and a name that is no submodule stays an AttributeError (dotted ones too: an import
    error before a review)."""
    code = ("import sys\nimport psctl\n"
            "heavy = [m for m in ('torch', 'OpenImageIO', 'scipy', 'psctl.infer') if m in sys.modules]\n"
            "assert not heavy, heavy\n"
            "print(psctl.infer.array_normals.__name__, psctl.eval.compare_methods.__name__, "
            "psctl.io.capture.iter_images.__name__, psctl.classic.L2Accumulator.__name__, "
            "psctl.synth.render.__name__, psctl.models.lcnet.__name__)\n"
            "for owner, name in ((psctl, 'nothing'), (psctl.io, 'nothing'), (psctl, '_infer'), (psctl, 'a.b'),\n"
            "                    (psctl, 'io.capture'), (psctl.io, 'x..y'), (psctl, '.')):\n"
            "    try:\n        getattr(owner, name)\n    except AttributeError:\n        pass\n"
            "    else:\n        raise SystemExit(name)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["array_normals", "compare_methods", "iter_images", "L2Accumulator",
                                   "psctl.synth.render", "psctl.models.lcnet"]


@pytest.mark.parametrize("argv, says", [
    (["normals", "x", "--bogus"], "--bogus"),            # an unknown option
    (["normals"], "'path'"),                               # a missing argument
    (["normals", "x", "--views", "abc"], "--views"),      # a value of the wrong type
    (["nosuch"], "nosuch"),                                # an unknown command
    (["info", "x", "--encoding"], "psctl info: option '--encoding' requires"),  # an option without its value
])
def test_command_line_mistake_is_one_line(argv, says):
    """Typer's own parse errors follow the user-error rule too: one line, exit code 2, no box."""
    proc = cli(*argv)
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and says in lines[0].lower() and "--help" in lines[0], proc.stderr
    assert "\u256d" not in proc.stderr and "Traceback" not in proc.stderr


# --- bad input: one line naming the file, exit code 2, no traceback, no output ---------------------


def _break(kind: str, folder: Path) -> str:
    """Damage a good capture folder; return the file name the error must mention."""
    if kind == "missing image":
        (folder / "003.png").unlink()
        return "003.png"
    if kind == "count mismatch":
        rows = (folder / "light_directions.txt").read_text().splitlines()
        (folder / "light_directions.txt").write_text("\n".join(rows[:-1]) + "\n")
        return "light_directions.txt"
    if kind == "malformed light":
        rows = (folder / "light_directions.txt").read_text().splitlines()
        rows[4] = "0.1 zero 0.9"
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        return "light_directions.txt"
    if kind == "nan light":
        rows = (folder / "light_directions.txt").read_text().splitlines()
        rows[2] = "nan 0 1"
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        return "light_directions.txt"
    if kind == "zero-length light":
        rows = (folder / "light_directions.txt").read_text().splitlines()
        rows[1] = "0 0 0"
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        return "light_directions.txt"
    if kind == "short light row":
        rows = (folder / "light_directions.txt").read_text().splitlines()
        rows[0] = "0.1 0.2"
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        return "light_directions.txt"
    if kind == "bad intensity":
        rows = (folder / "light_intensities.txt").read_text().splitlines()
        rows[3] = "1 0 1"
        (folder / "light_intensities.txt").write_text("\n".join(rows) + "\n")
        return "light_intensities.txt"
    if kind in ("tiny intensity", "huge intensity"):  # 0 or inf once in float32
        rows = (folder / "light_intensities.txt").read_text().splitlines()
        rows[4] = "1e-46 1 1" if kind == "tiny intensity" else "1 1e39 1"
        (folder / "light_intensities.txt").write_text("\n".join(rows) + "\n")
        return "light_intensities.txt"
    if kind == "coplanar lights":
        rows = [f"{np.cos(t):.6f} 0 {np.sin(t):.6f}" for t in np.linspace(0.3, 1.2, 12)]  # all in the plane y = 0
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        return "light_directions.txt"
    if kind == "black images":
        for k in range(12):
            write_image(folder / f"{k + 1:03d}.png", np.zeros((40, 40, 3)), "uint16")
        return str(folder.name)
    if kind == "listed folder":
        (folder / "003.png").unlink()
        (folder / "003.png").mkdir()
        return "003.png"
    if kind == "mask folder":
        (folder / "mask.png").unlink()
        (folder / "mask.png").mkdir()
        return "mask.png"
    if kind == "image size":
        write_image(folder / "005.png", np.zeros((30, 40, 3)), "uint16")
        return "005.png"
    if kind == "mask size":
        write_image(folder / "mask.png", np.ones((20, 20)), "uint8")
        return "mask.png"
    if kind == "gt size":
        import scipy.io

        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": np.zeros((20, 20, 3))})
        return "Normal_gt.mat"
    if kind == "empty mask":
        write_image(folder / "mask.png", np.zeros((40, 40)), "uint8")
        return "mask.png"
    if kind == "corrupt image":
        (folder / "007.png").write_bytes(b"this is not a png")
        return "007.png"
    if kind == "truncated image":
        data = (folder / "008.png").read_bytes()
        (folder / "008.png").write_bytes(data[: len(data) // 2])
        return "008.png"
    if kind == "nan image":
        for k in range(12):
            (folder / f"{k + 1:03d}.png").rename(folder / f"{k + 1:03d}.exr")
        (folder / "filenames.txt").write_text("\n".join(f"{k + 1:03d}.exr" for k in range(12)))
        write_image(folder / "004.exr", np.full((40, 40, 3), np.nan), "float")
        return "004.exr"
    if kind == "too few images":
        (folder / "filenames.txt").write_text("001.png\n002.png\n")
        rows = (folder / "light_directions.txt").read_text().splitlines()[:2]
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        (folder / "light_intensities.txt").unlink()
        return str(folder.name)
    if kind == "underscore light":  # float() reads '1_0' as 10
        rows = (folder / "light_directions.txt").read_text().splitlines()
        rows[1] = "1_0 0 1"
        (folder / "light_directions.txt").write_text("\n".join(rows) + "\n")
        return "light_directions.txt"
    if kind in ("text gt", "cell gt"):
        import scipy.io

        value = "x" if kind == "text gt" else np.array([np.zeros(2), np.zeros(3)], dtype=object)
        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": value})
        return "Normal_gt.mat"
    if kind == "listed broken link":
        (folder / "filenames.txt").write_text("\n".join(f"{k + 1:03d}.png" for k in range(12)) + "\n")
        (folder / "003.png").unlink()
        os.symlink(folder / "gone.png", folder / "003.png")
        return "003.png: listed in filenames.txt but is a broken link"
    if kind in ("listed link loop", "listed link to a device"):  # each was "a broken link" (helper-170)
        (folder / "filenames.txt").write_text("\n".join(f"{k + 1:03d}.png" for k in range(12)) + "\n")
        (folder / "003.png").unlink()
        if kind == "listed link loop":
            os.symlink(folder / "loop.png", folder / "003.png")
            os.symlink(folder / "003.png", folder / "loop.png")
            return "003.png: listed in filenames.txt but is a loop of symbolic links"
        os.symlink("/dev/null", folder / "003.png")
        return "003.png: listed in filenames.txt but is a link to /dev/null, which is a device, not a regular file"
    raise ValueError(kind)


BAD = ["missing image", "count mismatch", "malformed light", "nan light", "zero-length light", "short light row",
       "bad intensity", "image size", "mask size", "gt size", "empty mask", "corrupt image", "truncated image",
       "nan image", "too few images", "tiny intensity", "huge intensity", "coplanar lights", "black images",
       "listed folder", "mask folder", "underscore light", "text gt", "cell gt", "listed broken link",
       "listed link loop", "listed link to a device"]


@pytest.mark.parametrize("kind", BAD)
def test_bad_input(kind, capture, tmp_path):
    before = {p.name: p.read_bytes() for p in capture.iterdir()}
    culprit = _break(kind, capture)
    damaged = {p.name: p.read_bytes() if p.is_file() else None for p in capture.iterdir()}
    out = tmp_path / "out"
    proc = cli("normals", capture, "--method", "l2", "--out", out)
    assert proc.returncode == 2, (kind, proc.stdout, proc.stderr)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, (kind, proc.stderr)
    assert culprit in lines[0], (kind, lines[0])
    assert "Traceback" not in proc.stderr
    assert not out.exists() or not any(out.iterdir())  # no partial output
    assert {p.name: p.read_bytes() if p.is_file() else None for p in capture.iterdir()} == damaged  # inputs untouched
    assert before  # (the fixture was a valid folder before _break)


def test_output_folder_not_writable(capture, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should be")
    proc = cli("normals", capture, "-m", "l2", "--out", blocker / "out")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "out" in proc.stderr
    assert blocker.read_text() == "a file where a folder should be"


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores directory permissions")
def test_output_folder_read_only(capture, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        proc = cli("normals", capture, "-m", "l2", "--out", ro / "out")
        assert proc.returncode == 2 and "not writable" in proc.stderr
    finally:
        ro.chmod(0o700)


def test_missing_lights_point_at_psctl_lights_output_beside(tmp_path):
    """light_directions.txt missing where psctl lights (or calibrate) wrote one into PATH/psctl:
    the error says it is never read from there and how to use it (helper-159)."""
    import shutil

    from psctl.api import run_normals
    from psctl.errors import PsctlError

    write_capture(tmp_path / "c", n=6, size=24)
    (tmp_path / "c" / "psctl").mkdir()
    shutil.move(tmp_path / "c" / "light_directions.txt", tmp_path / "c" / "psctl" / "light_directions.txt")
    for method in ("l2", "ps-fcn"):
        with pytest.raises(PsctlError) as e:
            run_normals(tmp_path / "c", method=method, out=tmp_path / "o")
        assert e.value.path == str(tmp_path / "c" / "light_directions.txt")
        assert e.value.message.endswith(f"({tmp_path / 'c' / 'psctl' / 'light_directions.txt'} is an output of psctl "
                                        f"lights or calibrate, never read from there: copy it, and "
                                        f"light_intensities.txt where there is one, into {tmp_path / 'c'} to use it)")
    assert not (tmp_path / "o").exists()


def test_replaced_notes_name_only_psctl_commands_lists(tmp_path):
    """A stray .psctl-foo (a backup, say) names no psctl command; psctl lights' list does (helper-161)."""
    from psctl.io.atomic import replaced_notes

    (tmp_path / "depth.png").write_bytes(b"x")
    (tmp_path / ".psctl-foo").write_text("depth.png\n")
    assert replaced_notes(tmp_path, ["depth.png"], "depth") == [
        f"outputs: replaced depth.png in {tmp_path}, which no earlier psctl depth run there had listed"]
    (tmp_path / ".psctl-lights").write_text("depth.png\n/etc/passwd\n")
    assert replaced_notes(tmp_path, ["depth.png"], "depth") == [
        f"outputs: replaced depth.png in {tmp_path}, written there by an earlier psctl lights run"]


def test_a_read_only_parent_is_the_folder_named(tmp_path, monkeypatch):
    """A folder still to be made in a read-only one: the read-only one is named (as root, whom
    permissions do not stop, os.access is what says so here)."""
    import psctl.io.atomic as atomic
    from psctl.errors import PsctlError

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(atomic.os, "access", lambda p, mode: False if os.fspath(p) == str(ro) else real(p, mode))
    with pytest.raises(PsctlError) as e:
        atomic.check_output_dir(ro / "psctl" / "deeper")
    assert e.value.path == str(ro / "psctl" / "deeper") and e.value.message == f"cannot create output folder: {ro} is not writable"
    with pytest.raises(PsctlError) as e:
        atomic.check_output_dir(ro)
    assert e.value.message == "output folder is not writable"


@pytest.mark.parametrize("args,needle", [
    (["normals", "/nonexistent/folderPNG"], "does not exist"),
    (["normals", "{capture}", "--format", "png16,tiff"], "--format"),
    (["normals", "{capture}", "--method", "magic"], "unknown --method 'magic'"),
    (["info", "{capture}/001.png"], "not a folder"),
])
def test_other_user_errors(args, needle, capture):
    proc = cli(*[a.replace("{capture}", str(capture)) for a in args])
    assert proc.returncode == 2 and needle in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_an_unknown_option_suggests_only_options_spelt_like_it(capture):
    """click compares option names with their dashes, which alone made '--bogus' suggest '--out'."""
    proc = cli("normals", capture, "--bogus")
    assert proc.returncode == 2 and "No such option: --bogus" in proc.stderr and "--out" not in proc.stderr
    proc = cli("normals", capture, "--methd", "l2")
    assert proc.returncode == 2 and "--method" in proc.stderr and "--seed" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    proc = cli("normals", capture, "--hepl")  # --help is an option too (a review: it was no longer suggested)
    assert proc.returncode == 2 and "Possible options: --help)" in proc.stderr, proc.stderr


@pytest.mark.parametrize("args,needle", [
    (["normals", "{capture}", "-m", "l2", "-n", "5", "--seed", "-1"], "--seed must be 0 or more"),
    (["lights", "{capture}", "-n", "5", "--seed", "-1"], "--seed must be 0 or more"),
    (["normals", "{capture}", "-m", "l2", "--device", "gpu"], "unknown --device 'gpu'"),
])
def test_bad_options_before_any_work(args, needle, capture, tmp_path):
    proc = cli(*[a.replace("{capture}", str(capture)) for a in args], "--out", tmp_path / "o")
    assert proc.returncode == 2 and needle in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


def test_messages_show_brackets_as_they_are(tmp_path):
    folder = tmp_path / "cap[red]x"
    write_capture(folder)
    (folder / "light_directions.txt").write_text("0 0 1\n")  # one row for 12 images
    proc = cli("normals", folder, "-m", "l2")
    assert proc.returncode == 2 and "cap[red]x/light_directions.txt" in proc.stderr, proc.stderr
    (folder / "light_directions.txt").unlink()
    r = cli("normals", folder, "-m", "l2", "--out", tmp_path / "o")
    assert r.returncode == 2 and "cap[red]x" in r.stderr


def test_notes_for_an_image_selection_that_does_nothing(capture, tmp_path):
    r = json.loads(cli("normals", capture, "-m", "l2", "-n", "100", "--out", tmp_path / "o", "--json",
                         check=True).stdout)
    assert r["n_images"] == 12 and any("all 12 used" in n for n in r["notes"])
    r = json.loads(cli("normals", capture, "-m", "l2", "--seed", "3", "--out", tmp_path / "o", "--json",
                         check=True).stdout)
    assert any("--seed is unused" in n for n in r["notes"])


def test_synth_never_writes_into_a_capture_or_other_data(capture, tmp_path):
    before = sorted(os.listdir(capture))
    proc = cli("synth", capture, "--preset", "blobby", "--size", "16", "--lights", "4", "-k", "1")
    assert proc.returncode == 2 and "not a psctl synth folder" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(os.listdir(capture)) == before
    out = tmp_path / "set"
    for _ in range(2):  # its own folder again is fine
        cli("synth", out, "--preset", "blobby", "--size", "16", "--lights", "4", "-k", "1", check=True)


def test_uncalibrated_folder_with_l2(capture, tmp_path):
    (capture / "light_directions.txt").unlink()
    proc = cli("normals", capture, "-m", "l2", "--out", tmp_path / "o")
    assert proc.returncode == 2 and "light_directions.txt" in proc.stderr


def test_eval_checks_every_object_before_writing(tmp_path):
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=1)
    write_capture(tmp_path / "root" / "bPNG", n=6, seed=2, gt="none")
    out = tmp_path / "out"
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out)
    assert proc.returncode == 2 and "bPNG" in proc.stderr and "ground truth" in proc.stderr
    assert not out.exists()


def test_eval_out_uses_object_names(tmp_path):
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=1)
    cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", tmp_path / "out",
          "--quiet", check=True)
    assert sorted(os.listdir(tmp_path / "out")) == [".psctl-eval", "a", "eval.json", "eval.png"]
    assert "normal.png" in os.listdir(tmp_path / "out" / "a")


def test_eval_shows_published_numbers_only_beside_folders_named_as_diligent(tmp_path):
    """`psctl eval --root R` defaults to --benchmark diligent; a folder "cat" of one's own data is
    not DiLiGenT's catPNG and gets no paper number (it got DiLiGenT's cat's before)."""
    write_capture(tmp_path / "root" / "ballPNG", n=6, seed=0)
    write_capture(tmp_path / "root" / "cat", n=6, seed=1)
    proc = cli("eval", "--root", tmp_path / "root", "-m", "l2", "--json", "--quiet", check=True)
    r = json.loads(proc.stdout)
    assert set(r["paper"]) == {"ball"} and r["paper_method"] == "l2"
    assert any("paper: cat not in folders named as DiLiGenT's (catPNG)" in n for n in r["notes"]), r["notes"]
    text = cli("eval", "--root", tmp_path / "root", "-m", "l2", check=True).stdout
    assert "catPNG" in " ".join(text.split())
    (tmp_path / "root" / "ballPNG").rename(tmp_path / "root" / "ball")
    r = json.loads(cli("eval", "--root", tmp_path / "root", "-m", "l2", "--json", "--quiet", check=True).stdout)
    assert r["paper"] == {} and r["paper_method"] is None and any("ball, cat not in" in n for n in r["notes"])
    assert r["benchmark"] == "diligent"  # (named as DiLiGenT's objects: the note says why no paper number)
    # objects none of which is named as one of DiLiGenT's: read as --benchmark folder (helper-169: the
    # table was headed "diligent: ROOT" over one's own objects)
    (tmp_path / "root" / "ball").rename(tmp_path / "root" / "mug")
    (tmp_path / "root" / "cat").rename(tmp_path / "root" / "vase")
    r = json.loads(cli("eval", "--root", tmp_path / "root", "-m", "l2", "--json", "--quiet", check=True).stdout)
    assert r["benchmark"] == "folder" and r["paper"] == {} and not any("DiLiGenT" in n for n in r["notes"])
    assert cli("eval", "--root", tmp_path / "root", "-m", "l2", check=True).stdout.startswith("folder: ")


def test_eval_out_writes_the_sheet_and_the_table(tmp_path):
    from psctl.io.capture import load_ground_truth, load_mask, open_capture
    from psctl.io.report import object_panel

    write_capture(tmp_path / "root" / "aPNG", n=6, seed=0)
    write_capture(tmp_path / "root" / "bPNG", n=6, seed=1, size=56)
    out = tmp_path / "out"
    r = json.loads(psctl("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out,
                         "--json", "--quiet", check=True).stdout)
    assert r["outputs"] == {"eval.png": str(out / "eval.png"), "eval.json": str(out / "eval.json")}
    saved = json.loads((out / "eval.json").read_text())
    assert [o["mae"] for o in saved["objects"]] == [o["mae"] for o in r["objects"]] and saved["mean_mae"] == r["mean_mae"]
    sheet, info = read_image(out / "eval.png")
    assert info.bits == 8 and sheet.shape[2] == 3
    # each object's maps, rebuilt from its own normal.png and ground truth, where the layout puts them
    # (12 px gaps; a title line, then a name line and an MAE line of 20 px each above the 160 px maps)
    x = 12
    for name in ("a", "b"):
        cap = open_capture(tmp_path / "root" / f"{name}PNG")
        mask, normals = load_mask(cap), read_normal_map(out / name / "normal.png")
        error = np.zeros(mask.shape, np.float32)
        error[mask] = angular_error(normals, load_ground_truth(cap), mask)
        p = object_panel(name, 0.0, normals, error, mask)
        h, w = p["normals"].shape[:2]
        np.testing.assert_allclose(sheet[84:84 + h, x:x + w], p["normals"], atol=1.5 / 255)
        np.testing.assert_allclose(sheet[84 + h + 4:84 + 2 * h + 4, x:x + w], p["error"], atol=1.5 / 255)
        assert w >= 11 * 12  # wider than its name and "MAE 12.34°": the column is the maps' width
        x += w + 12
    (out / "eval.png").write_bytes(b"an earlier run's")  # replaced, not kept
    r2 = psctl("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out, "--quiet",
               check=True)
    assert "eval.png" in r2.stdout and sorted(os.listdir(out)) == [".psctl-eval", "a", "b", "eval.json", "eval.png"]
    assert np.array_equal(read_image(out / "eval.png")[0], sheet)


def test_eval_out_names_an_earlier_runs_objects(tmp_path):
    write_capture(tmp_path / "r2" / "aPNG", n=6, seed=0)
    write_capture(tmp_path / "r2" / "bPNG", n=6, seed=1)
    write_capture(tmp_path / "r1" / "aPNG", n=6, seed=0)
    out = tmp_path / "out"
    r = json.loads(cli("eval", "--benchmark", "folder", "--root", tmp_path / "r2", "-m", "l2", "--out", out,
                         "--json", "--quiet", check=True).stdout)
    assert r["notes"] == []
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "r1", "-m", "l2", "--out", out, "--quiet",
                 check=True)
    assert "also holds b from an earlier run" in " ".join(proc.stdout.split())
    assert json.loads((out / "eval.json").read_text())["notes"][0].startswith("outputs:")
    assert sorted(os.listdir(out)) == [".psctl-eval", "a", "b", "eval.json", "eval.png"]  # left as they are


def test_eval_out_says_on_the_terminal_which_files_of_the_users_it_replaced(tmp_path):
    """A user's own eval.png in OUT, or normal.png in OUT/<object>, is replaced with a note printed
    on the terminal (the object's note was only in eval.json); psctl's own from an earlier run
    are replaced silently."""
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=0)
    out = tmp_path / "out"
    (out / "a").mkdir(parents=True)
    (out / "eval.png").write_text("mine")
    (out / "a" / "normal.png").write_text("mine too")
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out, check=True)
    text = " ".join(proc.stdout.split())
    assert f"replaced eval.png in {out}, which no earlier psctl eval run there had listed" in text, text
    assert f"replaced normal.png in {out / 'a'}" in text
    again = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out, check=True)
    assert "replaced" not in again.stdout


def test_eval_out_inside_the_root_runs_twice(tmp_path):
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=0)
    for _ in range(2):  # the second time, root/results (eval.png, a/) must not look like an object
        r = json.loads(cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out",
                             tmp_path / "root" / "results", "--json", "--quiet", check=True).stdout)
        assert [o["name"] for o in r["objects"]] == ["a"]
    r = cli("normals", tmp_path / "root" / "aPNG", "-m", "l2", "--out", tmp_path / "root" / "results", "--quiet")
    assert r.returncode == 0, r.stderr  # an eval output folder is no capture


def test_eval_out_refuses_a_capture_and_is_atomic_with_the_sheet(tmp_path, monkeypatch):
    from psctl.errors import PsctlError
    from psctl.eval import run_benchmark

    write_capture(tmp_path / "root" / "aPNG", n=6, seed=0)
    write_capture(tmp_path / "cap", n=6, seed=1)
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", tmp_path / "cap")
    assert proc.returncode == 2 and "holds a capture" in proc.stderr and len(proc.stderr.splitlines()) == 1
    assert not (tmp_path / "cap" / "eval.png").exists() and not (tmp_path / "cap" / "a").exists()

    def broken(*args, **kwargs):
        raise PsctlError(None, "no sheet")

    monkeypatch.setattr("psctl.io.report.benchmark_sheet", broken)
    with pytest.raises(PsctlError, match="no sheet"):
        run_benchmark("folder", tmp_path / "root", "l2", out=tmp_path / "new")
    assert not (tmp_path / "new").exists()  # nor the object's folder
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "eval.png").write_bytes(b"kept")
    with pytest.raises(PsctlError, match="no sheet"):
        run_benchmark("folder", tmp_path / "root", "l2", out=tmp_path / "old")
    assert sorted(os.listdir(tmp_path / "old")) == ["eval.png"] and (tmp_path / "old" / "eval.png").read_bytes() == b"kept"


def test_outputs_never_overwrite_inputs(capture):
    write_image(capture / "normal.png", np.zeros((40, 40, 3)), "uint16")  # a user's file named like an output
    (capture / "Normal_gt.mat").unlink()  # so normal.png is this folder's ground truth
    before = (capture / "normal.png").read_bytes()
    proc = cli("normals", capture, "-m", "l2", "--out", capture)
    assert proc.returncode == 2 and "capture folder" in proc.stderr and "input" in proc.stderr
    assert (capture / "normal.png").read_bytes() == before
    # and a run on a folder without ground truth never writes a normal.png that the next run
    # would read as its ground truth
    (capture / "normal.png").unlink()
    proc = cli("normals", capture, "-m", "l2", "--out", capture)
    assert proc.returncode == 2 and not (capture / "normal.png").exists()


def test_failed_write_leaves_no_output_folder(tmp_path):
    from psctl.io.atomic import staged_outputs

    out = tmp_path / "new" / "out"
    with pytest.raises(RuntimeError):
        with staged_outputs(out) as stage:
            (stage / "half.png").write_bytes(b"x")
            raise RuntimeError("disk full")
    assert not out.exists()


def test_a_folder_in_the_way_stops_the_whole_output(capture, tmp_path):
    out = tmp_path / "out"
    (out / "normal.exr").mkdir(parents=True)  # where a file will go
    proc = cli("normals", capture, "-m", "l2", "--out", out)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "normal.exr" in proc.stderr
    assert sorted(os.listdir(out)) == ["normal.exr"]  # nothing else written, no staging folder left


def test_failed_rename_puts_everything_back(tmp_path, monkeypatch):
    from psctl.errors import PsctlError
    from psctl.io.atomic import staged_outputs

    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    (out / "stale.txt").write_text("old stale")
    real = os.replace

    def flaky(src, dst):
        if Path(dst).name == "b.txt" and ".psctl-staging" in str(src):
            raise OSError(28, "No space left on device")
        real(src, dst)

    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(PsctlError, match="nothing was changed"):
        with staged_outputs(out, replaces=("a.txt", "b.txt", "stale.txt")) as stage:
            (stage / "a.txt").write_text("new a")
            (stage / "b.txt").write_text("new b")
    assert sorted(os.listdir(out)) == ["a.txt", "stale.txt"]
    assert (out / "a.txt").read_text() == "old a" and (out / "stale.txt").read_text() == "old stale"


@pytest.mark.parametrize("failure", ["putting back fails too", "ctrl-c"])
def test_earlier_outputs_are_never_lost(tmp_path, monkeypatch, failure):
    """A commit that fails and cannot put the earlier files back leaves them in the staging
    folder and says where; Ctrl-C between two renames puts everything back."""
    from psctl.errors import PsctlError
    from psctl.io.atomic import staged_outputs

    out = tmp_path / "out"
    out.mkdir()
    for name in ("a.txt", "b.txt"):
        (out / name).write_text(f"old {name}")
    real = os.replace
    interrupted = []

    def flaky(src, dst):
        if Path(dst).name == "b.txt" and Path(dst).parent == out and ".psctl-staging" in str(src):
            if failure == "ctrl-c" and not interrupted:
                interrupted.append(1)  # once: the rollback's own renames go through
                raise KeyboardInterrupt
            if failure != "ctrl-c":
                raise OSError(13, "Permission denied")
        if failure != "ctrl-c" and Path(src).parent.name == ".replaced":
            raise OSError(13, "Permission denied")  # and the earlier files cannot come back
        real(src, dst)

    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(KeyboardInterrupt if failure == "ctrl-c" else PsctlError) as err:
        with staged_outputs(out) as stage:
            (stage / "a.txt").write_text("new a")
            (stage / "b.txt").write_text("new b")
    monkeypatch.setattr(os, "replace", real)
    if failure == "ctrl-c":
        assert sorted(os.listdir(out)) == ["a.txt", "b.txt"]
        assert [(out / n).read_text() for n in ("a.txt", "b.txt")] == ["old a.txt", "old b.txt"]
    else:
        kept = Path(err.value.path)
        assert "could not be put back" in str(err.value) and kept.parent.parent == out
        assert sorted((kept / n).read_text() for n in os.listdir(kept)) == ["old a.txt", "old b.txt"]


def test_two_runs_into_one_folder_at_once_leave_one_runs_outputs(capture, tmp_path, monkeypatch):
    """A psctl normals that finishes into the folder while another is still at work there: the
    later commit reads the earlier run's list then (under the folder's lock), so no normal.exr of
    the other object is left beside its normal.png (an interruption audit: 10 of 20 trials); and
    a psctl depth whose normal map is replaced meanwhile writes nothing."""
    import psctl.io.normals as io_normals
    from psctl.api import run_normals
    from psctl.depth import run_depth
    from psctl.errors import PsctlError

    other = tmp_path / "otherPNG"
    write_capture(other, n=6, size=32, seed=5)
    out = tmp_path / "out"
    real = io_normals.write_normal_map
    state = {"done": False}

    def meanwhile(*args, **kwargs):  # the first run writes its files; the other one finishes now
        if not state["done"]:
            state["done"] = True
            run_normals(other, method="l2", out=out, formats=["png16", "exr"])
        return real(*args, **kwargs)

    monkeypatch.setattr(io_normals, "write_normal_map", meanwhile)
    r = run_normals(capture, method="l2", out=out, formats=["png16", "npy"])
    assert state["done"]
    assert sorted(os.listdir(out)) == [".psctl-normals", "error.png", "normal.npy", "normal.png", "report.json"]
    assert json.loads((out / "report.json").read_text())["object"] == r["object"]

    # psctl depth reads out/normal.npy; a psctl normals replaces it before depth's files are in place
    monkeypatch.setattr(io_normals, "write_normal_map", real)
    import psctl.io.mesh as io_mesh

    real_ply = io_mesh.write_ply

    def replaced(*args, **kwargs):
        run_normals(capture, method="l2", out=out, formats=["png16", "npy"], n_images=4)
        return real_ply(*args, **kwargs)

    monkeypatch.setattr(io_mesh, "write_ply", replaced)
    with pytest.raises(PsctlError, match="changed while this run read it"):
        run_depth(capture, normals=out / "normal.npy", out=out)
    assert not any(n.startswith(("depth", "mesh", "shading", ".psctl-depth", ".psctl-staging")) for n in os.listdir(out))


def test_a_killed_runs_working_folder_goes_with_the_next_run(capture, tmp_path):
    """kill -9 leaves a hidden staging folder; the next run into the folder removes it when its
    process is gone, unless it holds earlier outputs set aside by a commit; folders of running
    processes, of other machines and of older psctl versions stay."""
    from psctl.api import run_normals
    from psctl.io.atomic import _machine

    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True).stdout)
    host = _machine()
    out = tmp_path / "out"
    left = out / f".psctl-staging.{host}-{dead}-a1"
    left.mkdir(parents=True)
    (left / "normal.png").write_text("half written")
    aside = out / f".psctl-staging.{host}-{dead}-b2" / ".replaced"
    aside.mkdir(parents=True)
    (aside / "normal.png").write_text("an earlier run's")
    stay = [out / f".psctl-staging.{host}-{os.getpid()}-c3", out / f".psctl-staging.elsewhere-{dead}-d4",
            out / ".psctl-staging.e5"]
    for f in stay:
        f.mkdir()
    r = run_normals(capture, method="l2", out=out)
    assert not left.exists() and (aside / "normal.png").read_text() == "an earlier run's"
    assert any(n.startswith(f"outputs: {aside} holds files of an earlier run") for n in r["notes"])  # told where
    assert all(f.is_dir() for f in stay) and (out / "normal.png").is_file()


def _hold_lock(folder: Path, seconds: float, marker: Path) -> subprocess.Popen:
    """Another process holding ``folder``'s flock for ``seconds``; it writes ``marker`` just
    before letting go. Returns once the lock is held."""
    script = ("import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDONLY); fcntl.flock(fd, fcntl.LOCK_EX)\n"
              "print('locked', flush=True); time.sleep(float(sys.argv[2])); open(sys.argv[3], 'w').close()")
    holder = subprocess.Popen([sys.executable, "-c", script, str(folder), str(seconds), str(marker)],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    return holder


def test_an_output_folder_that_is_a_link_loop_is_one_line(capture, tmp_path):
    """--out naming a symbolic link to itself: one line and exit 2 for normals, depth and eval
    (Path.resolve raised RuntimeError in the capture and root checks)."""
    loop = tmp_path / "loop"
    loop.symlink_to("loop")
    write_capture(tmp_path / "root" / "aPNG", n=6, size=24)
    cli("normals", capture, "-m", "l2", "-o", tmp_path / "n", check=True)
    for args in (("normals", capture, "-m", "l2", "-o", loop), ("normals", capture, "-m", "l2", "-o", loop / "sub"),
                 ("depth", capture, "--normals", tmp_path / "n" / "normal.exr", "-o", loop),
                 ("eval", "-b", "folder", "--root", tmp_path / "root", "-m", "l2", "-o", loop)):
        proc = cli(*args)
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "loop" in proc.stderr, args


def test_outputs_move_in_only_while_the_folder_is_not_locked(capture, tmp_path, monkeypatch, capsys):
    """Two commits into a folder take turns: a run whose files are ready waits for another
    process's flock on the folder; a lock held past LOCK_WAIT is none of psctl's (flock OUT cmd
    around psctl), and the run goes on without it and says so; Ctrl-C stops a run that waits."""
    import signal

    import psctl.io.atomic as atomic
    from psctl.api import run_normals

    out = tmp_path / "out"
    out.mkdir()
    holder = _hold_lock(out, 2.0, tmp_path / "released")
    run_normals(capture, method="l2", out=out)
    assert (tmp_path / "released").exists() and (out / "normal.png").is_file()  # it waited for the lock
    holder.wait()
    from psctl.eval import run_benchmark  # psctl eval --out's batch too

    write_capture(tmp_path / "root" / "aPNG", n=6, size=24)
    (tmp_path / "bench").mkdir()
    holder = _hold_lock(tmp_path / "bench", 2.0, tmp_path / "released1")
    run_benchmark("folder", tmp_path / "root", method="l2", out=tmp_path / "bench")
    assert (tmp_path / "released1").exists() and (tmp_path / "bench" / "eval.png").is_file()
    holder.wait()

    monkeypatch.setattr(atomic, "LOCK_WAIT", 0.5)
    holder = _hold_lock(out, 30.0, tmp_path / "released2")
    try:
        (out / "normal.png").unlink()
        run_normals(capture, method="l2", out=out)
        assert (out / "normal.png").is_file() and not (tmp_path / "released2").exists()
        assert "still locked after 0.5 s" in capsys.readouterr().err
        # the command line, waiting (it says so after 2 s), stops on Ctrl-C, and writes nothing
        (out / "normal.png").unlink()
        proc = subprocess.Popen([sys.executable, "-m", "psctl.cli", "normals", str(capture), "-m", "l2", "-o", str(out)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                # a terminal's Ctrl-C, also when this test run is a background job
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        assert "waiting for" in proc.stderr.readline()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 130 and not (out / "normal.png").exists()
        assert not [n for n in os.listdir(out) if n.startswith(".psctl-staging")]
    finally:
        holder.kill()


def test_a_folder_holds_one_runs_outputs(capture, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    cli("normals", capture, "-m", "l2", "--out", out, "--format", "png16,exr,npy", check=True)
    (capture / "Normal_gt.mat").unlink()
    r = json.loads(cli("normals", capture, "-m", "l2", "--out", out, "--format", "png16", "--json",
                         check=True).stdout)
    # no old error map or EXR beside the new normals; the user's file stays; the report is this run's
    assert sorted(os.listdir(out)) == [".psctl-normals", "normal.png", "notes.txt", "report.json"]
    assert any("removed error.png, normal.exr, normal.npy" in n for n in r["notes"]), r["notes"]
    saved = json.loads((out / "report.json").read_text())
    assert saved["mae"] is None and saved["method"] == "l2" and saved["notes"] == r["notes"]
    # files psctl normals did not write there are never removed, even with its names
    (out / ".psctl-normals").unlink()
    write_image(out / "error.png", np.zeros((4, 4)), "uint8")
    (out / "normal.exr").mkdir()  # in the way: refused before any work, not after it
    proc = cli("normals", capture, "-m", "l2", "--out", out, "--format", "exr")
    assert proc.returncode == 2 and "normal.exr: is in the way of an output file" in proc.stderr, proc.stderr
    (out / "normal.exr").rmdir()
    r = json.loads(cli("normals", capture, "-m", "l2", "--out", out, "--format", "exr", "--json",
                         check=True).stdout)
    assert sorted(os.listdir(out)) == [".psctl-normals", "error.png", "normal.exr", "normal.png", "notes.txt",
                                       "report.json"]
    # a file of the same name that no listed run wrote is replaced with a note, never silently
    assert any("replaced report.json" in n for n in r["notes"]), r["notes"]
    r = json.loads(cli("normals", capture, "-m", "l2", "--out", out, "--format", "exr", "--json",
                         check=True).stdout)
    assert not any("replaced" in n for n in r["notes"]), r["notes"]  # now listed: psctl's own


def test_outputs_never_go_into_another_capture(capture, tmp_path):
    other = tmp_path / "otherPNG"
    write_capture(other, gt="png")  # its ground truth is Normal_gt.png; a normal.png would count too
    before = sorted(os.listdir(other))
    for cmd in (["normals", capture, "-m", "l2"], ["lights", capture]):
        proc = cli(*cmd, "--out", other)
        assert proc.returncode == 2 and "holds a capture" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(os.listdir(other)) == before


def test_eval_out_is_all_or_nothing(tmp_path):
    for k, name in enumerate(("aPNG", "bPNG", "cPNG")):
        write_capture(tmp_path / "root" / name, n=6, seed=k)
    data = (tmp_path / "root" / "cPNG" / "003.png").read_bytes()
    (tmp_path / "root" / "cPNG" / "003.png").write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out)
    assert proc.returncode == 2 and "003.png" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()  # a and b were done, and are not written either
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", out)
    assert proc.returncode == 2 and sorted(os.listdir(out)) == ["keep.txt"]


def test_eval_out_may_not_be_the_root(tmp_path):
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=1)
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--out", tmp_path / "root")
    assert proc.returncode == 2 and "benchmark root" in proc.stderr
    assert sorted(os.listdir(tmp_path / "root")) == ["aPNG"]


def test_eval_refuses_two_objects_of_the_same_name(tmp_path):
    write_capture(tmp_path / "root" / "cat", n=6, seed=1)
    write_capture(tmp_path / "root" / "catPNG", n=6, seed=2)
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2")
    assert proc.returncode == 2 and "cat, catPNG" in proc.stderr and "Traceback" not in proc.stderr


def test_ensemble_command_and_auto(capture, tmp_path):
    """--method ensemble (and auto with both networks installed) averages PS-FCN and PS-FCN+N;
    --weights with it, or a missing network, is one line and exit 2 with nothing written."""
    import torch

    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    wdir = tmp_path / "w"
    wdir.mkdir()
    env = {"PSCTL_WEIGHTS": str(wdir)}
    torch.manual_seed(0)
    save_weights(wdir / "ps_fcn.pt", PSFCN(), {"method": "ps-fcn", "train_images": 32})
    proc = cli("normals", capture, "-m", "ensemble", "--out", tmp_path / "x", env=env)
    assert proc.returncode == 2 and "ps-fcn-n" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()
    assert json.loads(cli("normals", capture, "--out", tmp_path / "a1", "--json", env=env, check=True).stdout)[
        "method"] == "ps-fcn"
    torch.manual_seed(1)
    save_weights(wdir / "ps_fcn_n.pt", PSFCN(), {"method": "ps-fcn-n", "train_images": 32})
    r = json.loads(cli("normals", capture, "--out", tmp_path / "a2", "--json", env=env, check=True).stdout)
    assert r["method"] == "ensemble" and any(n.startswith("ensemble: the unit mean") for n in r["notes"])
    assert sum(n.startswith("ps-fcn") and "weights" in n for n in r["notes"]) == 2  # both files named
    for m in ("ps-fcn", "ps-fcn-n"):
        cli("normals", capture, "-m", m, "--out", tmp_path / m, "-q", env=env, check=True)
    mean = read_normal_map(tmp_path / "ps-fcn" / "normal.exr").astype(np.float64) + read_normal_map(
        tmp_path / "ps-fcn-n" / "normal.exr")
    m = np.linalg.norm(mean, axis=-1) > 0
    mean[m] /= np.linalg.norm(mean[m], axis=-1, keepdims=True)
    assert angular_error(read_normal_map(tmp_path / "a2" / "normal.exr"), mean, m).max() < 0.01
    proc = cli("normals", capture, "-m", "ensemble", "--weights", wdir / "ps_fcn.pt", "--out", tmp_path / "y", env=env)
    assert proc.returncode == 2 and "ensemble uses the installed" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "y").exists()
    # spread: the angle between the two networks' normals, a picture and the report's numbers
    n1, n2 = (read_normal_map(tmp_path / m / "normal.exr") for m in ("ps-fcn", "ps-fcn-n"))
    angle = angular_error(n1, n2, m)
    sp = r["spread"]
    assert sp["mean"] == pytest.approx(angle.mean(), abs=0.05) and sp["p90"] == pytest.approx(
        np.percentile(angle, 90), abs=0.05)
    assert r["mae"] is not None and sp["mae_top10"] is not None and sp["mae_rest"] is not None  # ground truth
    assert sorted(r["outputs"]) == ["error", "normal_exr", "normal_png", "report", "spread"]
    assert read_image(tmp_path / "a2" / "spread.png")[0].shape[2] == 3
    assert "spread" not in json.loads((tmp_path / "ps-fcn" / "report.json").read_text())
    assert not (tmp_path / "ps-fcn" / "spread.png").exists()
    # the same folder with one network: spread.png is the ensemble's, removed with a note
    r1 = json.loads(cli("normals", capture, "-m", "ps-fcn", "--out", tmp_path / "a2", "--json", env=env,
                          check=True).stdout)
    assert not (tmp_path / "a2" / "spread.png").exists() and any("removed spread.png" in n for n in r1["notes"])
    out = cli("normals", capture, "-m", "ensemble", "--out", tmp_path / "a3", env=env, check=True).stdout
    assert "spread (angle between the ensemble's networks)" in out
    from psctl.io.capture import holds_capture

    assert not holds_capture(tmp_path / "a3")  # psctl's own outputs, spread.png included, are no capture
    write_capture(tmp_path / "root" / "aPNG", n=6, seed=0)  # psctl eval --out: each object's spread too
    r = json.loads(cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "ensemble", "--out",
                         tmp_path / "ev", "--json", "--quiet", env=env, check=True).stdout)
    assert r["objects"][0]["spread"]["mean"] > 0 and (tmp_path / "ev" / "a" / "spread.png").is_file()
    assert read_image(tmp_path / "ev" / "eval.png")[0].shape[0] > 3 * 160  # three rows of maps


def test_train_command(tmp_path):
    """The CLI end to end, with and without the progress bar; bad method is a one-line error."""
    cfg = Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "run", "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    assert "finished" in proc.stderr and (tmp_path / "run" / "best.pt").is_file()
    proc = cli("train", "magic", "--config", cfg, "--out", tmp_path / "run2", "--quiet")
    assert proc.returncode == 2 and "magic" in proc.stderr and "Traceback" not in proc.stderr


def test_train_says_how_it_stopped(tmp_path, monkeypatch):
    """Ctrl-C checkpoints and exits 130, not 0 as a finished run; a stop before the first
    validation names no best.pt; --install says when it did not install; bad --max-minutes and
    a $PSCTL_WEIGHTS that is a file are refused before training."""
    import signal

    import psctl.train as T
    from psctl.checkpoint import Stop

    cfg = Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"
    for bad in ("-1", "nan", "0"):
        proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "r", "--max-minutes", bad)
        assert proc.returncode == 2 and "--max-minutes: must be a positive number" in proc.stderr, proc.stderr
    (tmp_path / "wfile").write_text("x")
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "r", "--install",
               env={"PSCTL_WEIGHTS": str(tmp_path / "wfile")})
    assert proc.returncode == 2 and "is not a folder: --install writes" in proc.stderr, proc.stderr
    assert not (tmp_path / "r").exists()
    stop = Stop()
    with stop:
        stop._handle(signal.SIGINT, None)
    assert stop.requested and stop.signal == signal.SIGINT
    stopped = {"samples": 8, "seconds": 1.0, "best_val": None, "finished": False, "signal": int(signal.SIGINT)}
    monkeypatch.setattr(T, "train", lambda *a, **k: stopped)
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "r", "-q", "--install", "--force",
               env={"PSCTL_WEIGHTS": str(tmp_path / "w")})
    assert proc.returncode == 130, proc.stderr
    assert "no validation yet, so no best.pt" in proc.stderr and "not installed: the run stopped" in proc.stderr
    assert "stopped by Ctrl-C (SIGINT) (continue with --resume" in " ".join(proc.stderr.split())
    for sig, exit_code, said in ((signal.SIGTERM, 143, "stopped by SIGTERM"), (None, 0, "stopped by --max-minutes")):
        stopped["signal"] = None if sig is None else int(sig)
        proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "r", "-q")
        assert proc.returncode == exit_code and said in proc.stderr, proc.stderr
    # a best validation whose best.pt was removed since: not named as the weights (a review's finding)
    stopped.update(signal=None, finished=True, best_val=12.5)
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "r", "-q")
    said = " ".join(proc.stderr.split())
    assert proc.returncode == 0 and f"12.50°, but {tmp_path / 'r' / 'best.pt'}, which held it, is missing" in said, said
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "best.pt").write_bytes(b"weights")
    said = " ".join(cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "r", "-q").stderr.split())
    assert f"12.50°; weights {tmp_path / 'r' / 'best.pt'}" in said, said


def test_train_install_refuses_to_replace_a_release_file(tmp_path):
    """--install never overwrites an installed file silently: refused before training, unless --force."""
    cfg = Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"
    wdir = tmp_path / "w"
    wdir.mkdir()
    (wdir / "ps_fcn.pt").write_bytes(b"release")
    env = {"PSCTL_WEIGHTS": str(wdir)}
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "run", "--install", "-q", env=env)
    assert proc.returncode == 2 and "already installed" in proc.stderr and "--force" in proc.stderr
    assert not (tmp_path / "run").exists() and (wdir / "ps_fcn.pt").read_bytes() == b"release"
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "run", "--force", "-q", env=env)
    assert proc.returncode == 2 and "--install" in proc.stderr
    proc = cli("train", "ps-fcn", "--config", cfg, "--out", tmp_path / "run", "--install", "--force", "-q", env=env)
    assert proc.returncode == 0, proc.stderr
    assert (wdir / "ps_fcn.pt").read_bytes() == (tmp_path / "run" / "best.pt").read_bytes()


def test_train_average(tmp_path):
    """psctl train METHOD --average A --average B --out RUN writes RUN/best.pt; misuse is one line, exit 2."""
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    cfg = Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"
    best, other = tmp_path / "best.pt", tmp_path / "other.pt"  # weights files of the method (psctl train's own: test_train.py)
    save_weights(best, PSFCN(), {"method": "ps-fcn", "train_images": 32})
    save_weights(other, PSFCN(), {"method": "ps-fcn", "train_images": 32})
    proc = cli("train", "ps-fcn", "--average", best, "--average", other, "--out", tmp_path / "avg")
    assert proc.returncode == 0 and "averaged 2 files" in proc.stderr and "validation" not in proc.stderr, proc.stderr
    proc = cli("train", "ps-fcn", "--average", best, "--average", other, "--config", cfg, "--out", tmp_path / "avg_val")
    assert proc.returncode == 0 and "synthetic validation" in proc.stderr, proc.stderr
    assert (tmp_path / "avg" / "best.pt").is_file()
    for args, says in ((("ps-fcn-n", "--average", best, "--average", other, "--out", tmp_path / "a2"), "holds ps-fcn weights, not ps-fcn-n"),
                       (("ps-fcn", "--average", best, "--average", other), "--out RUN"),
                       (("ps-fcn", "--average", best, "--average", best, "--out", tmp_path / "a6"), "is given twice"),
                       (("bogus", "--average", best, "--average", other, "--out", tmp_path / "a7"), "cannot train 'bogus'"),
                       (("ps-fcn", "--average", best, "--out", tmp_path / "a3"), "at least two"),
                       (("ps-fcn", "--average", best, "--average", tmp_path / "nope.pt", "--out", tmp_path / "a4"), "nope.pt"),
                       (("ps-fcn", "--average", best, "--average", other, "--out", tmp_path / "a5", "--install", "--force"),
                        "--install")):
        proc = cli("train", *args)
        assert proc.returncode == 2 and says in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not any((tmp_path / d).exists() for d in ("a2", "a3", "a4", "a5", "a6", "a7"))


def test_every_public_name_resolves():
    """psctl.__all__ lists only names that exist (psctl.load_capture did not: `from psctl import *` failed)."""
    import psctl

    for name in psctl.__all__:
        assert getattr(psctl, name) is not None, name


def test_root_group_exit_codes(capsys):
    """psctl's root group: 0 when a command finishes, 1 with one line for an abort (an EOFError
    inside a command), the command's own code for typer.Exit."""
    import typer

    from psctl.cli import _Root

    app = typer.Typer(cls=_Root, add_completion=False)

    @app.command()
    def ok() -> None:
        pass

    @app.command()
    def eof() -> None:
        raise EOFError

    @app.command()
    def three() -> None:
        raise typer.Exit(3)

    for name, code in (("ok", 0), ("eof", 1), ("three", 3)):
        with pytest.raises(SystemExit) as e:
            typer.main.get_command(app).main([name], prog_name="psctl")
        assert e.value.code == code, name
    err = capsys.readouterr().err
    assert "Aborted" in err and "Traceback" not in err


def test_paths_the_system_refuses_are_one_line_errors(capture, tmp_path):
    """An OSError (here: a name over 255 bytes) is the user's path, not a crash: one line naming
    it, exit code 2, nothing written."""
    long = "a" * 300
    for args in (["info", tmp_path / long], ["normals", capture, "-m", "l2", "-o", tmp_path / long / "out"],
                 ["normals", tmp_path / long, "-m", "l2"]):
        proc = cli(*args)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert proc.returncode == 2 and len(lines) == 1, (args, proc.stderr)
        assert "Traceback" not in proc.stderr and long in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [capture.name]


def test_eval_says_once_what_every_object_shares(tmp_path):
    """A note that changes what the table means (--images asked for more than there are) is one
    line for all the objects it concerns, not one per object, and not only in --json."""
    for name in ("a", "b"):
        write_capture(tmp_path / "root" / name, n=6, size=24)
    proc = cli("eval", "--benchmark", "folder", "--root", tmp_path / "root", "-m", "l2", "--images", "9", "-q")
    assert proc.returncode == 0, proc.stderr
    text = " ".join((proc.stdout + proc.stderr).split())
    assert text.count("every object: images: --images 9 asks for more than the 6 there are") == 1, text


def test_a_benchmark_root_says_what_it_leaves_out(tmp_path):
    """Subfolders that look meant as objects but hold no image, and a root's own images when
    objects.txt makes it a root, are named (info and eval), not silently skipped."""
    root = tmp_path / "root"
    write_capture(root / "a", n=4)
    (root / "b").mkdir()
    (root / "b" / "light_directions.txt").write_text((root / "a" / "light_directions.txt").read_text())
    (root / "notes").mkdir()  # nothing of a capture: no word
    (root / "notes" / "readme.txt").write_text("x")
    r = json.loads(cli("info", root, "--json").stdout)
    assert [o["object"] for o in r["objects"]] == ["a"]
    assert r["notes"] == ["objects: skipped b: holds capture files (lights, mask or ground truth) but no image"]
    assert "note: objects: skipped b" in cli("info", root).stdout
    e = json.loads(cli("eval", "--benchmark", "folder", "--root", root, "-m", "l2", "--json").stdout)
    assert e["notes"] == r["notes"]
    (root / "objects.txt").write_text("a\n")
    write_image(root / "001.png", np.zeros((8, 8, 3)), "uint8")
    r = json.loads(cli("info", root, "--json").stdout)
    assert r["notes"] == ["objects: 1 image in the root itself (001.png) not read: objects.txt makes it a "
                          "benchmark root of the folders it lists"]


def test_python_m_psctl_is_the_command(tmp_path: Path):
    """``python -m psctl``: the command where its script is not on PATH, named "psctl" in messages."""
    run = lambda *a: subprocess.run([sys.executable, "-m", "psctl", *a], capture_output=True, text=True,  # noqa: E731
                                    env={**os.environ, "COLUMNS": "100"})
    from psctl import __version__
    assert run("--version").stdout.strip() == f"psctl {__version__}"
    proc = run("normals", str(tmp_path / "missing"))
    assert proc.returncode == 2 and "missing" in proc.stderr and "Traceback" not in proc.stderr
    proc = run("info")
    assert proc.returncode == 2 and proc.stderr.startswith("psctl info: Missing argument")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a file size limit (RLIMIT_FSIZE) stands in for a full disk")
def test_a_full_disk_is_one_line_and_nothing_written(capture, tmp_path):
    """Writes that fail for want of room (here a file size limit, as a full disk or a quota): one
    line naming the output by its final name, exit 2, no output folder; a full stdout too."""
    import resource
    import signal

    def run(limit: int, *args: str, stdout=subprocess.PIPE) -> subprocess.CompletedProcess:
        def limited() -> None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG from write() instead of a kill
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

        return subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, args)], stdout=stdout,
                              stderr=subprocess.PIPE, text=True, preexec_fn=limited,
                              env={**os.environ, "COLUMNS": "200"})

    before = sorted(os.listdir(capture))
    for cmd, out, names in ((["normals", capture, "-m", "l2"], "n", ("normal", "error")),
                            (["depth", capture, "--normals", capture / "ok" / "normal.exr"], "d",
                             ("depth", "mesh", "shading"))):
        if cmd[0] == "depth":
            psctl("normals", capture, "-m", "l2", "--out", capture / "ok", "-q", check=True)
            before = sorted(os.listdir(capture))
        proc = run(2048, *cmd, "--out", tmp_path / out)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        line = proc.stderr.strip()
        assert len(line.splitlines()) == 1 and f"{tmp_path / out}/" in line and ".psctl-staging" not in line, line
        assert any(f"/{n}." in line for n in names) and ("cannot write" in line or "written incompletely" in line)
        assert not (tmp_path / out).exists() and sorted(os.listdir(capture)) == before
    with open(tmp_path / "info.txt", "w") as f:  # stdout on a full disk
        proc = run(0, "info", capture, stdout=f)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "cannot write the report to standard output (file too large)" in proc.stderr  # info writes no files
    assert "files were written" not in proc.stderr


def test_objects_txt_and_out_mistakes_say_what_they_are(tmp_path):
    """objects.txt listing the root itself or a file, a broken link as --out: one line each
    saying so (they read 'pass one object folder, or use psctl eval', 'missing' and 'File
    exists' before)."""
    root = tmp_path / "root"
    write_capture(root / "a", n=6, seed=0)
    for listed, words in ((".\na\n", "objects.txt: lists ., the root itself"),
                          ("a/..\n", "objects.txt: lists a/.., the root itself")):
        (root / "objects.txt").write_text(listed)
        proc = cli("eval", "--benchmark", "folder", "--root", root, "-m", "l2")
        assert proc.returncode == 2 and words in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    (root / "notes").write_text("x")
    (root / "objects.txt").write_text("notes\n")
    proc = cli("eval", "--benchmark", "folder", "--root", root, "-m", "l2")
    assert proc.returncode == 2 and "listed in objects.txt but is a file, not an object folder" in proc.stderr
    (root / "objects.txt").unlink()
    (tmp_path / "dl").symlink_to(tmp_path / "nowhere" / "x")
    for cmd in (["normals", root / "a", "-m", "l2"], ["eval", "--benchmark", "folder", "--root", root, "-m", "l2"]):
        proc = cli(*cmd, "--out", tmp_path / "dl")
        assert proc.returncode == 2 and "dl: is a broken link (to " in proc.stderr, proc.stderr
    assert (tmp_path / "dl").is_symlink() and not (tmp_path / "nowhere").exists()


def test_objects_txt_naming_the_root_by_its_absolute_path(tmp_path, monkeypatch):
    """objects.txt listing the root by an absolute path while --root is relative: the same one
    line (it was a ValueError traceback)."""
    root = tmp_path / "root"
    write_capture(root / "a", n=6, seed=0)
    (root / "objects.txt").write_text(f"{root}\n")
    monkeypatch.chdir(tmp_path)
    proc = cli("eval", "--benchmark", "folder", "--root", "root", "-m", "l2")
    assert proc.returncode == 2 and f"objects.txt: lists {root}, the root itself" in proc.stderr, proc.stderr


def test_average_refuses_training_options_and_bad_devices(tmp_path):
    """--average trains nothing: --max-minutes and --lcnet with it, or a --device that does not
    exist, are one line (they were accepted without a word); a folder as --weights says so."""
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights

    for name in ("a.pt", "b.pt"):
        save_weights(tmp_path / name, PSFCN(), {"method": "ps-fcn", "train_images": 8})
    base = ("train", "ps-fcn", "--average", tmp_path / "a.pt", "--average", tmp_path / "b.pt", "--out", tmp_path / "o")
    for extra, words in ((["--max-minutes", "1"], "--max-minutes: is for training; --average only averages\n"),
                         (["--lcnet", tmp_path / "a.pt"], "--lcnet: is for training"),
                         (["--device", "tpu"], "tpu")):
        proc = cli(*base, *extra)
        assert proc.returncode == 2 and words in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert not (tmp_path / "o").exists()
    proc = cli("normals", tmp_path, "-m", "ps-fcn", "--weights", tmp_path)
    assert proc.returncode == 2
    write_capture(tmp_path / "cap", n=6)
    proc = cli("normals", tmp_path / "cap", "-m", "ps-fcn", "--weights", tmp_path)
    assert proc.returncode == 2 and "is a folder, not a weights file" in proc.stderr, proc.stderr


def test_train_and_synth_names_in_any_case(tmp_path):
    """As normals' --method: PS-FCN, BLOBBY, DILIGENT, Mixed and Lambertian are ps-fcn, blobby,
    diligent, mixed and lambertian."""
    proc = cli("synth", tmp_path / "s", "--preset", "BLOBBY", "--light-dist", "DILIGENT", "--intensities", "Mixed",
               "--size", "32", "--lights", "8", "--materials", "1", "-q")
    assert proc.returncode == 0 and (tmp_path / "s" / "objects.txt").is_file(), proc.stderr
    from psctl.errors import PsctlError
    from psctl.refine import refine_config

    assert refine_config("Lambertian") == {"falloff": "lambertian"}
    with pytest.raises(PsctlError, match="--falloff must be shifted or lambertian, not 'lambert'"):
        refine_config("lambert")
    cfg = Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"
    proc = cli("train", "PS-FCN", "--config", cfg, "--out", tmp_path / "r", "-q")
    assert proc.returncode == 0 and json.loads((tmp_path / "r" / "state.json").read_text())["method"] == "ps-fcn"


def test_precision_flag_errors_are_one_line(capture, tmp_path):
    """--precision with a bad name, or fp16 on the CPU, is one line naming the problem, exit 2,
    nothing written; l2 (float64) notes it unused."""
    for value, msg in (("half", "unknown --precision 'half'"), ("fp16", "fp16 is for CUDA")):
        proc = cli("normals", capture, "-m", "ps-fcn-n", "--device", "cpu", "--precision", value,
                   "--out", tmp_path / "x")
        assert proc.returncode == 2 and msg in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()
    r = json.loads(cli("normals", capture, "-m", "l2", "--precision", "bf16", "--out", tmp_path / "l2", "--json",
                       check=True).stdout)
    assert r["precision"] == "float32" and any("unused" in n for n in r["notes"])
    # --device cuda with l2: a note too (it was taken without a word; a QA helper), and a bad name lists cuda:K
    from psctl.api import run_normals
    from psctl.errors import PsctlError

    r = run_normals(capture, method="l2", device="cuda", write=False)
    assert "device: l2 solves with NumPy on the CPU; --device cuda unused" in r["notes"]
    assert not any("device" in n for n in run_normals(capture, method="l2", device="cpu", write=False)["notes"])
    with pytest.raises(PsctlError, match=r"unknown --device 'gpu'; choose from auto, cpu, cuda or cuda:K"):
        run_normals(capture, method="l2", device="gpu", write=False)


def test_inputs_in_the_output_folder_under_an_output_name_are_refused(capture, tmp_path):
    """A file the run reads (--weights, --normals, --K, --lcnet) that sits in the output folder
    under one of the run's output names is refused before any work, never replaced (a review's
    fuzzing found each of these overwritten with a note)."""
    import hashlib
    import shutil

    from psctl.api import run_normals
    from psctl.depth import run_depth
    from psctl.errors import PsctlError
    from psctl.eval import run_benchmark
    from psctl.lights import run_lights

    out = tmp_path / "o"
    out.mkdir()
    weights = Path(__file__).resolve().parents[1] / "weights"
    run_normals(capture, "l2", out=tmp_path / "n")
    cases = [
        ("depth.png", tmp_path / "n" / "normal.png", lambda f: run_depth(capture, normals=f, out=out)),
        ("mesh.ply", None, lambda f: run_depth(capture, K=f, out=out)),
        ("report.json", weights / "ps_fcn.pt", lambda f: run_normals(capture, "ps-fcn", weights=f, out=out)),
        ("light_directions_estimated.txt", weights / "lcnet.pt",
         lambda f: run_normals(capture, "sdps", lcnet=f, out=out)),
        ("lights.png", weights / "lcnet.pt", lambda f: run_lights(capture, weights=f, out=out)),
        ("eval.json", weights / "ps_fcn.pt", lambda f: run_benchmark("folder", root=capture.parent, method="ps-fcn",
                                                                      weights=f, out=out)),
    ]
    for name, source, run in cases:
        f = out / name
        if source is None:
            f.write_text("1 0 16\n0 1 16\n0 0 1\n")
        else:
            shutil.copy(source, f)
        digest = hashlib.sha256(f.read_bytes()).hexdigest()
        with pytest.raises(PsctlError, match=f"{name}: is the --\\w+(-\\w+)? file this run reads"):
            run(f)
        assert hashlib.sha256(f.read_bytes()).hexdigest() == digest and sorted(os.listdir(out)) == [name]
        f.unlink()


def test_fuzzed_failures_are_one_line(capture, tmp_path, capsys, monkeypatch):
    """Cases a review's fuzzing found: images that overflow float32 once divided by a tiny
    intensity; ground truth of huge vectors (still directions); running out of memory; a report
    that cannot be printed (stdout on a full disk); a full disk under synth's Normal_gt.mat."""
    import warnings

    import typer

    from psctl.api import run_normals
    from psctl.cli import _user_errors
    from psctl.errors import PsctlError
    from psctl.io.images import write_image

    data = write_capture(tmp_path / "huge", n=6)
    for k, img in enumerate(data["images"]):  # float images of huge values: allowed as they are
        (tmp_path / "huge" / f"{k + 1:03d}.png").unlink()
        write_image(tmp_path / "huge" / f"{k + 1:03d}.exr", img * 1e30, "float")
    (tmp_path / "huge" / "filenames.txt").write_text("".join(f"{k + 1:03d}.exr\n" for k in range(6)))
    (tmp_path / "huge" / "light_intensities.txt").write_text("1e-12 1e-12 1e-12\n" * 6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw numpy warning may reach the user
        with pytest.raises(PsctlError, match=r"001\.exr: divided by its light intensity \(1e-12\) its values pass"):
            run_normals(tmp_path / "huge", "l2", write=False)
        # ground truth of huge vectors: directions all the same
        gt = data["normals"] * 1e30
        gt[data["mask"] & (np.arange(gt.shape[1]) == 20)[None, :]] = [0, 0, 1e20]
        write_image(capture / "Normal_gt.exr", gt.astype(np.float32), "float")
        (capture / "Normal_gt.mat").unlink(missing_ok=True)
        r = run_normals(capture, "l2", write=False)
        assert r["n_evaluated_pixels"] == r["n_mask_pixels"] and r["mae"] < 5
        from psctl.depth import run_depth

        write_image(tmp_path / "n.exr", (np.abs(data["normals"]) * 1e30).astype(np.float32), "float")  # no component < 0
        assert run_depth(capture, normals=tmp_path / "n.exr", write=False)["outputs"] == {}
    for exc, needle in ((MemoryError(), "out of memory"),):
        with pytest.raises(typer.Exit) as e, _user_errors():
            raise exc
        err = capsys.readouterr().err
        assert e.value.exit_code == 2 and needle in err and len(err.strip().splitlines()) == 1
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "psctl.cli", "normals", str(capture), "-m", "l2", "--json",
                               "-o", str(tmp_path / "o")], stdout=full, stderr=subprocess.PIPE, text=True)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "cannot write the report to standard output" in proc.stderr and "files were written" in proc.stderr
    # stdout closed (`--json >&-`): Python has no sys.stdout then; one line, not an AttributeError
    proc = subprocess.run([sys.executable, "-m", "psctl.cli", "normals", str(capture), "-m", "l2", "--json",
                           "-o", str(tmp_path / "o2")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          preexec_fn=lambda: os.close(1))
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "standard output is closed" in proc.stderr and (tmp_path / "o2" / "normal.png").is_file()
    real_write = Path.write_bytes

    def full_disk(self, data):  # the disk fills as Normal_gt.mat is written (in memory first since session 50)
        if "Normal_gt" in self.name:
            raise OSError(28, "No space left on device")
        return real_write(self, data)

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    from psctl.cli import app

    with pytest.raises(SystemExit) as e:
        app(["synth", str(tmp_path / "s"), "--preset", "blobby", "--size", "32", "--lights", "4", "-k", "1", "-q"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Normal_gt.mat" in err and "no space left" in err.lower(), err
    assert not (tmp_path / "s").exists()


def test_second_review_of_the_fuzzing_fixes(capture, tmp_path, monkeypatch, capsys):
    """A symbolic-link loop given as an input is its own one-line error again (not a RuntimeError
    from the inputs check); an input is never removed as a stale output; eval's label and
    eval.json say what ran (l2: one view, full size); torch's CPU allocator failing is one line;
    zero-filled binary is not called UTF-16."""
    import shutil

    import typer

    from psctl.api import run_normals
    from psctl.cli import _user_errors
    from psctl.errors import PsctlError
    from psctl.eval import method_label, run_benchmark
    from psctl.io.capture import _not_utf8

    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    with pytest.raises(PsctlError, match="loop"):
        run_normals(capture, "ps-fcn", weights=tmp_path / "loop", out=tmp_path / "o1")
    weights = Path(__file__).resolve().parents[1] / "weights" / "ps_fcn.pt"
    run_normals(capture, "l2", out=tmp_path / "s", formats=("png16", "exr"))
    shutil.copy(weights, tmp_path / "s" / "normal.exr")  # an earlier output's name, now the weights
    r = run_normals(capture, "ps-fcn", out=tmp_path / "s", formats=("png16",), weights=tmp_path / "s" / "normal.exr")
    assert (tmp_path / "s" / "normal.exr").read_bytes() == weights.read_bytes()
    assert not any("removed" in n and "normal.exr" in n for n in r["notes"])
    res = run_benchmark("folder", root=capture.parent, method="l2", views=8, downsample=2)
    assert (res["views"], res["downsample"], res["precision"]) == (1, 1, "float32") and method_label(res) == "l2"
    with pytest.raises(typer.Exit) as e, _user_errors():
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:121] data. DefaultCPUAllocator: can't allocate memory: "
                           "you tried to allocate 1099511627776 bytes. Error code 12 (Cannot allocate memory)")
    err = capsys.readouterr().err
    assert e.value.exit_code == 2 and "out of memory (" in err and "1099511627776 bytes" in " ".join(err.split())
    said = " ".join(err.split()).split("out of memory (", 1)[1].split(" ...)", 1)[0]  # cut at a word (an audit)
    assert said.split()[-1] in "Error code 12 (Cannot allocate memory)".split(), said
    with pytest.raises(RuntimeError, match="a bug"), _user_errors():  # other RuntimeErrors keep their traceback
        raise RuntimeError("a bug")
    (tmp_path / "zeros.txt").write_bytes(bytes(64))
    assert "UTF-16" not in _not_utf8(tmp_path / "zeros.txt")


def test_closed_stdout_exits_as_cat_does(capture, tmp_path):
    """`psctl info X | head -1`: once the reader has gone, psctl stops silently with 128 + SIGPIPE
    (click and Rich said 1, which reads as psctl's own failure); files already written stay."""
    for args in (["info", capture], ["info", capture, "--json"], ["--help"],
                 ["normals", capture, "-m", "l2", "-q", "-o", tmp_path / "o"]):
        r, w = os.pipe()
        os.close(r)  # no reader from the start: the first write fails, whatever its size
        try:
            proc = subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, args)], stdout=w,
                                  stderr=subprocess.PIPE, text=True)
        finally:
            os.close(w)
        assert (proc.returncode, proc.stderr) == (141, ""), (args, proc.returncode, proc.stderr)
    assert (tmp_path / "o" / "normal.png").is_file() and (tmp_path / "o" / "report.json").is_file()


def test_train_whose_stderr_reader_goes_away_stops_at_a_checkpoint(tmp_path):
    """`psctl train ... 2>&1 | head -1` in a log: the progress line that finds no reader stops the
    run at a checkpoint, exit 141 (it died at once, without one, before)."""
    r, w = os.pipe()
    os.close(r)
    try:
        proc = subprocess.run([sys.executable, "-m", "psctl.cli", "train", "ps-fcn", "--config",
                               str(Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"), "--out", str(tmp_path / "run"), "--device", "cpu"],
                              stdout=subprocess.PIPE, stderr=w, text=True)
    finally:
        os.close(w)
    assert proc.returncode == 141 and proc.stdout == ""
    state = json.loads((tmp_path / "run" / "state.json").read_text())
    assert 0 < state["samples"] < 48  # stopped at the first progress line (tiny.yaml: 48 samples)
    assert psctl("train", "ps-fcn", "--resume", tmp_path / "run", "--device", "cpu", "-q").returncode == 0


def test_train_whose_note_finds_no_reader_still_stops_at_a_checkpoint(tmp_path):
    """The data note (no training meshes) is printed before the run folder exists: with no reader
    it must not end the run there without a checkpoint (a review's finding)."""
    (tmp_path / "none").mkdir()
    cfg = tmp_path / "mesh.yaml"
    text = (Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml").read_text()
    cfg.write_text(text.replace("shapes: {blobby: 1.0}", "shapes: {blobby: 1.0, mesh: 0.5}"))
    r, w = os.pipe()
    os.close(r)
    try:
        proc = subprocess.run([sys.executable, "-m", "psctl.cli", "train", "ps-fcn", "--config", str(cfg), "--out",
                               str(tmp_path / "run"), "--device", "cpu"], stdout=subprocess.PIPE, stderr=w, text=True,
                              env={**os.environ, "PSCTL_MESHES": str(tmp_path / "none")})
    finally:
        os.close(w)
    assert proc.returncode == 141
    state = json.loads((tmp_path / "run" / "state.json").read_text())
    assert 0 < state["samples"] < 48 and state["data_notes"]


def test_a_closed_stderr_at_start_still_runs(capture, tmp_path):
    """`psctl normals X 2>&-` (or a daemon without fd 2): Python makes sys.stderr None; the run
    failed with exit 1 and wrote nothing. Now it runs, without progress bars or messages, and a
    user error is still exit 2, with nothing printed on stdout in its place."""
    run = lambda *a: subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, a)], capture_output=False,  # noqa: E731
                                    stdout=subprocess.PIPE, text=True, preexec_fn=lambda: os.close(2))
    proc = run("normals", capture, "-m", "l2", "-o", tmp_path / "o")
    assert proc.returncode == 0 and (tmp_path / "o" / "normal.png").is_file()
    proc = run("normals", tmp_path / "missing", "-m", "l2")
    assert proc.returncode == 2 and proc.stdout == ""
    proc = run("normals", capture, "--bogus")
    assert proc.returncode == 2 and proc.stdout == ""
    proc = run("train", "ps-fcn", "--config", Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml",
               "--out", tmp_path / "run", "--device", "cpu")
    assert proc.returncode == 0 and (tmp_path / "run" / "best.pt").is_file()


def test_eval_takes_every_option_normals_takes():
    """`psctl eval` runs each object as `psctl normals` does: a method option added to one and
    not the other (the commands and their library functions pass 14 of them along by name) would
    make the benchmark's numbers come from other settings than a user's run. Same names, same
    defaults, on both layers."""
    import inspect

    from psctl import cli
    from psctl.api import run_normals
    from psctl.eval import run_benchmark

    def options(f, own):
        return {k: p.default for k, p in inspect.signature(f).parameters.items() if k not in own}

    assert options(run_normals, {"path", "arrays", "batch", "formats", "write"}) == \
        options(run_benchmark, {"benchmark", "root", "batch"})
    # eval's -m also takes several methods (a comparison); None means auto, as normals' default
    assert options(cli.normals, {"path", "fmt", "method"}) == \
        options(cli.evaluate, {"benchmark", "root", "method", "markdown"})
    assert inspect.signature(cli.normals).parameters["method"].default == "auto"
    assert inspect.signature(cli.evaluate).parameters["method"].default is None


def _two_objects(root: Path) -> Path:
    for name, seed in (("ballPNG", 1), ("catPNG", 2)):
        write_capture(root / name, n=6, size=24, seed=seed)
    return root


def test_eval_compares_methods_in_one_table(tmp_path):
    """-m given more than once (or a comma list): one table, each method's row as its own eval
    gives it, then the paper's rows once each; with --out each method's folder as its own eval
    --out writes it, compare.png their eval.png one above the other, and compare.json."""
    from psctl.eval import run_benchmark

    root = _two_objects(tmp_path / "root")
    r = json.loads(cli("eval", "--root", root, "-m", "l2,ps-fcn", "-m", "L2", "--json", check=True).stdout)
    assert r["methods"] == ["l2", "ps-fcn"] and [run["method"] for run in r["runs"]] == ["l2", "ps-fcn"]
    for run in r["runs"]:
        alone = run_benchmark("diligent", root, method=run["method"])
        assert [o["mae"] for o in run["objects"]] == pytest.approx([o["mae"] for o in alone["objects"]])
        assert run["paper_method"] == run["method"]
    table = cli("eval", "--root", root, "-m", "l2", "-m", "ps-fcn", check=True).stdout
    lines = table.splitlines()
    order = [next(i for i, line in enumerate(lines) if label in line)
             for label in ("l2 (psctl)", "ps-fcn (psctl)", "l2 (paper)", "ps-fcn (paper)")]
    assert order == sorted(order)
    for run in r["runs"]:
        row = next(line for line in lines if f"{run['method']} (psctl)" in line)
        assert all(f"{o['mae']:.2f}" in row for o in run["objects"]) and f"{run['mean_mae']:.2f}" in row
    assert sum("(paper)" in line for line in lines) == 2
    for columns in ("50", "30"):  # turned (objects as rows), then a line per row: no number cut off
        narrow = cli("eval", "--root", root, "-m", "l2,ps-fcn", env={"COLUMNS": columns}, check=True).stdout
        flat = " ".join(narrow.split())
        assert all(f"{o['mae']:.2f}" in flat for run in r["runs"] for o in run["objects"])
        assert all(f"{run['mean_mae']:.2f}" in flat for run in r["runs"])
        assert max(len(line) for line in narrow.splitlines()[1:]) <= int(columns)
    md = cli("eval", "--root", root, "-m", "l2,ps-fcn", "--markdown", check=True).stdout.splitlines()
    assert [line.split(" | ")[0] for line in md[2:]] == ["| l2 (psctl)", "| ps-fcn (psctl)", "| l2 (paper)",
                                                         "| ps-fcn (paper)"]
    assert md[3] == "| ps-fcn (psctl) | " + " | ".join(f"{o['mae']:.2f}" for o in r["runs"][1]["objects"]) + \
        f" | {r['runs'][1]['mean_mae']:.2f} |"

    out = tmp_path / "out"
    w = json.loads(cli("eval", "--root", root, "-m", "l2,ps-fcn", "--out", out, "--json", check=True).stdout)
    assert w["outputs"] == {f: str(out / f) for f in ("compare.png", "compare.json")}
    assert json.loads((out / "compare.json").read_text()) == w
    sheets = [read_image(out / m / "eval.png")[0] for m in ("l2", "ps-fcn")]
    for m, run in zip(("l2", "ps-fcn"), w["runs"]):
        assert json.loads((out / m / "eval.json").read_text()) == run
        assert (out / m / "cat" / "normal.png").is_file()
    # the same comparison again into its folder (compare.png is no input image there)
    again = json.loads(cli("eval", "--root", root, "-m", "l2,ps-fcn", "--out", out, "--json", check=True).stdout)
    assert [run["mean_mae"] for run in again["runs"]] == [run["mean_mae"] for run in w["runs"]]
    both = read_image(out / "compare.png")[0]
    assert both.shape == (sheets[0].shape[0] + 12 + sheets[1].shape[0], max(s.shape[1] for s in sheets), 3)
    assert np.array_equal(both[:sheets[0].shape[0], :sheets[0].shape[1]], sheets[0])
    assert np.array_equal(both[-sheets[1].shape[0]:, :sheets[1].shape[1]], sheets[1])


def test_a_comparison_runs_each_network_once_per_object(tmp_path, monkeypatch):
    """ps-fcn, ps-fcn-n and the ensemble compared: the ensemble takes its members' normals from
    their runs (helper-165: 10 of the dev split's 20 network runs were repeats), with a note; its
    files are those of an ensemble run alone. The member after the ensemble takes its normals too;
    the options (views) are part of what is reused; without the ensemble nothing is kept."""
    import psctl.infer as infer
    from psctl.eval import compare_methods, run_benchmark
    from psctl.io.capture import open_capture
    from psctl.io.images import read_image

    root = _two_objects(tmp_path / "root")
    calls = []
    real = infer._capture_member
    monkeypatch.setattr(infer, "_capture_member", lambda c, m, method, *a, **k: calls.append(method) or
                        real(c, m, method, *a, **k))
    res = compare_methods("diligent", ["ps-fcn", "ensemble", "ps-fcn-n"], root=root, out=tmp_path / "c")
    assert sorted(calls) == ["ps-fcn"] * 2 + ["ps-fcn-n"] * 2, calls
    calls.clear()
    alone = run_benchmark("diligent", root, method="ensemble", out=tmp_path / "e")
    assert len(calls) == 4
    ens, last = res["runs"][1], res["runs"][2]
    assert [o["mae"] for o in ens["objects"]] == [o["mae"] for o in alone["objects"]]
    for name in ("ball", "cat"):
        for f in ("normal.exr", "spread.png", "error.png"):
            np.testing.assert_array_equal(read_image(tmp_path / "c" / "ensemble" / name / f)[0],
                                          read_image(tmp_path / "e" / name / f)[0])
    for run, member in ((ens, "ps-fcn"), (last, "ps-fcn-n")):  # (ps-fcn-n first ran in the ensemble)
        for o in run["objects"]:
            said = [n for n in o["notes"] if "taken from an earlier run" in n]
            assert len(said) == 1 and said[0].startswith(f"{member}: normals taken from"), o["notes"]
    assert not any("earlier run" in n for o in res["runs"][0]["objects"] for n in o["notes"])
    assert [n for n in res["notes"] if "took the normals" in n] == [
        "methods: ensemble and ps-fcn-n took the normals of the networks that ran before them on the same inputs "
        "from those runs (each network ran once per object): their seconds leave that time out"]
    calls.clear()  # a comparison keeps nothing for the next one
    compare_methods("diligent", ["ps-fcn", "ensemble"], root=root, views=2)
    assert sorted(calls) == ["ps-fcn"] * 2 + ["ps-fcn-n"] * 2, calls
    # what a result is kept under: the inputs and options, the network's file
    cap = open_capture(root / "ballPNG")
    mask = np.ones((24, 24), bool)
    key = infer.reuse_key(cap, mask, "ps-fcn", None, {"views": 1})
    assert key == infer.reuse_key(open_capture(root / "ballPNG"), mask.copy(), "ps-fcn", None, {"views": 1})
    other = mask.copy()
    other[0, 0] = False
    assert len({key, infer.reuse_key(cap, mask, "ps-fcn", None, {"views": 2}),
                infer.reuse_key(cap, other, "ps-fcn", None, {"views": 1}),
                infer.reuse_key(cap.subset([0, 1, 2, 3]), mask, "ps-fcn", None, {"views": 1}),
                infer.reuse_key(cap, mask, "ps-fcn-n", None, {"views": 1}),
                infer.reuse_key(open_capture(root / "catPNG"), mask, "ps-fcn", None, {"views": 1})}) == 6
    calls.clear()
    compare_methods("diligent", ["ps-fcn", "ps-fcn-n"], root=root)  # no ensemble: each once anyway
    assert len(calls) == 4
    # helper-167: a key of the images' paths alone took a capture taken again into the same names, and
    # one of the run's config alone a changed DEFAULT_INFER setting, as the same; a result is taken once
    from psctl.api import run_normals
    from psctl.io.images import write_image

    kept, cap = {}, root / "ballPNG"
    calls.clear()
    run_normals(cap, method="ps-fcn", write=False, reuse=kept)
    run_normals(cap, method="ps-fcn", write=False, reuse=kept)  # taken
    assert len(calls) == 1 and len(kept) == 0
    run_normals(cap, method="ps-fcn", write=False, reuse=kept)  # (taken once: computed, kept again)
    img = read_image(cap / "003.png")[0]
    write_image(cap / "003.png", img[::-1].copy(), "uint16", kind="linear")
    run_normals(cap, method="ps-fcn", write=False, reuse=kept)
    assert len(calls) == 3, calls
    monkeypatch.setitem(infer.DEFAULT_INFER, "grow", 8)
    run_normals(cap, method="ps-fcn", write=False, reuse=kept)
    assert len(calls) == 4, calls
    # a comparison keeps no more than its budget: past it, computed again
    calls.clear()
    monkeypatch.setattr(infer, "REUSE_MB", 0)
    compare_methods("diligent", ["ps-fcn", "ensemble"], root=root)
    assert sorted(calls) == ["ps-fcn"] * 4 + ["ps-fcn-n"] * 2, calls


def test_eval_and_a_comparison_into_one_folder_say_what_the_other_left(tmp_path):
    """A single-method eval into a folder where a comparison wrote (or the reverse) leaves the
    other's files, as an earlier run's object folders are left, and says so (a QA helper's
    finding: it was silent)."""
    from psctl.eval import compare_methods, run_benchmark

    root = _two_objects(tmp_path / "root")
    out = tmp_path / "out"
    compare_methods("diligent", ["l2", "ps-fcn"], root=root, out=out)
    r = run_benchmark("diligent", root, method="l2", out=out)
    said = [n for n in r["notes"] if "earlier comparison" in n]
    assert said == [f"outputs: {out} also holds an earlier comparison's (several methods) compare.png, "
                    f"compare.json, l2/, ps-fcn/ (left as they are)"], r["notes"]
    assert (out / "compare.json").is_file() and (out / "eval.json").is_file()
    again = compare_methods("diligent", ["l2", "ps-fcn"], root=root, out=out)
    said = [n for n in again["notes"] if "earlier single-method" in n]
    assert said == [f"outputs: {out} also holds an earlier single-method eval's eval.png, eval.json, ball/, "
                    f"cat/ (left as they are)"], again["notes"]
    fresh = tmp_path / "fresh"  # each kind alone, or again over its own: no such note
    assert not [n for n in run_benchmark("diligent", root, method="l2", out=fresh)["notes"] if "earlier" in n]
    assert not [n for n in run_benchmark("diligent", root, method="l2", out=fresh)["notes"] if "earlier" in n]


def test_eval_comparison_refuses_before_any_method_runs(tmp_path, monkeypatch):
    """A comparison that cannot finish stops before its first method runs (a typo, --weights, a
    method without weights), and one that fails in a later method leaves no output at all."""
    import psctl.eval as ev
    from psctl.errors import PsctlError

    root = _two_objects(tmp_path / "root")
    out = tmp_path / "out"
    calls = []
    real = ev.run_benchmark
    monkeypatch.setattr(ev, "run_benchmark", lambda *a, **k: calls.append(k["method"]) or real(*a, **k))
    with pytest.raises(PsctlError, match="unknown --method 'bogus'"):
        ev.compare_methods("diligent", ["l2", "bogus"], root=root, out=out)
    with pytest.raises(PsctlError, match="names one network's file"):
        ev.compare_methods("diligent", ["l2", "ps-fcn"], root=root, out=out, weights=tmp_path / "w.pt")
    with weights_in(tmp_path / "empty"), pytest.raises(PsctlError, match="ps_fcn.pt"):
        (tmp_path / "empty").mkdir()
        ev.compare_methods("diligent", ["l2", "ps-fcn"], root=root, out=out)
    assert calls == [] and not out.exists()

    def second_fails(*a, **k):
        calls.append(k["method"])
        if len(calls) == 2:
            raise PsctlError(root / "catPNG", "made to fail")
        return real(*a, **k)

    monkeypatch.setattr(ev, "run_benchmark", second_fails)
    with pytest.raises(PsctlError, match="made to fail"):
        ev.compare_methods("diligent", ["l2", "ps-fcn"], root=root, out=out)
    assert calls == ["l2", "ps-fcn"] and not out.exists()  # l2's finished folder went with the failure
    with pytest.raises(TypeError, match=r"compare_methods\(\) got an unexpected keyword argument 'bogus'"):
        ev.compare_methods("diligent", ["l2", "ps-fcn"], root=root, bogus=1)
    # two names of one run (auto is l2 without weights): run once, and said
    with weights_in(tmp_path / "empty"):
        r = ev.compare_methods("diligent", ["l2", "auto"], root=root)
    assert r["methods"] == ["l2"] and len(r["runs"]) == 2 - 1
    assert any(n.startswith("methods: auto runs what l2 runs") for n in r["notes"])
    proc = cli("eval", "--root", root, "-m", "l2,", "--out", out)  # an empty name: one line, exit 2
    assert proc.returncode == 2 and "unknown --method ''" in proc.stderr and not out.exists()


def test_train_in_a_log_says_its_start_line_only_for_a_run_that_starts(tmp_path):
    """In a log (stderr not a terminal) psctl train opens with a line naming the run; a recipe
    refused at once printed it too, before its error (seen in session 50): now one line."""
    repo = Path(__file__).resolve().parents[1]
    bad = cli("train", "ps-fcn", "--config", repo / "configs" / "ps_fcn_n_gpu_stage12.yaml", "--out", tmp_path / "x")
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [
        f"error: {repo / 'configs' / 'ps_fcn_n_gpu_stage12.yaml'}: config 'method' is 'ps-fcn-n': the recipe is for "
        "another network than ps-fcn; train ps-fcn-n with it, or choose a ps-fcn recipe"]
    assert not (tmp_path / "x").exists()
    good = cli("train", "ps-fcn", "--config", repo / "configs" / "tiny.yaml", "--out", tmp_path / "run", "--device", "cpu")
    assert good.returncode == 0, good.stderr
    assert good.stderr.splitlines()[0].startswith(f"train ps-fcn in {tmp_path / 'run'}: a line every 30 s")


def test_train_stopped_by_sigterm_says_so_and_exits_143(tmp_path):
    """A real SIGTERM to psctl train (configs/gpu_session.sh's deadline, `timeout -s TERM`): a
    checkpoint, the line saying how the run stopped, exit 143. (A change for library callers
    re-raised the signal into the command's own handler, which then printed only 'terminated'.)"""
    import signal
    import time

    cfg = tmp_path / "long.yaml"
    cfg.write_text((Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml").read_text()
                   .replace("samples: 48", "samples: 100000"))
    proc = subprocess.Popen([sys.executable, "-m", "psctl.cli", "train", "ps-fcn", "--config", str(cfg), "--out",
                             str(tmp_path / "run"), "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    log = tmp_path / "run" / "log.jsonl"
    deadline = time.monotonic() + 120
    while not (log.is_file() and log.read_text().strip()) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert f"stopped by SIGTERM (continue with --resume {tmp_path / 'run'})" in err, err
    assert (tmp_path / "run" / "state.json").is_file()


def test_main_silences_libpng_only_while_it_runs(monkeypatch):
    """psctl.cli.main turns fd 2's silencing on for the command; called in a notebook, it must
    not leave it on for the library calls after it."""
    from psctl.cli import main
    from psctl.errors import C_STDERR

    monkeypatch.setattr(sys, "argv", ["psctl", "--help"])
    with pytest.raises(SystemExit):
        main()
    assert C_STDERR["silence"] is False


def test_an_input_listed_in_the_output_folder_is_never_removed_nor_replaced(tmp_path, fake_weights):
    """An image listed by its path in filenames.txt can sit in an output folder under an output's
    name (a hostile-input audit): psctl normals removed it as an earlier run's leftover, and
    psctl depth wrote over it. Inputs are never modified: a clash is refused, a leftover kept."""
    import hashlib

    from psctl.api import run_normals
    from psctl.depth import run_depth
    from psctl.errors import PsctlError
    from psctl.lights import run_lights

    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()
    write_capture(tmp_path / "c1", n=6, size=32, seed=1)
    out = tmp_path / "O"
    run_normals(tmp_path / "c1", method="l2", out=out, albedo=True)  # albedo.png is on O's list now
    write_capture(tmp_path / "c2", n=6, size=32, seed=2)
    names = (tmp_path / "c2" / "filenames.txt").read_text().split()
    shutil.copy(tmp_path / "c2" / names[0], out / "albedo.png")  # c2's first image, kept in O
    (tmp_path / "c2" / "filenames.txt").write_text("\n".join([str(out / "albedo.png"), *names[1:]]) + "\n")
    before = digest(out / "albedo.png")
    r = run_normals(tmp_path / "c2", method="l2", out=out)  # without --albedo: albedo.png would be stale
    assert digest(out / "albedo.png") == before and "albedo.png" not in " ".join(r["notes"])
    assert r["mae"] < 2
    # an output of this run under the input's name: refused before any work, by every command
    for name, run in (("shading.png", lambda: run_depth(tmp_path / "c2", out=out)),
                      ("lights.png", lambda: run_lights(tmp_path / "c2", out=out, weights=fake_weights / "lcnet.pt",
                                                        device="cpu", views=1, refine=False)),
                      ("error.png", lambda: run_normals(tmp_path / "c2", method="l2", out=out))):
        shutil.copy(tmp_path / "c2" / names[1], out / name)
        (tmp_path / "c2" / "filenames.txt").write_text("\n".join([names[0], str(out / name), *names[2:]]) + "\n")
        kept = digest(out / name)
        with pytest.raises(PsctlError, match="is an input of this capture; choose another --out"):
            run()
        assert digest(out / name) == kept, name


def test_a_fifo_or_endless_file_in_place_of_psctls_own_files_does_not_hang(tmp_path):
    """psctl reads back files it wrote itself (an output folder's list, report.json beside a
    normal map). A FIFO there blocked the run for ever and a link to /dev/zero filled the memory
    (a hostile-input audit): only a regular file of bounded size is read, anything else counts as
    absent (the list: no earlier run; report.json: no albedo for the mesh's colours)."""
    write_capture(tmp_path / "c", n=6, size=32)
    run = lambda *a: subprocess.run([sys.executable, "-m", "psctl.cli", *map(str, a)], capture_output=True,
                                    text=True, timeout=120)
    for kind in ("fifo", "zero"):
        out = tmp_path / f"o_{kind}"
        out.mkdir()
        odd = out / ".psctl-normals"
        os.mkfifo(odd) if kind == "fifo" else os.symlink("/dev/zero", odd)
        proc = run("normals", tmp_path / "c", "-m", "l2", "--out", out, "-q")
        if kind == "fifo":  # not a file: in the way, refused in one line before any work
            assert proc.returncode == 2 and "is in the way of an output file" in proc.stderr, proc.stderr
            odd.unlink()
            proc = run("normals", tmp_path / "c", "-m", "l2", "--out", out, "-q")
        assert proc.returncode == 0, proc.stderr
        assert odd.is_file() and "normal.png" in odd.read_text().split()  # replaced by the run's own list
        report = out / "report.json"
        report.unlink()
        os.mkfifo(report) if kind == "fifo" else os.symlink("/dev/zero", report)
        proc = run("depth", tmp_path / "c", "--normals", out / "normal.png", "--out", tmp_path / f"d_{kind}", "-q")
        assert proc.returncode == 0, proc.stderr
        assert (tmp_path / f"d_{kind}" / "depth.exr").is_file()


def test_escape_sequences_in_names_are_written_out(tmp_path):
    """A file name holding a terminal escape sequence (a downloaded capture's filenames.txt) was
    echoed raw in the error line, able to retitle or clear the user's terminal (a hostile-input
    audit): control characters are written out, and the error stays one line."""
    write_capture(tmp_path / "c", n=6, size=32)
    bad = "x\x1b]0;PWNED\x07\x1b[2J\n.png"
    listed = [*[f"{k:03d}.png" for k in range(1, 6)], bad.replace("\n", "")]  # a missing image, so named
    (tmp_path / "c" / "filenames.txt").write_text("\n".join(listed) + "\n")
    proc = cli("normals", tmp_path / "c", "-m", "l2", "--out", tmp_path / "o")
    assert proc.returncode == 2 and "\x1b" not in proc.stderr and "\x07" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "\\x1b]0;PWNED" in proc.stderr, proc.stderr
    (tmp_path / "c" / "filenames.txt").write_text("\n".join([*listed[:5], "006.png"]) + "\n")
    proc = cli("normals", tmp_path / "c", "-m", "l2", "--out", tmp_path / ("o" + bad) / "x")  # a line break too
    assert proc.returncode == 0 and "\x1b" not in proc.stderr + proc.stdout, proc.stderr
    (tmp_path / "a\nfile").write_text("")  # --out under a file whose name breaks the line: still one line
    proc = cli("normals", tmp_path / "c", "-m", "l2", "--out", tmp_path / "a\nfile" / "x")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "a\\x0afile" in proc.stderr
    # a note naming the folder, and the summary's lines: written out as well
    (tmp_path / "c" / "filenames.txt").unlink()
    os.rename(tmp_path / "c", tmp_path / ("c" + bad.replace("\n", "")))
    proc = cli("normals", tmp_path / ("c" + bad.replace("\n", "")), "-m", "l2", "--out", tmp_path / "o2")
    assert proc.returncode == 0, proc.stderr
    assert "\x1b" not in proc.stdout + proc.stderr and "\\x1b]0;PWNED" in proc.stdout


def test_values_near_float32s_limit_give_one_line_and_the_right_advice(tmp_path):
    """A float image with values near float32's limit: numpy's overflow warnings broke the one-line
    rule (hot pixels, psctl info's mean), and sdps' error told to rescale light_intensities.txt,
    which it does not read, quoting LCNet's estimate as if it were the file's (a hostile-input audit)."""
    from psctl.io.images import read_image, write_image

    write_capture(tmp_path / "c", n=6, size=32)
    names = (tmp_path / "c" / "filenames.txt").read_text().split()
    img = read_image(tmp_path / "c" / names[0])[0].astype(np.float32)
    img[10, 10:12, 0] = 3e38
    (tmp_path / "c" / names[0]).unlink()
    write_image(tmp_path / "c" / "001.exr", img, "float")
    (tmp_path / "c" / "filenames.txt").write_text("\n".join(["001.exr", *names[1:]]) + "\n")
    proc = cli("info", tmp_path / "c", "--check")
    assert proc.returncode == 0 and "Warning" not in proc.stderr and ".. inf" not in proc.stdout, proc.stderr
    proc = cli("normals", tmp_path / "c", "-m", "l2", "--out", tmp_path / "o")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "divided by its light intensity" in proc.stderr and "or light_intensities.txt" in proc.stderr
    # sdps' second stage reads the images divided by LCNet's intensities (here a small estimate)
    from psctl.errors import PsctlError
    from psctl.io.capture import iter_images, open_capture
    from psctl.lights import LightEstimate, lit_capture

    cap = open_capture(tmp_path / "c")
    est = LightEstimate(cap.lights, np.full(cap.n_images, 0.25, np.float32), {})
    with pytest.raises(PsctlError, match=r"divided by its estimated light intensity \(0.25\) its values pass "
                                         r"float32's range; rescale the images$"):
        list(iter_images(lit_capture(cap, est)))


def test_a_folder_that_cannot_be_searched_is_named(tmp_path, monkeypatch, capsys):
    """Path.is_file() raises EACCES for a probe (objects.txt) inside a folder without x permission:
    the message names that folder, not the file psctl was only looking for (a QA helper's
    finding, session 58: "nox/objects.txt: permission denied" for a capture folder of mode 644)."""
    import errno

    import typer

    from psctl.cli import _user_errors

    blocked = str(tmp_path / "nox")
    monkeypatch.setattr(os, "access", lambda p, mode, **k: not os.fspath(p).startswith(blocked))
    with pytest.raises(typer.Exit) as e, _user_errors():
        raise PermissionError(errno.EACCES, "Permission denied", os.path.join(blocked, "sub", "objects.txt"))
    err = capsys.readouterr().err
    assert e.value.exit_code == 2 and len(err.strip().splitlines()) == 1
    assert f"{blocked}: permission denied (the folder cannot be searched" in err  # the outermost one
    # a file that is itself unreadable, in a folder that can be searched, is named as before
    with pytest.raises(typer.Exit), _user_errors():
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "a.png"))
    err = capsys.readouterr().err
    assert f"{tmp_path / 'a.png'}: permission denied" in err and "searched" not in err


def test_readme_lists_every_short_option():
    """README's 'Short options' line names each short option with its long one, all of them, and
    no command uses a short name for another long option (-n is --images everywhere)."""
    import re

    import typer.main

    from psctl.cli import app

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    line = readme[readme.index("Short options,"):].split("\n\n")[0]
    listed = dict(re.findall(r"`(-[a-z])` `(--[a-z-]+)`", line))
    group = typer.main.get_command(app)
    used: dict[str, set[str]] = {"-h": {"--help"}}
    for name, command in group.commands.items():
        for param in command.params:
            opts = [*getattr(param, "opts", []), *getattr(param, "secondary_opts", [])]
            longs = [o for o in opts if o.startswith("--")]
            for short in (o for o in opts if re.fullmatch(r"-[a-zA-Z]", o)):
                used.setdefault(short, set()).update(longs)
    assert all(len(longs) == 1 for longs in used.values()), used
    assert {k: v.pop() for k, v in used.items()} == listed


def test_info_check_refuses_ground_truth_that_psctl_normals_refuses(tmp_path):
    """A Normal_gt.mat of nothing but NaN passed `psctl info --check` ('none damaged') and then
    stopped psctl normals (a QA helper's finding): --check now gives normals' one line."""
    import scipy.io

    from psctl.io.capture import GT_HINT

    folder = tmp_path / "nan"
    write_capture(folder, n=4)
    gt = folder / "Normal_gt.mat"
    assert gt.is_file()
    scipy.io.savemat(gt, {"Normal_gt": np.full((40, 40, 3), np.nan)})
    for args in (("info", folder, "--check"), ("normals", folder, "-m", "l2", "-o", tmp_path / "o")):
        proc = cli(*args)
        assert proc.returncode == 2 and proc.stderr.strip() == \
            f"error: {gt}: ground truth has no valid normal inside the mask; {GT_HINT}", (args, proc.stderr)


def test_a_bad_ground_truth_says_how_to_run_without_it(tmp_path):
    """Ground truth only scores the normals, yet a bad one stops the commands that open the
    folder (helper-163): their one line says how to run without it. psctl info without --check
    notes ground truth with no normal inside the mask (it noted only a .mat's problems), and
    psctl normals refuses that before its work, not after it."""
    import OpenImageIO as oiio

    from psctl.io.capture import GT_HINT

    folder = tmp_path / "c"
    write_capture(folder, n=4)
    gt = folder / "Normal_gt.png"
    (folder / "Normal_gt.mat").unlink()
    gt.write_bytes(b"not a png")
    for args in (("normals", folder, "-m", "l2", "-o", tmp_path / "o"), ("lights", folder, "-o", tmp_path / "o")):
        proc = cli(*args)
        assert proc.returncode == 2 and proc.stderr.startswith(f"error: {gt}: ") and \
            proc.stderr.strip().endswith(f"; {GT_HINT}"), (args, proc.stderr)
    assert not (tmp_path / "o").exists()
    # a ground truth of normals outside the mask only
    codes = np.zeros((40, 40, 3), np.uint16)
    codes[:2] = 32768
    codes[:2, :, 2] = 65535
    buf = oiio.ImageBuf(oiio.ImageSpec(40, 40, 3, oiio.UINT16))
    buf.set_pixels(oiio.ROI(), codes)
    gt.unlink()
    assert buf.write(str(gt))
    mask = np.zeros((40, 40, 1), np.uint8)
    mask[10:30, 10:30] = 255
    buf = oiio.ImageBuf(oiio.ImageSpec(40, 40, 1, oiio.UINT8))
    buf.set_pixels(oiio.ROI(), mask)
    assert buf.write(str(folder / "mask.png"))
    proc = cli("info", folder, "--json")
    assert proc.returncode == 0 and "Normal_gt.png: ground truth has no valid normal inside the mask (psctl normals " \
        "and eval stop on it)" in json.loads(proc.stdout)["notes"], proc.stdout
    proc = cli("normals", folder, "-m", "l2", "-o", tmp_path / "o")  # (after the work, it came without the hint)
    assert proc.returncode == 2 and proc.stderr.strip() == \
        f"error: {gt}: ground truth has no valid normal inside the mask; {GT_HINT}", proc.stderr


def test_readme_and_docs_link_to_files_that_exist():
    """Markdown links and pictures in README.md and docs/*.md that point into the repository
    (docs/img/*.png, docs/usage.md, ...) name files that exist (a picture renamed or not committed
    shows as a broken image on the project's page)."""
    import re

    root = Path(__file__).resolve().parents[1]
    missing = []
    for doc in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or an anchor in the same file
            if not (doc.parent / target.split("#")[0]).exists():
                missing.append(f"{doc.relative_to(root)}: {target}")
    assert not missing, missing
    assert (root / "docs" / "img" / "dev_split_l2_vs_ensemble.png").is_file()


_KILL_AT_RENAME = """
import os, signal, sys
import psctl.io.atomic as atomic
from psctl.api import run_normals

count, real, kill, fail = [0], os.replace, int(sys.argv[1]), int(sys.argv[4])

def replace(a, b, *args, **kwargs):  # kill -9 at the N-th rename of the commit (or of its rollback)
    if ".psctl-staging" in str(a) + str(b):
        count[0] += 1
        if count[0] == fail:  # a full disk at a placement: the commit rolls back
            raise OSError(28, "No space left on device")
        if count[0] == kill:
            os.kill(os.getpid(), signal.SIGKILL)
    return real(a, b, *args, **kwargs)

atomic.os.replace = replace
run_normals(sys.argv[2], method="l2", out=sys.argv[3], formats=["png16", "npy"])
"""


# the 13th rename: 4 files written in the stage (each renamed from its temporary name), 4 earlier
# files set aside, then the last of the 5 placements
@pytest.mark.parametrize("fail", [0, 13], ids=["commit", "rollback"])
def test_a_run_killed_between_two_renames_leaves_a_list_of_psctls_files(capture, tmp_path, fail):
    """kill -9 at each rename of a commit (-f png16,npy after an -f exr run; or, after a full disk
    at its last placement, of its rollback), then a -f png16 run: the folder holds that run's files,
    neither the first run's normal.exr nor the killed run's normal.npy (the old list went aside
    first, so the next run did not know normal.exr was psctl's, and psctl depth then read the
    stale map: an interruption audit; the rollback undid in the commit's order: a review), with
    a note where earlier files were set aside."""
    from psctl.api import run_normals

    n = fail + 1
    while True:
        out = tmp_path / f"out{n}"
        run_normals(capture, method="l2", out=out, formats=["exr"], n_images=4)
        r = subprocess.run([sys.executable, "-c", _KILL_AT_RENAME, str(n), str(capture), str(out), str(fail)],
                           capture_output=True, text=True)
        done = r.returncode != -9  # past the last rename: nothing killed
        assert not done or r.returncode == (1 if fail else 0), r.stderr
        again = run_normals(capture, method="l2", out=out, formats=["png16"])
        assert sorted(f for f in os.listdir(out) if not f.startswith(".")) == \
            ["error.png", "normal.png", "report.json"], n
        aside = [d for d in out.glob(".psctl-staging.*/.replaced") if any(d.iterdir())]
        assert bool(aside) == any("set aside by a run stopped" in m for m in again["notes"]), n
        if done:
            assert n > fail + 6  # every rename was tried
            break
        n += 1


def test_depth_reads_the_map_the_run_there_wrote(capture, tmp_path):
    """psctl depth in PATH/psctl picks the map the psctl normals run whose report.json is there
    wrote, not a normal.exr left by another (first in its order); where that map has changed
    since, the first there is read, with a note."""
    from psctl.api import run_normals
    from psctl.depth import pick_normal_file, run_depth
    from psctl.io.images import write_image

    run_normals(capture, method="l2", formats=["png16"])
    folder = capture / "psctl"
    flat = np.zeros((40, 40, 3), np.float32)
    flat[..., 2] = 1
    write_image(folder / "normal.exr", flat, "float32", kind="data")  # someone else's map
    assert pick_normal_file(folder) == (folder / "normal.png", None)
    r = run_depth(capture, write=False)
    assert r["normals"] == os.path.abspath(folder / "normal.png")
    assert not any(m.startswith("normals: ") for m in r["notes"])
    os.utime(folder / "normal.png", ns=(1, 1))  # changed since the run
    picked, note = pick_normal_file(folder)
    assert picked == folder / "normal.exr" and "it wrote normal.png, since changed or removed" in note
    r = run_depth(capture, write=False)
    assert r["normals"] == os.path.abspath(folder / "normal.exr") and note in r["notes"]
    # the run wrote two maps and the first changed since: the second is read, with a note (helper-170)
    run_normals(capture, method="l2", formats=["exr", "npy"])
    os.utime(folder / "normal.exr", ns=(1, 1))
    picked, note = pick_normal_file(folder)
    assert picked == folder / "normal.npy" and note == (
        "normals: normal.npy read; normal.exr, which the same psctl normals run wrote first, changed since, so it "
        "was passed over (name a map with --normals)")
    (folder / "report.json").unlink()
    assert pick_normal_file(folder) == (folder / "normal.exr", None)  # no report: the first there, as before


def test_capture_paths_unreadable_to_os_access_are_psctls_to_judge(tmp_path, monkeypatch):
    """click's own readability test answered a folder without read permission with "Invalid value
    for 'path': path ... is not readable" (helper-170), unlike every other error ("error: PATH:
    permission denied"). The capture and root arguments leave it to psctl: here os.access says
    no (root, as on CI, may read anything) and psctl, which can read the folder, runs."""
    from tests.conftest import write_capture

    write_capture(tmp_path / "cap", n=6, size=16)
    np.savetxt(tmp_path / "K.txt", [[40.0, 0, 8], [0, 40.0, 8], [0, 0, 1]])
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if mode == os.R_OK and
                        os.fspath(p).startswith(str(tmp_path)) else real(p, mode, *a, **k))
    for args in (["info", tmp_path / "cap"], ["normals", tmp_path / "cap", "-m", "l2", "-o", tmp_path / "n"],
                 ["depth", tmp_path / "cap", "-o", tmp_path / "d"], ["eval", "-b", "folder", "--root", tmp_path,
                                                                    "-m", "l2"],
                 ["depth", tmp_path / "cap", "-o", tmp_path / "dk", "--K", tmp_path / "K.txt"]):  # every path option
        r = cli(*args, "-q")
        assert r.returncode == 0 and "not readable" not in r.stderr, (args, r.stderr)


def test_ctrl_c_while_the_command_imports_exits_130_quietly(monkeypatch, capsys):
    """Ctrl-C in the first 0.1 s, while psctl.cli's modules import, printed Python's
    KeyboardInterrupt traceback (helper-177); the entry point exits 130 as at any later moment."""
    import builtins

    from psctl import _start

    real = builtins.__import__

    def interrupted(name, *args, **kwargs):
        if name == "psctl.cli":
            raise KeyboardInterrupt
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", interrupted)
    with pytest.raises(SystemExit) as e:
        _start.main()
    assert e.value.code == 130 and capsys.readouterr().err == ""

"""weights/lineage.yaml (every stage behind the release weights) and its replay, psctl.lineage."""

from __future__ import annotations

import copy
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from psctl import lineage as lin
from psctl.errors import PsctlError
from psctl.models.weights import read_weights
from psctl.train import STOP, check_method_recipe

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def manifest() -> dict:
    return lin.load_lineage()


def test_every_stage_is_a_recipe_todays_code_accepts(manifest):
    """A replay must not fail hours in on a recipe key that has since been renamed or refused."""
    stages = manifest["stages"]
    trained = [s for s in stages.values() if "recipe" in s]
    assert len(trained) >= 35
    for sid, s in stages.items():
        if "recipe" not in s:
            assert len(s["average"]) >= 2, sid
            continue
        config = lin.stage_recipe(s, None if s["init"] is None else "start.pt")
        check_method_recipe(s["method"], config)  # the stream's options with today's psctl.synth
        tr = s["recipe"]["train"]
        # kept at or before the planned end (a run's last batch may pass it)
        assert config["train"]["samples"] == s["samples"] < tr["samples"] + tr["batch_size"], sid
        # the schedule is the recorded one: halvings in samples, so stopping early keeps it
        assert config["train"]["lr_halve_every"] == s["recipe"]["train"]["lr_halve_every"], sid


def test_each_release_file_is_its_last_stage(manifest):
    """The installed files are the manifest's: a new release file needs a new stage (written by
    benchmarks/lineage_from_git.py), or this fails."""
    for file, sid in manifest["ships"].items():
        stage = manifest["stages"][sid]
        assert hashlib.sha256((REPO / file).read_bytes()).hexdigest() == stage["sha256"], file
        md = read_weights(REPO / file).metadata
        assert md["method"] == stage["method"]
        assert md["samples_seen"] == stage.get("samples", stage.get("samples_seen")), file
        order = lin.stages_for(manifest, file)
        assert order[-1] == sid and len(order) == len(set(order))
        for k, s in enumerate(order):  # every stage after the ones it starts from
            assert all(order.index(p) < k for p in lin._parents(manifest["stages"][s])), (file, s)
        assert manifest["stages"][order[0]]["init"] is None  # from scratch


def test_lineage_sample_counts_match_the_docs(manifest):
    """docs/training.md's counts for two lineages (scale stage 4, PS-FCN stage 12), from the manifest."""
    order = lin.stages_for(manifest, "ps_fcn_n.scale4")
    assert sum(manifest["stages"][s]["samples"] for s in order) == 1_283_488
    order = lin.stages_for(manifest, "ps_fcn.12")
    assert sum(manifest["stages"][s]["samples"] for s in order) == 1_107_520  # PS-FCN stage 12's


def test_manifest_is_what_git_history_gives():
    """The manifest is written from the weights committed over the project's history, each link
    checked against the child's record of its start; a hand edit or a stale file fails here."""
    probe = subprocess.run(["git", "-C", str(REPO), "cat-file", "-e", "9485390:weights/ps_fcn_n.pt"],
                           capture_output=True)
    if probe.returncode != 0:
        pytest.skip("no git history here (a shallow clone or an unpacked archive)")
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "lineage_from_git.py"), "--check"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr


def _small(manifest: dict) -> dict:
    """A five-stage lineage of real recipes: PS-FCN+N from scratch, PS-FCN from it, UPS-FCN from
    that (the light filters dropped), a second PS-FCN stage, and the average of the two PS-FCNs."""
    st = manifest["stages"]
    pick = {"a": ("ps_fcn_n.1", None), "b": ("ps_fcn.1", "a"), "c": ("ps_fcn.2", "b"), "u": ("ups_fcn.1", "b")}
    stages = {k: {**copy.deepcopy(st[src]), "init": init} for k, (src, init) in pick.items()}
    stages["avg"] = {"method": "ps-fcn", "average": ["b", "c"]}
    return {"ships": {"weights/x.pt": "avg"}, "stages": stages}


def _weights(path: Path) -> dict:
    return read_weights(path).state_dict


def test_tiny_replay_chains_stages_and_resumes_exactly(manifest, tmp_path):
    torch.set_num_threads(2)
    small = _small(manifest)
    lines: list[str] = []
    res = lin.rebuild("weights/x.pt", tmp_path / "a", small, device="cpu", tiny=True, report=lines.append)
    assert res["finished"] and res["file"] == tmp_path / "a" / "avg" / "best.pt"
    assert [ln.split(":")[0] for ln in lines] == ["[1/4] a", "[2/4] b", "[3/4] c", "[4/4] avg"]
    # each stage started from its parent's result (its recorded start), at the tiny sample count
    for sid, parent in (("b", "a"), ("c", "b")):
        md = read_weights(tmp_path / "a" / sid / "model.pt").metadata
        assert md["init"]["path"].endswith(f"{parent}/model.pt") and md["samples_seen"] == 4
        assert md["method"] == "ps-fcn"
    b, c = _weights(tmp_path / "a" / "b" / "model.pt"), _weights(tmp_path / "a" / "c" / "model.pt")
    avg = _weights(res["file"])
    assert all(torch.allclose(avg[k].float(), (b[k].float() + c[k].float()) / 2, atol=1e-6) for k in avg)
    assert any(not torch.equal(b[k], c[k]) for k in b)  # c trained on from b
    # UPS-FCN from PS-FCN: the light input dropped, as configs/ups_fcn_cpu.yaml did
    res_u = lin.rebuild("u", tmp_path / "a", small, device="cpu", tiny=True, report=lines.append)
    assert res_u["finished"] and read_weights(res_u["file"]).method == "ups-fcn"
    assert lines[-1].startswith("[3/3] u") and len(lines) == 5  # a and b were not trained again

    # interrupted in stage c (as by a signal: train's progress says STOP), then called again;
    # a and b are copied in finished (the replay skips them: saves two stages' time)
    import shutil

    for sid in ("a", "b"):
        shutil.copytree(tmp_path / "a" / sid, tmp_path / "b" / sid)
    stopped: list[dict] = []

    def stop_in_c(rec: dict):
        if not stopped and (tmp_path / "b" / "c").exists():
            stopped.append(rec)
            return STOP
        return None

    res = lin.rebuild("weights/x.pt", tmp_path / "b", small, device="cpu", tiny=True, report=lambda s: None,
                      progress=stop_in_c)
    assert not res["finished"] and res["stage"] == "c" and stopped[0]["samples"] < 4
    res = lin.rebuild("weights/x.pt", tmp_path / "b", small, device="cpu", tiny=True, report=lambda s: None)
    assert res["finished"]
    one, two = _weights(tmp_path / "a" / "avg" / "best.pt"), _weights(res["file"])
    assert all(torch.equal(one[k], two[k]) for k in one)  # the same bits as the uninterrupted replay

    # a real replay into the tiny one's folder went on with its runs and called their files the
    # result (helper-197); now the stage's recipe is compared first
    with pytest.raises(PsctlError, match="holds a run of another recipe than stage 'a'.*--tiny replay"):
        lin.rebuild("weights/x.pt", tmp_path / "b", small, device="cpu", report=lambda s: None)
    # an average of members that have since changed is not kept as it is
    shutil.copy(tmp_path / "a" / "c" / "model.pt", tmp_path / "b" / "b" / "model.pt")
    with pytest.raises(PsctlError, match="average of other files than its members"):
        lin.rebuild("weights/x.pt", tmp_path / "b", small, device="cpu", tiny=True, report=lambda s: None)


def test_manifest_errors_name_the_file_and_the_stage(tmp_path, manifest):
    import yaml

    bad = copy.deepcopy(_small(manifest))
    bad["stages"]["c"]["init"] = "nowhere"
    path = tmp_path / "l.yaml"
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(PsctlError, match="stage 'c' starts from 'nowhere', which is not a stage") as e:
        lin.load_lineage(path)
    assert str(e.value.path) == str(path)
    bad["stages"]["c"]["init"], bad["stages"]["a"]["init"] = "b", "c"  # a -> c -> b -> a
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(PsctlError, match="depends on itself"):
        lin.load_lineage(path)
    with pytest.raises(PsctlError, match="neither a stage nor a release file"):
        lin.stages_for(manifest, "weights/ps_fcn_dagger.pt")
    assert lin.main(["plan", "nothing", "--lineage", str(tmp_path / "missing.yaml")]) == 2


def test_manifest_values_are_checked(tmp_path, manifest):
    """Malformed manifests were tracebacks (KeyError, TypeError) or read a string as a list of
    letters (helper-197)."""
    import yaml

    path = tmp_path / "l.yaml"
    for change, needle in ((lambda m: m["stages"]["b"].pop("samples"), "stage 'b' needs a recipe mapping and a positive"),
                           (lambda m: m["stages"]["b"].update(samples="four"), "positive whole 'samples'"),
                           (lambda m: m["stages"]["b"].update(samples=0), "positive whole 'samples'"),
                           (lambda m: m["stages"]["b"].update(recipe=[1, 2]), "needs a recipe mapping"),
                           (lambda m: m["stages"]["avg"].update(average="b"), "'average' must list at least two"),
                           (lambda m: m["stages"]["avg"].update(average=["b"]), "'average' must list at least two"),
                           (lambda m: m["ships"].update({"y.pt": "nowhere"}), "y.pt ships stage 'nowhere', which is not a stage"),
                           (lambda m: m["ships"].update({"x.pt": ["a"]}), r"x.pt ships stage \['a'\]"),
                           (lambda m: m["stages"]["c"].pop("method"), "stage 'c' names no method"),
                           # both, or neither (a mutation audit: both was taken as a recipe, its average ignored)
                           (lambda m: m["stages"]["avg"].update(recipe={}, samples=4), "stage 'avg' must have either"),
                           (lambda m: m["stages"]["avg"].pop("average"), "stage 'avg' must have either")):
        bad = _small(manifest)
        change(bad)
        path.write_text(yaml.safe_dump(bad))
        with pytest.raises(PsctlError, match=needle):
            lin.load_lineage(path)
    # a recipe today's code refuses: named with the manifest and the stage, before anything trains
    bad = _small(manifest)
    bad["stages"]["c"]["recipe"]["train"]["lr"] = "fast"
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(PsctlError, match=r"stage 'c': config 'train.lr'") as e:
        lin.rebuild("weights/x.pt", tmp_path / "out", lin.load_lineage(path), device="cpu", tiny=True,
                    report=lambda s: None)
    assert str(e.value.path) == str(path) and not (tmp_path / "out").exists()
    with pytest.raises(PsctlError, match="must be above 0"):
        lin.rebuild("weights/x.pt", tmp_path / "out", _small(manifest), device="cpu", max_seconds=0)


def test_one_rebuild_at_a_time_into_a_folder(tmp_path, manifest):
    fcntl = pytest.importorskip("fcntl")
    out = tmp_path / "out"
    out.mkdir()
    fd = os.open(out, os.O_RDONLY)  # another process's rebuild, as far as flock can tell (another open file)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(PsctlError, match="another rebuild is running into this folder"):
            lin.rebuild("weights/x.pt", out, _small(manifest), device="cpu", tiny=True, report=lambda s: None)
    finally:
        os.close(fd)
    assert out.is_dir() and not any(out.iterdir())  # nothing written, and the user's folder kept


def test_real_recipes_that_draw_the_mesh_require_it(manifest):
    """Without the mesh folder a real replay trained the first eight stages on procedural shapes
    with only a note, and failed at the first recipe that said require_meshes (helper-197)."""
    first = manifest["stages"]["ps_fcn_n.1"]
    assert "require_meshes" not in first["recipe"]["data"] and first["recipe"]["data"]["shapes"]["mesh"] > 0
    assert lin.stage_recipe(first, None)["data"]["require_meshes"] is True
    tiny = lin.stage_recipe(first, None, tiny=True)["data"]
    assert tiny["require_meshes"] is False and tiny["shapes"] == {"blobby": 1.0}  # tiny: procedural only


def test_plan_lists_a_release_files_stages(capsys):
    assert lin.main(["plan", "weights/lcnet.pt"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("lcnet.1 ") and out[-2].startswith("lcnet.gpu7 ")
    assert out[-1] == "7 stages, 644,624 samples trained in all"
    # the same file however it is named (helper-198: ./ and absolute paths were refused)
    for name in ("./weights/lcnet.pt", str(REPO / "weights" / "lcnet.pt"), "lcnet.pt"):
        assert lin.stages_for(lin.load_lineage(), name)[-1] == "lcnet.gpu7", name
    assert lin.main(["plan", "lcnet.1"]) == 0 and capsys.readouterr().out.splitlines()[-1].startswith("1 stage,")


def test_a_release_file_by_its_full_path_in_the_manifests_checkout(tmp_path, monkeypatch, capsys):
    """--lineage names another checkout's manifest (an installed wheel has none of its own): that
    checkout's release file by its full path is the file, as in the checkout psctl runs from; without
    a manifest the message says to pass --lineage (helper-199)."""
    other = tmp_path / "clone" / "weights"
    other.mkdir(parents=True)
    (other / "lineage.yaml").write_bytes((REPO / "weights" / "lineage.yaml").read_bytes())
    assert lin.main(["plan", str(other / "lcnet.pt"), "--lineage", str(other / "lineage.yaml")]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "7 stages, 644,624 samples trained in all"
    monkeypatch.setattr(lin, "LINEAGE", tmp_path / "site-packages" / "weights" / "lineage.yaml")  # as a wheel
    assert lin.main(["plan", "lcnet.pt"]) == 2
    assert capsys.readouterr().err.strip().endswith("not in the wheel): pass --lineage FILE")
    assert lin.main(["plan", "lcnet.pt", "--lineage", str(tmp_path / "nope.yaml")]) == 2
    assert capsys.readouterr().err.strip() == f"psctl.lineage: {tmp_path / 'nope.yaml'}: lineage manifest is missing"


def test_a_warmup_longer_than_the_stage_is_shortened_to_it(manifest):
    """A stage's recipe whose warmup is longer than its kept sample count (or than a --tiny
    replay's 4 samples) ramps the lr over the stage instead of being refused by check_recipe
    (a mutation audit: no test held the shortening)."""
    stage = {**copy.deepcopy(manifest["stages"]["ps_fcn.1"]), "samples": 500}
    stage["recipe"]["train"]["warmup"] = 1000
    assert lin.stage_recipe(stage, None)["train"]["warmup"] == 500
    assert lin.stage_recipe(stage, None, tiny=True)["train"]["warmup"] == 4
    stage["recipe"]["train"]["warmup"] = 100  # shorter: kept
    assert lin.stage_recipe(stage, None)["train"]["warmup"] == 100


def test_a_rebuild_that_writes_nothing_leaves_no_empty_out_folder(tmp_path, manifest):
    """--out made by a rebuild that stopped before its first stage wrote anything (its time
    limit already spent) is removed, as an output that holds nothing; a folder the user made is
    kept (a mutation audit: dropping the removal failed no test)."""
    out = tmp_path / "new" / "out"
    res = lin.rebuild("weights/x.pt", out, _small(manifest), device="cpu", tiny=True, max_seconds=1e-9,
                      report=lambda s: None)
    assert not res["finished"] and res["stage"] == "a" and not out.exists()
    out.mkdir(parents=True)
    lin.rebuild("weights/x.pt", out, _small(manifest), device="cpu", tiny=True, max_seconds=1e-9, report=lambda s: None)
    assert out.is_dir() and not any(out.iterdir())


def test_rebuild_says_how_a_stage_failed_and_how_it_stopped(tmp_path, manifest, monkeypatch, capsys):
    """A mutation audit's gaps: a stage's own run folder that cannot be resumed is named with the
    way out (removing it trains the stage again); `rebuild` stopped by a signal exits 130, by its
    time limit 0; the progress printer's last line (the stage's end) is always shown."""
    out = tmp_path / "out"
    (out / "a").mkdir(parents=True)
    (out / "a" / "state.json").write_text("{not json")
    with pytest.raises(PsctlError, match=rf"stage 'a' of the rebuild; removing {out / 'a'} trains it again\)"):
        lin.rebuild("weights/x.pt", out, _small(manifest), device="cpu", tiny=True, report=lambda s: None)
    for sig, code in ((15, 130), (None, 0)):
        monkeypatch.setattr(lin, "rebuild", lambda *a, **k: {"finished": False, "file": None, "stage": "a", "signal": sig})
        assert lin.main(["rebuild", "weights/lcnet.pt", "--out", str(tmp_path / "r")]) == code
        assert "stopped in stage a" in capsys.readouterr().out
    show = lin._every(3600.0)
    rec = {"samples": 4, "total": 8, "loss": 0.5, "samples_per_s": 2.0}
    show(rec)  # within the interval: quiet
    show({**rec, "samples": 8})  # the last step: shown
    assert capsys.readouterr().out.strip().startswith("8/8 samples, loss 0.5000")

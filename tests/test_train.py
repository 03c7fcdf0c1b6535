"""The training loop: a tiny recipe trains on CPU, the loss goes down, checkpoints resume."""

from __future__ import annotations

import contextlib
import json
import time
from pathlib import Path

import pytest
import torch

from psctl.errors import PsctlError
from psctl.infer import cpu_has_bf16
from psctl.models.ps_fcn import PSFCN
from psctl.models import WEIGHTS_METHODS
from psctl.models.weights import read_weights
from psctl.train import load_config, merge, train

REPO = Path(__file__).resolve().parents[1]


def tiny(samples: int = 48) -> dict:
    cfg = load_config(REPO / "configs" / "tiny.yaml")
    return merge(cfg, {"train": {"samples": samples}})


def test_tiny_recipe_trains_and_loss_goes_down(tmp_path):
    torch.set_num_threads(2)
    # bf16 where the CPU has it (tiny.yaml is float32 for the exactness tests): the loop's amp path
    st = train("ps-fcn-n", merge(tiny(48), {"train": {"amp": "bf16"}}), tmp_path / "run", device="cpu")
    assert st["finished"] and st["samples"] == 48
    log = [json.loads(l) for l in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in log if "loss" in r]
    assert losses[-1] < losses[0], losses
    # 1 - cos lies in [0, 2]: a loss negated on its way to the optimiser (trained away from the
    # normals) still falls, but below 0 (helper-191)
    assert all(0 <= x <= 2 for x in losses), losses
    w = read_weights(tmp_path / "run" / "model.pt")
    torch.manual_seed(0)  # the recipe's seed draws the initial weights, as psctl.train does
    start = PSFCN({"fuse": "max", "lights": True}).state_dict()
    moved = [k for k, v in w.state_dict.items() if not torch.equal(v.float(), start[k].float())]
    assert len(moved) == len(start), "every parameter took optimiser steps"  # a step skipped leaves them all
    w = read_weights(tmp_path / "run" / "best.pt")
    meta = w.metadata
    assert meta["method"] == "ps-fcn-n" and meta["train_images"] == 8 and meta["normalization"] == "per-channel"
    assert meta["samples_seen"] > 0 and "synthetic_val_mae" in meta["metrics"]
    assert "input_mean" not in meta  # +N removes the exposure
    # what trained it: the CPU's model and whether bf16 really ran (emulated bf16 is not used)
    assert meta["device"].startswith("cpu: ") and meta["device"].endswith("cores)")
    assert meta["precision"] == ("bfloat16 autocast" if cpu_has_bf16() else "float32")
    assert all(p.stat().st_size < 16 * 2**20 for p in (tmp_path / "run").iterdir())


def test_the_losses_are_least_at_the_truth():
    """The training losses themselves: 1 - n.n_gt is 0 on the true normals and 2 on their
    opposites (background pixels left out); LCNet's cross-entropy is lower for logits peaked on the
    true classes than on others. The tiny training runs only see a logged loss fall."""
    from psctl.models.lcnet import DEFAULT_CONFIG, classification_loss, dirs_to_classes, ints_to_classes
    from psctl.train import cosine_loss

    g = torch.Generator().manual_seed(0)
    gt = torch.nn.functional.normalize(torch.randn(2, 3, 8, 8, generator=g), dim=1)
    mask = torch.zeros(2, 1, 8, 8)
    mask[:, :, 2:6, 2:6] = 1
    far = gt.clone()
    far[:, :, 0, 0] = -gt[:, :, 0, 0]  # wrong only outside the mask: no cost
    assert float(cosine_loss(far, gt, mask)) == pytest.approx(0, abs=1e-6)
    assert float(cosine_loss(-gt, gt, mask)) == pytest.approx(2, abs=1e-6)

    dirs = torch.nn.functional.normalize(torch.randn(5, 3, generator=g).abs() + 0.3, dim=1)
    ints = torch.rand(5, generator=g) * 1.8 + 0.2
    c = DEFAULT_CONFIG
    cx, cy = dirs_to_classes(dirs, c["dirs_cls"])
    ci = ints_to_classes(ints, c["ints_cls"], *c["ints_range"])

    def peaked(cls, k, shift=0):
        return torch.nn.functional.one_hot((cls + shift) % k, k).float() * 20

    right = {"dir_x": peaked(cx, c["dirs_cls"]), "dir_y": peaked(cy, c["dirs_cls"]), "ints": peaked(ci, c["ints_cls"])}
    wrong = {"dir_x": peaked(cx, c["dirs_cls"], 3), "dir_y": peaked(cy, c["dirs_cls"], 3),
             "ints": peaked(ci, c["ints_cls"], 3)}
    low, terms = classification_loss(right, dirs, ints)
    high = classification_loss(wrong, dirs, ints)[0]
    assert 0 <= float(low) < 1e-6 and float(high) > 50, (float(low), float(high))
    assert set(terms) == {"dir_x", "dir_y", "ints"}


def test_nan_loss_stops_the_run_before_the_step(tmp_path):
    """A non-finite loss stops training with one clear error and never reaches the weights."""
    from psctl.train import synth_stream

    class Poisoned:
        def __init__(self, inner):
            self.inner, self.calls = inner, 0

        def next_batch(self):
            self.calls += 1
            b = self.inner.next_batch()
            if self.calls == 2:  # the second training batch (each validation stream is used once)
                b["images"] = torch.full_like(b["images"], float("nan"))
            return b

        def __getattr__(self, name):
            return getattr(self.inner, name)

    with pytest.raises(PsctlError, match=r"training loss is nan at step 2"):
        train("ps-fcn", tiny(48), tmp_path / "run", device="cpu",
              make_stream=lambda *a, **k: Poisoned(synth_stream(*a, **k)))
    # the run stopped before its first checkpoint: nothing to resume, so nothing is left (no
    # weights file with NaN in it, no folder a new run with the same --out would trip on)
    assert not (tmp_path / "run").exists()


def test_a_batch_without_object_pixels_stops_the_run(tmp_path):
    """A review: blobby steps 1 renders no object pixel, so every loss was exactly 0 (not NaN) and
    a finite validation of other shapes let the run finish and be installed."""
    cfg = merge(tiny(16), {"data": {"blobby": {"steps": 1}}, "val": {"data": {"blobby": {"steps": 48}}}})
    with pytest.raises(PsctlError, match=r"run: training batch 1 has no object pixel \(0 samples seen; see "
                                         r"data.shapes, data.blobby\): stopped; no checkpoint had been written"):
        train("ps-fcn", cfg, tmp_path / "run", device="cpu")
    assert not (tmp_path / "run").exists()


def test_a_nan_validation_of_the_start_weights_trains_nothing(tmp_path, monkeypatch):
    import psctl.train as T

    train("ps-fcn", tiny(8), tmp_path / "first", device="cpu")
    monkeypatch.setattr(T, "evaluate", lambda task, val: float("nan"))
    with pytest.raises(PsctlError, match=r"validation mae of train.init's weights is nan .*: nothing was trained"):
        train("ps-fcn", merge(tiny(8), {"train": {"init": str(tmp_path / "first" / "best.pt")}}), tmp_path / "run",
              device="cpu")
    assert not (tmp_path / "run").exists()


def test_a_recipe_file_names_the_missing_file_and_checks_with_the_runs_crops(tmp_path):
    """A review: load_config replaced the missing file's name by the recipe's, and checked data
    against the stream's default crop (32), not train.crop."""
    import yaml

    base = yaml.safe_load((REPO / "configs" / "tiny.yaml").read_text())
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump({**base, "data": {**base["data"], "mesh_cache": str(tmp_path / "nope.npz")}}))
    with pytest.raises(PsctlError, match=r"nope.npz: not found \(synth stream option 'mesh_cache' names this file\) "
                                         r"\(in the recipe .*r.yaml\)"):
        load_config(recipe)
    crop = base["train"]["crop"]
    recipe.write_text(yaml.safe_dump({**base, "data": {**base["data"], "scale": [crop, 2 * crop]}}))
    assert load_config(recipe)["data"]["scale"] == [crop, 2 * crop]


def test_a_nan_validation_stops_the_run_and_is_never_kept(tmp_path, monkeypatch):
    """An audit: a recipe whose shapes rendered empty (blobby steps 0, refused now) validated at
    NaN, finished with exit 0 and --install installed its best.pt. A non-finite validation now
    stops the run like a non-finite loss: no best.pt from it, nothing left of a new run."""
    import psctl.train as T

    monkeypatch.setattr(T, "evaluate", lambda task, val: float("nan"))
    with pytest.raises(PsctlError, match=r"run: validation mae is nan at 16 samples \(no object pixel in the "
                                         r"validation views\?.*\): stopped; no checkpoint had been written, so "
                                         r"nothing is kept"):
        train("ps-fcn", merge(tiny(48), {"train": {"val_every": 16}}), tmp_path / "run", device="cpu")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("where, value, message", [
    ("data", {"batch_size": 2}, r"config 'data.batch_size' is set by the run, not the stream's options: give it as "
                                r"train.batch_size"),
    ("data", {"n_images": 3}, r"'data.n_images' .* give it as train.images_per_sample"),
    ("data", {"device": "cuda"}, r"'data.device' .* psctl train --device"),
    ("val", {"data": {"seed": 5}}, r"'val.data.seed' .* give it as val.seed$"),
])
def test_stream_options_the_run_sets_are_refused_in_the_recipe(tmp_path, where, value, message):
    """An audit: data.batch_size, n_images, crop, seed and device were silently overridden by the
    run's own (the same loss and validation as without them)."""
    with pytest.raises(PsctlError, match=message):
        train("ps-fcn", merge(tiny(8), {where: value}), tmp_path / "run", device="cpu")
    assert not (tmp_path / "run").exists()


def test_a_run_that_fails_before_its_first_checkpoint_leaves_nothing(tmp_path, monkeypatch):
    """Out of memory at the first step left the new folder with an empty log.jsonl; a failure
    after a validation also left best.pt, and the same --out was then refused."""
    from psctl.train import synth_stream

    class Failing:
        def __init__(self, inner, at):
            self.inner, self.at, self.calls = inner, at, 0

        def next_batch(self):
            self.calls += 1
            if self.calls == self.at:
                raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 1 bytes")
            return self.inner.next_batch()

        def __getattr__(self, name):
            return getattr(self.inner, name)

    def failing_at(at):  # the training stream only (made first); the validation set's stays whole
        made = []

        def make(*a, **k):
            made.append(1)
            return Failing(synth_stream(*a, **k), at) if len(made) == 1 else synth_stream(*a, **k)
        return make

    cfg = merge(tiny(48), {"train": {"val_every": 8}})
    with pytest.raises(RuntimeError, match="can't allocate"):  # the first step, in a folder with parents to make
        train("ps-fcn", cfg, tmp_path / "a" / "b" / "run", device="cpu", make_stream=failing_at(1))
    assert not (tmp_path / "a").exists()
    # an earlier stopped run's log (configs/gpu_session.sh starts such folders again) keeps its lines
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "log.jsonl").write_text('{"step": 2}\n')
    with pytest.raises(RuntimeError, match="can't allocate"):
        train("ps-fcn", cfg, tmp_path / "run", device="cpu", make_stream=failing_at(2))
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["log.jsonl"]
    assert (tmp_path / "run" / "log.jsonl").read_text() == '{"step": 2}\n'
    # after a validation (8 samples: two batches of 4) best.pt is kept, with the log that says what it is
    with pytest.raises(RuntimeError, match="can't allocate"):
        train("ps-fcn", cfg, tmp_path / "v", device="cpu", make_stream=failing_at(3))
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["best.pt", "log.jsonl"]
    assert '"val_mae"' in (tmp_path / "v" / "log.jsonl").read_text()
    with pytest.raises(PsctlError, match="holds the best.pt of a run that failed before its first checkpoint"):
        train("ps-fcn", cfg, tmp_path / "v", device="cpu")
    # a first checkpoint that fails half-way (a full disk at model.pt) leaves none of its parts
    import psctl.models.weights as weights

    real = weights.save_weights

    def full_disk(path, *a, **k):
        if Path(path).name.endswith("model.pt"):  # its staged name (.next.model.pt)
            raise OSError(28, "No space left on device", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(weights, "save_weights", full_disk)
    with pytest.raises(OSError, match="No space"):
        train("ps-fcn", merge(tiny(48), {"train": {"checkpoint_minutes": 0, "val_every": 1000}}), tmp_path / "c",
              device="cpu")
    assert not (tmp_path / "c").exists()
    monkeypatch.undo()
    (tmp_path / "mine").mkdir()  # a folder the user made stays, emptied of what the run wrote
    with pytest.raises(RuntimeError, match="can't allocate"):
        train("ps-fcn", cfg, tmp_path / "mine", device="cpu", make_stream=failing_at(2))
    assert (tmp_path / "mine").is_dir() and not any((tmp_path / "mine").iterdir())
    st = train("ps-fcn", cfg, tmp_path / "mine", device="cpu")  # and takes the run
    assert st["finished"] and (tmp_path / "mine" / "best.pt").is_file()
    # after a checkpoint a failure keeps the run, to resume
    with pytest.raises(RuntimeError, match="can't allocate"):
        train("ps-fcn", merge(cfg, {"train": {"samples": 96}}), tmp_path / "mine", resume=True, device="cpu",
              make_stream=failing_at(2))
    assert {"state.json", "model.pt", "best.pt", "log.jsonl"} <= {p.name for p in (tmp_path / "mine").iterdir()}


def test_a_progress_that_cannot_report_stops_the_run_at_a_checkpoint(tmp_path):
    """The CLI's progress returns STOP once stderr's reader is gone; the run then stops as on a
    signal (SIGPIPE), checkpointed, instead of dying without a checkpoint. Another value (tqdm's
    update returns True) stops nothing."""
    import signal

    from psctl.train import STOP

    st = train("ps-fcn", tiny(16), tmp_path / "truthy", device="cpu", progress=lambda rec: True)
    assert st["finished"] and st["signal"] is None
    calls = []
    st = train("ps-fcn", merge(tiny(64), {"train": {"log_every": 2}}), tmp_path / "run", device="cpu",
               progress=lambda rec: calls.append(rec) or STOP)
    assert len(calls) == 1 and st["signal"] == signal.SIGPIPE and not st["finished"]
    assert st["samples"] == calls[0]["samples"] == 8 and (tmp_path / "run" / "state.json").is_file()
    st = train("ps-fcn", None, tmp_path / "run", resume=True, device="cpu", progress=lambda rec: None)
    assert st["finished"] and st["samples"] == 64 and st["signal"] is None

def test_resume_continues_exactly(tmp_path):
    """24 + 24 samples with a stop in between == 48 samples in one go."""
    cfg = tiny(48)
    a = train("ps-fcn", cfg, tmp_path / "a", device="cpu")
    half = merge(cfg, {"train": {"samples": 24}})
    train("ps-fcn", half, tmp_path / "b", device="cpu")
    b = train("ps-fcn", cfg, tmp_path / "b", resume=True, device="cpu")
    assert a["samples"] == b["samples"] == 48
    wa = read_weights(tmp_path / "a" / "model.pt").state_dict
    wb = read_weights(tmp_path / "b" / "model.pt").state_dict
    diff = max((wa[k] - wb[k]).abs().max().item() for k in wa)
    assert diff < 1e-5, diff
    # without +N the file records the exposure it was trained at: the centre of data.exposure
    assert read_weights(tmp_path / "a" / "model.pt").metadata["input_mean"] == pytest.approx((0.1 * 0.5) ** 0.5, rel=1e-5)


def test_resume_keeps_the_runs_recipe(tmp_path):
    cfg = tiny(16)
    train("ps-fcn", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu")
    with pytest.raises(PsctlError, match=r"another recipe \(train.lr differs\)"):  # which key (an audit: none named)
        train("ps-fcn", merge(cfg, {"train": {"lr": 0.5}}), tmp_path / "run", resume=True, device="cpu")
    with pytest.raises(PsctlError, match=r"another recipe \(data.noise, train.lr differ\)"):
        train("ps-fcn", merge(cfg, {"train": {"lr": 0.5}, "data": {"noise": 0.1}}), tmp_path / "run", resume=True,
              device="cpu")
    with pytest.raises(PsctlError, match=r"nope: no such run folder to resume"):
        train("ps-fcn", None, tmp_path / "nope", resume=True, device="cpu")
    st = train("ps-fcn", None, tmp_path / "run", resume=True, device="cpu")  # the saved recipe: 8 samples
    assert st["samples"] == 8 and st["config"]["train"]["samples"] == 8
    st = train("ps-fcn", cfg, tmp_path / "run", resume=True, device="cpu")  # a longer run is allowed
    assert st["samples"] == 16


def test_a_run_from_before_a_new_recipe_key_resumes(tmp_path):
    """Keys added to the recipe since a run started take their defaults on resume (a real CPU
    run died with a KeyError when train.init was added)."""
    cfg = tiny(16)
    train("ps-fcn", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu")
    state = tmp_path / "run" / "state.json"
    st = json.loads(state.read_text())
    del st["config"]["train"]["init"]
    state.write_text(json.dumps(st))
    assert train("ps-fcn", None, tmp_path / "run", resume=True, device="cpu")["samples"] == 8
    assert train("ps-fcn", cfg, tmp_path / "run", resume=True, device="cpu")["samples"] == 16


def test_a_run_from_before_the_run_options_were_refused_resumes(tmp_path):
    """A recipe could give data.seed or val.data.batch_size until session 67, which the run
    overrode with its own (train.seed, val.batch_size): such a run resumes, with or without its
    recipe file edited (the keys moved), and goes on exactly as it would have."""
    cfg = tiny(16)
    train("ps-fcn", cfg, tmp_path / "a", device="cpu")
    train("ps-fcn", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu")
    state = tmp_path / "run" / "state.json"
    st = json.loads(state.read_text())
    st["config"]["data"]["seed"] = 99  # as an old run's recipe recorded it
    st["config"]["val"]["data"] = {"batch_size": 3}
    state.write_text(json.dumps(st))
    assert train("ps-fcn", None, tmp_path / "run", resume=True, device="cpu")["samples"] == 8
    b = train("ps-fcn", cfg, tmp_path / "run", resume=True, device="cpu")  # the edited recipe: no such keys
    assert b["samples"] == 16
    wa = read_weights(tmp_path / "a" / "model.pt").state_dict
    wb = read_weights(tmp_path / "run" / "model.pt").state_dict
    assert max((wa[k] - wb[k]).abs().max().item() for k in wa) < 1e-5


def test_a_run_resumes_with_its_recipe_now_naming_the_method(tmp_path):
    """The recipes in configs/ gained a ``method:`` key in session 50: runs started from them
    before resume with the edited file (the key is a label the run's method already checks)."""
    cfg = tiny(16)
    train("ps-fcn", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu")
    assert train("ps-fcn", {**cfg, "method": "ps-fcn"}, tmp_path / "run", resume=True, device="cpu")["samples"] == 16
    with pytest.raises(PsctlError, match="is a ps-fcn run, and the recipe's 'method' is 'lcnet': resume without --config"):
        train("ps-fcn", {**cfg, "method": "lcnet"}, tmp_path / "run", resume=True, device="cpu")
    # the label in any case, as the command line takes method names (PS-FCN)
    assert train("PS-FCN", {**cfg, "method": "PS-FCN"}, tmp_path / "run", resume=True, device="cpu")["samples"] == 16


def test_shipped_recipes_name_their_method_and_fit_it():
    """Every recipe but tiny.yaml (for any method) says which network it trains, as
    docs/training.md's table does, so ``psctl train ps-fcn --config configs/ps_fcn_n_....yaml``
    (same shapes, another normalisation) is one line, not a silently wrong run."""
    import re

    from psctl.train import check_recipe, check_sizes

    table = {}
    for line in (REPO / "docs" / "training.md").read_text().splitlines():
        cells = line.strip().strip("|").split("|") if line.startswith("| `configs/") else []
        if len(cells) > 1:
            names, methods = re.findall(r"configs/(\w+\.yaml)", cells[0]), re.findall(r"`([\w-]+)`", cells[1])
            table.update(zip(names, methods if len(methods) == len(names) else methods * len(names)))
    for recipe in sorted((REPO / "configs").glob("*.yaml")):
        cfg = load_config(recipe)
        if recipe.name == "tiny.yaml":
            assert "method" not in cfg
            continue
        assert cfg.get("method") in WEIGHTS_METHODS, recipe.name
        assert table.get(recipe.name) == cfg["method"], recipe.name  # and every recipe is in the table
        check_sizes(cfg["method"], check_recipe(cfg))


def test_a_run_without_its_optimiser_state_resumes_with_fresh_moments(tmp_path):
    """configs/gpu_session.sh restores a run from model.pt and state.json alone (the Adam state
    is too large to bring back from every GPU call) by listing no optimiser files."""
    cfg = tiny(16)
    train("ps-fcn", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu")
    for f in (tmp_path / "run").glob("optim.*.pt"):
        f.unlink()
    state = tmp_path / "run" / "state.json"
    st = json.loads(state.read_text())
    with pytest.raises(PsctlError, match="optim.*missing"):  # listed but missing: not silently fresh
        train("ps-fcn", cfg, tmp_path / "run", resume=True, device="cpu")  # (lengthened: a finished run is not read)
    st["optim_files"] = []
    state.write_text(json.dumps(st))
    before = read_weights(tmp_path / "run" / "model.pt").state_dict
    st = train("ps-fcn", cfg, tmp_path / "run", resume=True, device="cpu")
    after = read_weights(tmp_path / "run" / "model.pt").state_dict
    assert st["samples"] == 16 and any((before[k] - after[k]).abs().max() > 0 for k in before)


def test_merge_keeps_the_recipe_data_section():
    cfg = merge(tiny(), {"data": {"intensities": "random"}})
    assert cfg["data"]["intensities"] == "random" and cfg["data"]["size"] == 32 and cfg["data"]["pool"] == 2


def test_data_windows_is_refused_outside_ps_fcn_dagger(tmp_path):
    cfg = tiny(8)
    with pytest.raises(PsctlError, match="data.windows"):
        train("ps-fcn-n", merge(cfg, {"data": {"windows": 16}}), tmp_path / "run", device="cpu")
    assert not (tmp_path / "run").exists()


def test_val_data_changes_the_validation_stream_only(tmp_path):
    from psctl.train import synth_stream

    seen = []

    def recording(data, **kw):
        seen.append((kw["seed"], dict(data)))
        return synth_stream(data, **kw)

    cfg = merge(tiny(8), {"val": {"data": {"lights": "diligent"}}})
    train("ps-fcn", cfg, tmp_path / "run", device="cpu", make_stream=recording)
    val_seed = cfg["val"]["seed"]
    assert [d.get("lights") for s, d in seen if s == val_seed] == ["diligent"]
    assert all(d.get("lights") != "diligent" for s, d in seen if s != val_seed) and len(seen) == 2
    with pytest.raises(PsctlError, match="unknown synth stream option"):
        train("ps-fcn", merge(tiny(8), {"val": {"data": {"light": "diligent"}}}), tmp_path / "bad", device="cpu")
    assert not (tmp_path / "bad").exists()  # refused before anything is written


def test_bad_config(tmp_path):
    (tmp_path / "c.yaml").write_text("train: {batchsize: 3}\n")
    with pytest.raises(PsctlError, match="batchsize"):
        load_config(tmp_path / "c.yaml")
    (tmp_path / "d.yaml").write_text("train: [1, 2\n")
    with pytest.raises(PsctlError, match="YAML"):
        load_config(tmp_path / "d.yaml")


def test_refuses_to_overwrite_a_run(tmp_path):
    train("ps-fcn", tiny(8), tmp_path / "run", device="cpu")
    with pytest.raises(PsctlError, match="--resume"):
        train("ps-fcn", tiny(8), tmp_path / "run", device="cpu")


def test_amp_settings_follow_device_and_cpu():
    from psctl.infer import cpu_has_bf16
    from psctl.train import amp_settings

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert amp_settings("bf16", cuda) == (True, torch.bfloat16)
    assert amp_settings("fp16", cuda) == (True, torch.float16)
    assert amp_settings("fp16", cpu)[0] is False  # fp16 autocast is CUDA only here
    assert amp_settings("none", cpu)[0] is False and amp_settings("none", cuda)[0] is False
    # bf16 on the CPU only where it is native: emulated bf16 is slower than float32
    assert amp_settings("bf16", cpu) == (cpu_has_bf16(), torch.bfloat16)


def test_cpu_bf16_means_the_cpu_flags_not_onednn_emulation():
    """oneDNN reports bf16 'supported' on any AVX-512 CPU, emulating it where AVX512-BF16 is
    missing (3x slower than float32 for PS-FCN there); psctl trains in bf16 only on the flags."""
    from psctl.infer import cpu_has_bf16

    info = Path("/proc/cpuinfo")
    if not info.exists():
        pytest.skip("no /proc/cpuinfo to compare with")
    flags = info.read_text().split()
    assert cpu_has_bf16() == ("avx512_bf16" in flags or "amx_bf16" in flags or "amx_tile" in flags)


def test_install_stores_float16_when_float32_is_over_the_limit(tmp_path, monkeypatch):
    import psctl.train as T
    from psctl.models.weights import load_network

    run = tmp_path / "run"
    train("ps-fcn", tiny(16), run, device="cpu")
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "w"))
    small = T.install_weights(run, "ps-fcn")  # under the limit: a byte copy
    assert small.read_bytes() == (run / "best.pt").read_bytes()
    with pytest.raises(PsctlError, match="already installed"):  # a release file is replaced on purpose only
        T.install_weights(run, "ps-fcn")
    # what psctl train --install checks before training, for Python too; names as the CLI takes them
    with pytest.raises(PsctlError, match="already installed"):
        T.check_install("PS-FCN")
    T.check_install("ps-fcn", replace=True)
    T.check_install("ps-fcn-n")
    assert T.check_method("PS-FCN-N") == "ps-fcn-n"
    with pytest.raises(PsctlError, match="cannot install 'ps-fcn-x'"):
        T.check_install("PS-FCN-X")
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "file"))
    with pytest.raises(PsctlError, match="is not a folder: --install writes the weights there"):
        T.check_install("ps-fcn")
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "w"))
    monkeypatch.setattr(T, "RELEASE_MAX_BYTES", small.stat().st_size - 1)
    half = T.install_weights(run, "ps-fcn", replace=True)
    w = read_weights(half)
    assert w.metadata["stored_dtype"] == "float16" and half.stat().st_size < (run / "best.pt").stat().st_size
    assert all(v.dtype == torch.float16 for v in w.state_dict.values() if v.is_floating_point())
    model, _, _ = load_network("ps-fcn", half)  # loads into float32 parameters
    ref = read_weights(run / "best.pt").state_dict
    for k, v in model.state_dict().items():
        assert v.dtype == torch.float32 and torch.allclose(v, ref[k], rtol=1e-3, atol=1e-4)
    monkeypatch.setattr(T, "RELEASE_MAX_BYTES", 100)
    with pytest.raises(PsctlError, match="even in float16"):
        T.install_weights(run, "ps-fcn", replace=True)
    assert read_weights(half).metadata["stored_dtype"] == "float16"  # the last good file is kept
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["ps_fcn.pt"]


def test_install_refuses_a_file_without_its_validation(tmp_path, monkeypatch):
    """A release file records its own validation (the model card quotes it): an average made without
    --config has none and is refused, named, before anything in the weights folder changes."""
    import psctl.train as T

    run = tmp_path / "run"
    train("ps-fcn", tiny(16), run, device="cpu")
    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "w"))
    import shutil

    twin = shutil.copy(run / "best.pt", tmp_path / "twin.pt")  # one path twice is refused
    bare = T.average_weights([run / "best.pt", twin], tmp_path / "avg")
    with pytest.raises(PsctlError, match="no synthetic validation") as e:
        T.install_weights(tmp_path / "avg", "ps-fcn")
    assert str(bare) in str(e.value) and not (tmp_path / "w").exists()
    with pytest.raises(PsctlError, match=r"'data.batch_size' is set by the run"):  # checked as training's (a review)
        T.average_weights([run / "best.pt", twin], tmp_path / "avg_bad", config=merge(tiny(16), {"data": {"batch_size": 8}}))
    T.average_weights([run / "best.pt", twin], tmp_path / "avg_val", config=tiny(16))
    assert T.install_weights(tmp_path / "avg_val", "ps-fcn").is_file()
    (run / "best.pt").unlink()  # validated, then removed: said so, not "no best weights yet" (a review)
    with pytest.raises(PsctlError, match="best.pt: is missing: the run's best validation was saved there"):
        T.install_weights(run, "ps-fcn", replace=True)
    (tmp_path / "fresh").mkdir()
    with pytest.raises(PsctlError, match="best.pt: no best weights in this run yet"):
        T.install_weights(tmp_path / "fresh", "ps-fcn", replace=True)  # (no state.json there)


_FAULTS_AFTER_FREE = """
import resource, sys, torch
from psctl.train import keep_freed_memory
if sys.argv[1] == "keep" and not keep_freed_memory():
    print("unsupported"); sys.exit()
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
x = torch.empty(64 << 20); x.fill_(1); del x          # 256 MB: the size of a training activation
before = faults(); y = torch.empty(60 << 20); y.fill_(1)  # a slightly smaller one fits in the freed block
print(faults() - before)
"""


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux")
def test_keep_freed_memory_reuses_pages_instead_of_faulting_them_in_again():
    """Without it glibc unmaps a freed 256 MB block and the next one is zeroed page by page."""
    import subprocess
    import sys

    def run(mode: str) -> str:
        return subprocess.run([sys.executable, "-c", _FAULTS_AFTER_FREE, mode], capture_output=True, text=True,
                              check=True).stdout.split()[-1]

    kept = run("keep")
    if kept == "unsupported":
        pytest.skip("the C library is not glibc")
    pages = (60 << 22) // 4096
    assert int(run("default")) > pages // 2  # the default really faults (else the test proves nothing)
    assert int(kept) < pages // 20


@pytest.mark.parametrize("recipe", sorted(p.name for p in (REPO / "configs").glob("*.yaml")))
def test_shipped_recipes_load_and_their_data_validate(recipe):
    """Every recipe in configs/ parses, has only known keys, and its data section is a valid
    stream config (a typo in a GPU recipe would otherwise surface only on the GPU)."""
    from psctl.synth.stream import make_config

    cfg = load_config(REPO / "configs" / recipe)
    data = make_config(cfg["data"], crop=cfg["train"]["crop"])
    assert data["n_images"] > 0 and cfg["train"]["samples"] > 0


@pytest.mark.parametrize("text,needle", [
    ("train: {lr: 1e-3}", "'train.lr' must be a finite number \\(write 1.0e-3"),
    ("train: {lr: .inf}", "'train.lr' must be a finite number, not inf"),
    ("train: {lr: 1" + "0" * 400 + "}", "'train.lr' must be a finite number"),
    ("train: {batch_size: four}", "'train.batch_size' must be a finite integer"),
    ("train: {batch_size: 4.5}", "'train.batch_size' must be a finite integer"),
    ("train: {checkpoint_minutes: -1.0}", "'train.checkpoint_minutes' must be 0 or more"),
    ("train: {batch_size: -4}", "'train.batch_size' must be positive"),
    ("train: {amp: fp8}", "'train.amp' must be one of bf16, fp16, none"),
    ("train: {betas: [0.9]}", "'train.betas' must be a list of 2 numbers"),
    ("train: {channels_last: 1}", "'train.channels_last' must be true or false"),
    ("", "config file is empty"),
    # found by a review: tracebacks, or accepted without a word
    ("train: 5", "section 'train' must be a mapping"),
    ("data: null", "section 'data' must be a mapping"),
    ("val: {data: 5}", "'val.data' must be a mapping"),
    ("data: {size: big}", "'size' must be a finite integer"),
    ("data: {noise: x}", "'noise' must be a finite number"),
    ("data: {noise: .nan}", "'noise' must be a finite number"),
    ("data: {blend: x}", "'blend' must be a finite number"),
    ("data: {texture: 1.5}", "'texture' is a chance"),
    ("data: {rotate: 'no'}", "'rotate' must be true or false"),
    ("data: {exposure: [0.5]}", "'exposure' must be \\[lo, hi\\]"),
    ("data: {exposure: [0.5, 0.1]}", "'exposure' must be \\[lo, hi\\]"),
    ("data: {clip: -1}", "'clip' must be a positive number"),
    ("data: {ambient: -1}", "'ambient' must be 0 or more"),
    ("data: {pool: 0}", "'pool' must be positive"),
    ("data: {pool: abc}", "'pool' must be a finite integer"),
    ("data: {capture: 5}", "'capture': expected a mapping"),
    ("data: {materials: {plastic: 1.0}}", "'materials': unknown plastic"),
    ("data: {shapes: {teapot: 1.0}}", "'shapes': unknown teapot"),
    ("normalization: bogus", "'normalization' must be one of none, per-channel, per-pixel"),
    ("train: {betas: [2.0, 0.999]}", "'train.betas' must be two numbers in \\[0, 1\\)"),
    ("train: {seed: 99999999999999999999}", "'train.seed' must be"),
    ("train: {lr: 1.0e-3, lr: 2.0e-3}", "duplicate key 'lr'"),
    ("train: {? [1, 2] : 3}", "not valid YAML"),  # an unhashable key: one line, not a TypeError
])
def test_recipe_values_are_checked_with_the_file(tmp_path, text, needle):
    from psctl.train import load_config

    cfg = tmp_path / "r.yaml"
    cfg.write_text(text + "\n")
    with pytest.raises(PsctlError, match=needle) as e:
        load_config(cfg)
    assert e.value.path == str(cfg)


def test_bad_run_folders_are_one_error(tmp_path):
    from psctl.train import train

    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(PsctlError, match="is a file"):
        train("ps-fcn", None, f, device="cpu")
    run = tmp_path / "run"
    run.mkdir()
    (run / "state.json").write_text("{not json")
    with pytest.raises(PsctlError, match="not a readable run state"):
        train("ps-fcn", None, run, resume=True, device="cpu")


def test_a_new_run_needs_a_new_or_empty_folder_and_removes_only_its_own_files(tmp_path):
    """--out into someone's folder appended to their log.jsonl and deleted their optim.*.pt."""
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "optim.backup.pt").write_bytes(b"mine")
    with pytest.raises(PsctlError, match="is not empty and holds no run"):
        train("ps-fcn", tiny(8), theirs, device="cpu")
    assert sorted(p.name for p in theirs.iterdir()) == ["optim.backup.pt"]
    foreign = tmp_path / "foreign"  # a log.jsonl that is not a run's: not appended to (a review's finding)
    foreign.mkdir()
    (foreign / "log.jsonl").write_text("my own log line 1\nline 2\n")
    with pytest.raises(PsctlError, match="log.jsonl: is not a psctl training log"):
        train("ps-fcn", tiny(8), foreign, device="cpu")
    assert (foreign / "log.jsonl").read_text() == "my own log line 1\nline 2\n"
    cut = tmp_path / "cut"  # a stopped run's log whose last record a kill cut short: started again, and the
    cut.mkdir()  # cut record dropped (the new first one was glued to it, and the next start refused it: a review)
    (cut / "log.jsonl").write_text('{"samples": 8, "loss": 0.5}\n{"samples": 16, "lo')
    train("ps-fcn", tiny(8), cut, device="cpu")
    lines = (cut / "log.jsonl").read_text().splitlines()
    assert lines[0] == '{"samples": 8, "loss": 0.5}' and all(isinstance(json.loads(x), dict) for x in lines), lines
    stopped = tmp_path / "stopped"  # only the log of a run that never checkpointed: started again
    stopped.mkdir()
    (stopped / "log.jsonl").write_text('{"step": 1}\n')
    with pytest.raises(PsctlError, match="stopped before its first checkpoint"):  # --resume: what to do instead
        train("ps-fcn", tiny(8), stopped, resume=True, device="cpu")
    assert train("ps-fcn", tiny(8), stopped, device="cpu")["samples"] == 8
    run = tmp_path / "run"
    train("ps-fcn", tiny(8), run, device="cpu")
    (run / "optim.7.pt").write_bytes(b"not the run's")  # not listed in state.json: left alone
    train("ps-fcn", tiny(16), run, resume=True, device="cpu")
    assert (run / "optim.7.pt").read_bytes() == b"not the run's"


@pytest.mark.parametrize("damage, needle", [
    ("truncate optim", "optim.0.pt: cannot be read"),
    ("empty optim", "optim.0.pt: cannot be read"),
    ("other optim", "optim.0.pt: is not a part of an optimiser state"),
    ("truncate stream", "stream.pt: cannot be read"),
    ("delete stream", "stream.pt: is missing"),
    ("other model", "model.pt: holds ps-fcn-n weights, not this ps-fcn run's"),
    ("other best", "best.pt: holds ps-fcn-n weights, not this ps-fcn run's"),
    ("garble optim", "optim.0.pt: is not a torch file psctl wrote"),
])
def test_a_damaged_run_is_one_error_on_resume(tmp_path, damage, needle):
    run = tmp_path / "run"
    train("ps-fcn", tiny(8), run, device="cpu")
    what, name = damage.split()
    f = run / {"optim": "optim.0.pt", "stream": "stream.pt", "model": "model.pt", "best": "best.pt"}[name]
    if what == "truncate":
        f.write_bytes(f.read_bytes()[:100])
    elif what == "empty":
        f.write_bytes(b"")
    elif what == "garble":
        f.write_bytes(bytes(range(256)) * 4)
    elif what == "other" and name in ("model", "best"):  # PS-FCN+N's file: the same shapes
        w = read_weights(run / "model.pt")
        from psctl.models.weights import save_weights

        save_weights(f, w.state_dict, {**w.metadata, "method": "ps-fcn-n", "normalization": "per-channel"})
    elif what == "other":
        torch.save({"x": torch.zeros(3)}, f)
    else:
        f.unlink()
    with pytest.raises(PsctlError, match=needle):
        train("ps-fcn", tiny(16), run, resume=True, device="cpu")


def test_warmup_ramps_the_learning_rate_then_the_halving_schedule_holds():
    from psctl.train import DEFAULT_CONFIG, lr_at

    cfg = merge(DEFAULT_CONFIG, {"train": {"lr": 1e-4, "lr_halve_every": 1000, "batch_size": 32, "warmup": 320}})
    rates = [lr_at(s, cfg) for s in (0, 96, 288, 320, 999, 1000)]
    assert rates[0] == pytest.approx(1e-5) and rates[1] == pytest.approx(4e-5)  # (samples + batch) / warmup
    assert rates[2] == rates[3] == rates[4] == pytest.approx(1e-4) and rates[5] == pytest.approx(5e-5)
    assert lr_at(0, merge(cfg, {"train": {"warmup": 0}})) == pytest.approx(1e-4)  # the default: none
    with pytest.raises(PsctlError, match="warmup"):
        from psctl.train import check_recipe

        check_recipe(merge(cfg, {"train": {"warmup": -5}}))


def test_average_weights_is_the_mean_and_says_of_what(tmp_path):
    """A uniform parameter average ("model soup") of two files of one network: the elementwise
    mean, runnable like any run's best.pt, its members listed; other networks are refused."""
    import hashlib

    import psctl.train as T
    from psctl.models.weights import for_method, load_network, save_weights

    run = tmp_path / "run"
    train("ps-fcn", tiny(16), run, device="cpu")
    a = read_weights(run / "best.pt")
    g = torch.Generator().manual_seed(0)
    b_state = {k: v + torch.randn(v.shape, generator=g) if v.is_floating_point() else v for k, v in a.state_dict.items()}
    b = save_weights(tmp_path / "b.pt", b_state, a.metadata)
    out = T.average_weights([run / "best.pt", b], tmp_path / "avg")
    w = read_weights(out)
    for k, v in a.state_dict.items():
        assert torch.allclose(w.state_dict[k], (v + b_state[k]) / 2, atol=1e-6), k
    m = w.metadata
    assert m["method"] == "ps-fcn" and m["architecture"] == a.metadata["architecture"]
    assert m["input_mean"] == a.metadata["input_mean"] and m["samples_seen"] == 2 * a.metadata["samples_seen"]
    assert [x["sha256"] for x in m["averaged_from"]] == [hashlib.sha256(p.read_bytes()).hexdigest() for p in (run / "best.pt", b)]
    assert m["metrics"] == {}  # nothing measured: the rule decides
    # each member says where and how it trained and what it started from (an average's own
    # device and precision only join the members' sets)
    for x in m["averaged_from"]:
        assert (x["device"], x["precision"], x["init"]) == (a.metadata["device"], a.metadata["precision"], a.metadata.get("init"))
    assert m["precision"] == a.metadata["precision"]  # the members' training precision, not the averaging's
    assert for_method(w, "ps-fcn") == for_method(a, "ps-fcn")  # same input scale and clip at inference
    load_network("ps-fcn", out)
    # measured on a recipe's set: the average of a file with itself scores what training logged for it
    import shutil

    twin = shutil.copy(run / "best.pt", tmp_path / "twin.pt")
    same = read_weights(T.average_weights([run / "best.pt", twin], tmp_path / "same", config=tiny(16)))
    assert same.metadata["metrics"]["synthetic_val_mae"] == pytest.approx(a.metadata["metrics"]["synthetic_val_mae"], abs=1e-3)
    assert same.metadata["validation"]["val"] == tiny(16)["val"]
    with pytest.raises(PsctlError, match="already exists"):
        T.average_weights([run / "best.pt", b], tmp_path / "avg")
    with pytest.raises(PsctlError, match="at least two"):
        T.average_weights([b], tmp_path / "one")
    with pytest.raises(PsctlError, match="is given twice"):
        T.average_weights([b, tmp_path / "." / "b.pt"], tmp_path / "twice")
    other = save_weights(tmp_path / "n.pt", a.state_dict, {**a.metadata, "method": "ps-fcn-n", "normalization": "per-channel"})
    with pytest.raises(PsctlError, match="n.pt: metadata 'method'"):
        T.average_weights([b, other], tmp_path / "mixed")
    small = {k: v[:1] if v.ndim else v for k, v in a.state_dict.items()}
    with pytest.raises(PsctlError, match="names or shapes"):
        T.average_weights([b, save_weights(tmp_path / "s.pt", small, a.metadata)], tmp_path / "shapes")
    assert not (tmp_path / "mixed").exists() and not (tmp_path / "shapes").exists()  # checked before anything is written


def test_validation_batches_apply_val_data():
    """benchmarks/val_compare.py rebuilds the training loop's set through validation_batches:
    val.data overrides data there (it did not once, so a recipe pinning val.data.scale failed)."""
    from psctl.train import validation_batches

    seen = []

    class Stub:
        def next_batch(self):
            return {}

    def make_stream(data, **kw):
        seen.append((data, kw))
        return Stub()

    cfg = merge(tiny(), {"data": {"scale": [32, 320], "scale_law": "log"},
                         "val": {"samples": 5, "batch_size": 2, "data": {"scale": None, "scale_law": "uniform"}}})
    assert len(validation_batches(cfg, torch.device("cpu"), make_stream)) == 3
    data, kw = seen[0]
    assert data["scale"] is None and data["scale_law"] == "uniform" and data["pool"] == cfg["data"]["pool"]
    assert kw["seed"] == cfg["val"]["seed"] and kw["crop"] == cfg["val"]["size"]


def test_validation_set_is_rendered_on_the_cpu_whatever_the_device():
    """The set is drawn on the CPU and moved to the training device: CUDA's generator gives
    other numbers for the same seed, so a set drawn there was another set (session 44)."""
    from psctl.train import Task, validation_set

    devices = []

    class Stub:
        def next_batch(self):
            return {"images": torch.ones(2, 3), "shapes": ["a", "b"]}

    def make_stream(data, **kw):
        devices.append(kw["device"])
        return Stub()

    task = Task(None, None, lambda b: (b["images"], b["shapes"]), None, "mae", {})
    cfg = merge(tiny(), {"val": {"samples": 4, "batch_size": 2}})
    items = validation_set(cfg, task, torch.device("meta"), make_stream)  # any device but the CPU
    assert devices == [torch.device("cpu")] and len(items) == 2
    assert all(x.device.type == "meta" and names == ["a", "b"] for x, names in items)


def test_recipes_may_use_yaml_merge_keys(tmp_path):
    cfg = tmp_path / "r.yaml"
    cfg.write_text("train: {batch_size: 4, samples: 8}\nval: {<<: {samples: 4}, images: 8}\n")
    assert load_config(cfg)["val"]["samples"] == 4


def test_a_second_ctrl_c_waits_for_the_checkpoint_being_written():
    """Two quick Ctrl-C: the first asks for a checkpoint, the second leaves at once, but not
    halfway through writing it (optimiser files without state.json: a run --resume refuses)."""
    import signal

    from psctl.checkpoint import Stop

    stop = Stop()
    written = []
    with pytest.raises(KeyboardInterrupt):
        with stop.whole():
            stop._handle(signal.SIGINT, None)
            stop._handle(signal.SIGINT, None)  # deferred
            written.append("state.json")
    assert written == ["state.json"] and stop.signal == signal.SIGINT
    with pytest.raises(KeyboardInterrupt):  # outside a checkpoint, as before
        stop._handle(signal.SIGINT, None)


def test_network_inputs_divide_by_intensities_only_for_calibrated_methods():
    """PS-FCN sees images divided by their (known) intensities, as the capture reader gives
    them; UPS-FCN, which has no lights, sees the images as captured."""
    from psctl.train import network_inputs

    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 3, 3, 4, 4, generator=g)
    e = torch.tensor([[0.5, 1.0, 2.0], [1.5, 0.25, 1.0]])
    lights = torch.nn.functional.normalize(torch.rand(2, 3, 3, generator=g), dim=-1)
    batch = {"images": images, "intensities": e, "lights": lights}
    x, l = network_inputs(batch, lights=True, normalization="none")
    assert torch.allclose(x, images / e[:, :, None, None, None]) and l is lights
    x, l = network_inputs(batch, lights=False, normalization="none")
    assert torch.equal(x, images) and l is None


def test_crop_windows_takes_rows_then_columns():
    from psctl.train import crop_windows

    x = torch.arange(2 * 3 * 8 * 8, dtype=torch.float32).reshape(2, 3, 8, 8)
    w = torch.tensor([[1, 4], [5, 0]])
    out = crop_windows(x, w, 3)
    assert torch.equal(out[0], x[0, :, 1:4, 4:7]) and torch.equal(out[1], x[1, :, 5:8, 0:3])


@pytest.mark.parametrize("decode", ["argmax", "soft"])
def test_ps_fcn_dagger_sees_lcnets_lights_and_intensities(tmp_path, decode):
    from psctl.models.lcnet import LCNet
    from psctl.models.weights import load_network, save_weights
    from psctl.synth.stream import SynthStream
    from psctl.train import load_config, merge, normals_task

    torch.manual_seed(0)
    save_weights(tmp_path / "lc.pt", LCNet({"size": 32}), {"method": "lcnet", "train_images": 8})
    cfg = load_config(REPO / "configs" / "tiny.yaml")
    cfg = merge(cfg, {"data": {**cfg["data"], "size": 32, "windows": 16}, "lcnet": {"decode": decode}})
    task = normals_task("ps-fcn-dagger", cfg, torch.device("cpu"), contextlib.nullcontext, tmp_path / "lc.pt")
    b = SynthStream({"batch_size": 2, "n_images": 8, "size": 32, "crop": 32, "pool": 2, "shapes": {"blobby": 1.0},
                     "intensities": "random", "windows": 16}, seed=4).next_batch()
    x, l, n, m = task.val_item(b)
    lc = load_network("lcnet", tmp_path / "lc.pt")[0]
    dirs, ints = lc.estimate(b["images"], b["masks"], decode)
    assert x.shape[-1] == 32  # validated on the whole view
    torch.testing.assert_close(l, dirs.float())
    assert not torch.allclose(l, b["lights"], atol=1e-3)
    torch.testing.assert_close(x, b["images"] / ints.float()[:, :, None, None, None])


def test_best_pt_is_the_best_validation(tmp_path, monkeypatch):
    import psctl.train as T
    from psctl.models.weights import read_weights

    scores = iter([5.0, 3.0, 4.0])
    monkeypatch.setattr(T, "evaluate", lambda task, val: next(scores))
    cfg = T.load_config(REPO / "configs" / "tiny.yaml")
    cfg = T.merge(cfg, {"train": {"samples": 24, "val_every": 8}})
    st = T.train("ps-fcn", cfg, tmp_path / "run", device="cpu")
    assert st["best_val"] == 3.0 and st["best_samples"] == 16
    meta = read_weights(tmp_path / "run" / "best.pt").metadata
    assert meta["metrics"]["synthetic_val_mae"] == 3.0 and meta["samples_seen"] == 16


def test_wall_seconds_count_the_whole_run(tmp_path, monkeypatch):
    import psctl.train as T
    from psctl.models.weights import read_weights

    scores = iter([1.0, 2.0])  # the last validation is no improvement: nothing saves the time then
    monkeypatch.setattr(T, "evaluate", lambda task, val: next(scores))

    def slow_stream(*a, **k):
        s = T.synth_stream(*a, **k)
        real = s.next_batch

        def next_batch():
            time.sleep(0.5)
            return real()

        s.next_batch = next_batch
        return s

    st = T.train("ps-fcn", merge(tiny(24), {"train": {"val_every": 12}}), tmp_path / "run", device="cpu", make_stream=slow_stream)
    assert st["seconds"] >= 3.0  # six steps of at least 0.5 s
    assert read_weights(tmp_path / "run" / "model.pt").metadata["wall_seconds"] >= 3.0


def test_a_resumed_run_validates_on_the_same_schedule(tmp_path):
    from psctl.train import train

    a = train("ps-fcn", merge(tiny(16), {"train": {"val_every": 8}}), tmp_path / "a", device="cpu")
    train("ps-fcn", merge(tiny(8), {"train": {"val_every": 8}}), tmp_path / "b", device="cpu")
    b = train("ps-fcn", merge(tiny(16), {"train": {"val_every": 8}}), tmp_path / "b", resume=True, device="cpu")
    assert [s for s, _ in a["val"]] == [s for s, _ in b["val"]] == [8, 16]


def test_average_adds_wall_times_and_refuses_other_lcnets(tmp_path):
    import psctl.train as T
    from psctl.errors import PsctlError
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import read_weights, save_weights

    meta = {"method": "ps-fcn-dagger", "train_images": 8, "lcnet": {"path": "lc1.pt"}}
    a = save_weights(tmp_path / "a.pt", PSFCN(), {**meta, "wall_seconds": 10.0, "samples_seen": 5})
    b = save_weights(tmp_path / "b.pt", PSFCN(), {**meta, "wall_seconds": 20.5, "samples_seen": 7})
    m = read_weights(T.average_weights([a, b], tmp_path / "avg")).metadata
    assert m["wall_seconds"] == 30.5 and m["samples_seen"] == 12 and m["lcnet"] == {"path": "lc1.pt"}
    c = save_weights(tmp_path / "c.pt", PSFCN(), {**meta, "lcnet": {"path": "lc2.pt"}})
    with pytest.raises(PsctlError, match="metadata 'lcnet'"):
        T.average_weights([a, c], tmp_path / "mixed")


def test_average_of_ps_fcn_dagger_is_measured_with_its_own_lcnet(tmp_path, monkeypatch):
    """--average --config measures PS-FCN† members on the lights of the LCNet they were trained
    with (their metadata's), not the recipe's or the installed one (none here)."""
    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import read_weights, save_weights
    from psctl.train import average_weights

    monkeypatch.setenv("PSCTL_WEIGHTS", str(tmp_path / "nothing installed"))
    torch.manual_seed(0)
    save_weights(tmp_path / "lc.pt", LCNet({"size": 32}), {"method": "lcnet", "train_images": 8})
    meta = {"method": "ps-fcn-dagger", "train_images": 8, "normalization": "none",
            "lcnet": {"path": str(tmp_path / "lc.pt"), "decode": "argmax"}}
    a = save_weights(tmp_path / "a.pt", PSFCN(), meta)
    b = save_weights(tmp_path / "b.pt", PSFCN(), meta)
    cfg = load_config(REPO / "configs" / "tiny.yaml")
    cfg = merge(cfg, {"data": {**cfg["data"], "size": 32}})
    m = read_weights(average_weights([a, b], tmp_path / "avg", config=cfg)).metadata
    assert m["lcnet"]["path"] == str(tmp_path / "lc.pt") and "synthetic_val_mae" in m["metrics"]


def test_recipe_sizes_and_method_are_checked_before_the_run(tmp_path):
    """PS-FCN's crops and validation windows not a multiple of 4, or a recipe naming another
    method: one line before the run folder exists (a torch shape error minutes in before)."""
    from psctl.train import average_weights, train

    for section, key, value, words in (("train", "crop", 14, "config 'train.crop' must be a multiple of 4 for ps-fcn"),
                                       ("val", "size", 30, "config 'val.size' must be a multiple of 4 for ps-fcn")):
        cfg = tiny()
        cfg[section][key] = value
        with pytest.raises(PsctlError, match=words):
            train("ps-fcn", cfg, tmp_path / "r")
        assert not (tmp_path / "r").exists()
    cfg = tiny()
    cfg["method"] = "lcnet"
    with pytest.raises(PsctlError, match="config 'method' is 'lcnet': the recipe is for another network than ps-fcn; "
                                         "train lcnet with it, or choose a ps-fcn recipe"):
        train("ps-fcn", cfg, tmp_path / "r")
    cfg["method"] = "ps-fcn"  # the same method: allowed
    from psctl.train import check_sizes

    check_sizes("ps-fcn", cfg)
    check_sizes("ps-fcn", {**cfg, "method": "PS-FCN"})  # names in any case, as the command line takes them
    from psctl.models.weights import save_weights

    for name in ("a.pt", "b.pt"):
        save_weights(tmp_path / name, PSFCN(), {"method": "ps-fcn", "train_images": 8})
    cfg = tiny()
    cfg["val"]["size"] = 30
    with pytest.raises(PsctlError, match="val.size' must be a multiple of 4"):  # --average --config measures on val
        average_weights([tmp_path / "a.pt", tmp_path / "b.pt"], tmp_path / "avg", cfg)
    # psctl train names the recipe's file in these errors, as in its other recipe errors (a QA
    # helper's finding); a crop larger than the views says when the scale was left unset
    from tests.test_cli import cli

    tiny_text = (REPO / "configs" / "tiny.yaml").read_text()
    assert "crop: 16," in tiny_text
    for name, text, words in (("crop18.yaml", tiny_text.replace("crop: 16,", "crop: 18,"),
                               "config 'train.crop' must be a multiple of 4"),
                              ("other.yaml", "method: lcnet\n" + tiny_text, "config 'method' is 'lcnet'"),
                              ("big.yaml", tiny_text.replace("crop: 16,", "crop: 4096,"), "need 0 < crop <= size")):
        (tmp_path / name).write_text(text)
        r = cli("train", "ps-fcn", "--config", tmp_path / name, "--out", tmp_path / "r", "-q")
        assert r.returncode == 2 and f"{tmp_path / name}: {words}" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "r").exists()
    assert "(crop 4096, size 32, scale unset, so (crop, size);" in r.stderr


def test_a_normalization_the_method_cannot_train_with_is_refused_before_the_run(tmp_path):
    """A ps-fcn recipe with normalization: per-channel (or ps-fcn-n with none) trained, then died at
    its first save with the run folder removed (the weights' loader refuses such files; a QA
    helper's finding): refused before the run folder exists now, naming the recipe's file. And
    --average --config measured the averaged files with the recipe's normalization, not theirs
    (the same file scored 8.36 or 11.22): a recipe that disagrees is refused, naming its file."""
    from psctl.models.ps_fcn import PSFCN
    from psctl.models.weights import save_weights
    from psctl.train import average_weights, check_sizes
    from tests.test_cli import cli

    for method, norm in (("ps-fcn", "per-channel"), ("ps-fcn", "per-pixel"), ("ps-fcn-n", "none"), ("lcnet", "per-pixel")):
        cfg = {**tiny(), "normalization": norm}
        with pytest.raises(PsctlError, match=f"config 'normalization' is '{norm}', which {method} cannot train"):
            train(method, cfg, tmp_path / "r")
        assert not (tmp_path / "r").exists()
    for method, norm in (("ps-fcn", "none"), ("ps-fcn-n", "per-pixel"), ("ups-fcn", "per-channel"),
                         ("ps-fcn-dagger", "none"), ("ps-fcn", None)):
        check_sizes(method, {**tiny(), "normalization": norm})  # allowed
    tiny_text = (REPO / "configs" / "tiny.yaml").read_text()
    (tmp_path / "pc.yaml").write_text(tiny_text + "normalization: per-channel\n")
    r = cli("train", "ps-fcn", "--config", tmp_path / "pc.yaml", "--out", tmp_path / "r", "-q")
    assert r.returncode == 2 and f"{tmp_path / 'pc.yaml'}: config 'normalization' is 'per-channel'" in r.stderr, r.stderr
    assert not (tmp_path / "r").exists()
    # --average: ups-fcn files trained without +N, measured on a recipe asking for it
    for name in ("a.pt", "b.pt"):
        save_weights(tmp_path / name, PSFCN({"lights": False}), {"method": "ups-fcn", "train_images": 8,
                                                       "normalization": "none"})
    with pytest.raises(PsctlError, match="config 'normalization' is 'per-channel' but the averaged files were "
                                         "trained with 'none'"):
        average_weights([tmp_path / "a.pt", tmp_path / "b.pt"], tmp_path / "avg", {**tiny(), "normalization": "per-channel"})
    r = cli("train", "ups-fcn", "--average", tmp_path / "a.pt", "--average", tmp_path / "b.pt", "--out",
            tmp_path / "avg2", "--config", tmp_path / "pc.yaml", "-q")
    assert r.returncode == 2 and f"{tmp_path / 'pc.yaml'}: config 'normalization' is 'per-channel' but" in r.stderr, \
        r.stderr
    assert not (tmp_path / "avg2").exists()


def test_a_tampered_run_is_one_error_on_resume(tmp_path):
    """A review's fuzzing: an optimiser part copied over another (half of Adam's state lost, the
    run went on without a word), a state.json value of the wrong kind (a TypeError), and
    --average into a folder holding other files (written beside them)."""
    import json as _json

    import psctl.train as T

    run = tmp_path / "run"
    train("ps-fcn", tiny(8), run, device="cpu")
    parts = _json.loads((run / "state.json").read_text())["optim_files"]
    assert len(parts) >= 2  # PS-FCN's Adam state is split: the case below needs two parts
    (run / parts[1]).write_bytes((run / parts[0]).read_bytes())
    with pytest.raises(PsctlError, match=f"{parts[1]}: repeats another part's optimiser state"):
        train("ps-fcn", tiny(16), run, resume=True, device="cpu")
    (run / parts[1]).unlink()  # one part alone: the state of only some parameters
    st = _json.loads((run / "state.json").read_text())
    (run / "state.json").write_text(_json.dumps({**st, "optim_files": parts[:1]}))
    with pytest.raises(PsctlError, match=r"optimiser parts hold the state of \d+ of \d+ parameters"):
        train("ps-fcn", tiny(16), run, resume=True, device="cpu")
    (run / "state.json").write_text(_json.dumps({**st, "samples": "lots"}))
    with pytest.raises(PsctlError, match=r"state.json: holds a bad 'samples' \(\"lots\"\)"):
        train("ps-fcn", tiny(16), run, resume=True, device="cpu")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "a.txt").write_text("x")
    with pytest.raises(PsctlError, match="busy: is not empty"):
        T.average_weights([run / "best.pt", run / "model.pt"], tmp_path / "busy")
    assert sorted(p.name for p in (tmp_path / "busy").iterdir()) == ["a.txt"]


@pytest.mark.parametrize("lcnet, needle", [
    ({"ints_range": [2.0, 0.2]}, "lcnet.ints_range' must be two intensities 0 < low < high"),
    ({"ints_range": [0.0, 2.0]}, "lcnet.ints_range' must be two intensities 0 < low < high"),
    ({"dirs_cls": 1}, "lcnet.dirs_cls' must be 2 to 3,600 classes, not 1"),
    ({"ints_cls": 1}, "lcnet.ints_cls' must be 2 to 3,600 classes"),
    # a typo's millions: heads of gigabytes that the memory guard did not count (a review)
    ({"dirs_cls": 10_000_000}, "lcnet.dirs_cls' must be 2 to 3,600 classes, not 10000000"),
    # an audit: negative weights ran the loss away (-226 -> -1570), zero ones learnt nothing, exit 0
    ({"loss_weights": [-1.0, -1.0, -1.0]}, r"lcnet.loss_weights' must be three weights .* 0 or more and not all 0"),
    ({"loss_weights": [0.0, 0.0, 0.0]}, r"lcnet.loss_weights' must be three weights"),
])
def test_lcnet_class_settings_are_checked(lcnet, needle):
    """A review's fuzzing: a reversed intensity range and one class trained without a word."""
    from psctl.train import DEFAULT_CONFIG, check_recipe

    with pytest.raises(PsctlError, match=needle):
        check_recipe(merge(DEFAULT_CONFIG, {"lcnet": lcnet}))


def test_a_validation_seed_equal_to_the_training_seed_is_refused(tmp_path):
    """val.seed = train.seed drew the validation set as the first training samples, without a
    word (a QA helper's finding: the same images and normals): refused before the run."""
    cfg = merge(tiny(), {"val": {"seed": 7}, "train": {"seed": 7}})
    with pytest.raises(PsctlError, match=r"config 'val.seed' equals 'train.seed' \(7\): the validation set would "
                                         r"be drawn as the first training samples"):
        train("ps-fcn", cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()


def test_weights_paths_in_a_recipe_are_named_when_wrong(tmp_path):
    """train.init: 5 said 'weights must be a path ... not 5', naming neither file nor key."""
    from psctl.train import DEFAULT_CONFIG, check_recipe

    for cfg, key in (({"train": {"init": 5}}, "train.init"), ({"lcnet": {"weights": [1]}}, "lcnet.weights"),
                     ({"train": {"init": ""}}, "train.init")):  # "" was read as no file: random weights (an audit)
        with pytest.raises(PsctlError, match=f"config '{key}' must be a weights file's path"):
            check_recipe(merge(DEFAULT_CONFIG, cfg))
    junk = Path(tmp_path) / "junk.pt"  # a damaged start file is said to be the recipe's (an audit)
    junk.write_bytes(b"not torch")
    with pytest.raises(PsctlError, match=r"junk.pt: cannot read weights file.*\(the recipe's train.init\)"):
        train("ps-fcn", merge(tiny(8), {"train": {"init": str(junk)}}), Path(tmp_path) / "run", device="cpu")
    with pytest.raises(PsctlError, match=r"config 'train.warmup' \(1,000,000 samples\) is longer than the run"):
        check_recipe(merge(DEFAULT_CONFIG, {"train": {"warmup": 1_000_000, "samples": 1000}}))  # lr ~0 throughout


def test_a_damaged_best_pt_stops_resume(tmp_path):
    """A review's fuzzing: junk in best.pt went unnoticed, and the resumed run named it as its weights."""
    run = tmp_path / "run"
    train("ps-fcn", tiny(8), run, device="cpu")
    assert (run / "best.pt").is_file()
    (run / "best.pt").write_text("x\n")
    with pytest.raises(PsctlError, match="best.pt"):
        train("ps-fcn", tiny(16), run, resume=True, device="cpu")


def test_a_recipe_too_large_for_memory_is_one_line_before_any_work(tmp_path, monkeypatch):
    """val.images: 100000 rendered for minutes and was killed for memory without a word."""
    from psctl.train import check_memory, memory_needed

    cfg = tiny(8)
    small = memory_needed(cfg, torch.device("cpu"))
    assert 0 < small < 2**27  # the tiny recipe: well under 128 MiB
    check_memory(cfg, torch.device("cpu"))
    huge = merge(cfg, {"val": {"images": 100_000, "size": 32, "samples": 256}})
    assert memory_needed(huge, torch.device("cpu")) > 2**39
    with pytest.raises(PsctlError, match=r"needs at least [\d,]+ GiB of memory, .*config 'val'"):
        train("ps-fcn", huge, tmp_path / "run", device="cpu")
    assert not (tmp_path / "run").exists()
    with pytest.raises(PsctlError, match=r"huge.yaml: the recipe needs at least"):  # an audit: the file was not named
        train("ps-fcn", huge, tmp_path / "run", device="cpu", recipe=tmp_path / "huge.yaml")
    # every shipped recipe fits an 8 GB laptop (the guard must not refuse what the project uses)
    for recipe in sorted((REPO / "configs").glob("*.yaml")):
        cfg_r = load_config(recipe)
        name = recipe.name
        method = cfg_r.get("method") or ("lcnet" if "lcnet" in name else "ps-fcn-n" if "ps_fcn_n" in name else
                                         "ups-fcn" if "ups" in name else "ps-fcn-dagger" if "dagger" in name else "ps-fcn")
        assert memory_needed(cfg_r, torch.device("cpu"), method.lower()) < 0.8 * 8 * 2**30, name
    # a CPU training step's activations count (an audit: images_per_sample 100000 passed, then ran out
    # of memory after half a minute); not on a GPU, where they are not in host memory
    steps = merge(cfg, {"train": {"images_per_sample": 100_000}})
    assert memory_needed(steps, torch.device("cpu"), "ps-fcn") > 2**36 > memory_needed(steps, torch.device("cpu"))
    assert memory_needed(steps, torch.device("cuda"), "ps-fcn") == memory_needed(steps, torch.device("cuda"))
    # under amp the step counts half, where amp really runs: not with bf16 on a CPU without it (a review)
    import psctl.infer

    bf16 = merge(steps, {"train": {"amp": "bf16"}})
    base = memory_needed(steps, torch.device("cpu"))
    with monkeypatch.context() as m:
        m.setattr(psctl.infer, "cpu_has_bf16", lambda: True)
        half = memory_needed(bf16, torch.device("cpu"), "ps-fcn") - base
        m.setattr(psctl.infer, "cpu_has_bf16", lambda: False)
        full = memory_needed(bf16, torch.device("cpu"), "ps-fcn") - base
    assert full == pytest.approx(2 * half) and full == pytest.approx(memory_needed(steps, torch.device("cpu"), "ps-fcn") - base)
    with pytest.raises(PsctlError, match=r"needs at least [\d,]+ GiB of memory, .*a training step: 'train' "
                                         r"batch_size, images_per_sample, crop"):
        train("ps-fcn", steps, tmp_path / "run", device="cpu")
    # the training stream's pool counts where it lives: on the host for a CPU run only
    big_pool = merge(cfg, {"data": {"pool": 4096}})
    assert memory_needed(big_pool, torch.device("cpu")) > memory_needed(big_pool, torch.device("meta")) + 2**28


_WITHOUT_OIIO = r"""
import importlib.abc, sys
from pathlib import Path


class NoOpenImageIO(importlib.abc.MetaPathFinder):  # the GPU machine has no OpenImageIO
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "OpenImageIO":
            raise ImportError("OpenImageIO is not on the GPU machine")


sys.meta_path.insert(0, NoOpenImageIO())
import torch
from psctl.train import load_config, merge, train

torch.set_num_threads(1)
repo, out = Path(sys.argv[1]), Path(sys.argv[2])
cfg = merge(load_config(repo / "configs" / "tiny.yaml"), {"train": {"samples": 16}})
for method in ("ps-fcn-n", "ps-fcn", "lcnet"):
    assert train(method, cfg, out / method, device="cpu")["finished"]
assert train("ps-fcn-dagger", cfg, out / "dagger", device="cpu", lcnet=out / "lcnet" / "best.pt")["finished"]
print(sorted(p.name for p in out.iterdir()))
"""


def test_training_needs_no_image_io(tmp_path):
    """The GPU machine that trains the release weights has torch, numpy, scipy, yaml, typer and rich
    but not OpenImageIO (DEVELOPERS.md): every network's training, validation and checkpoints run
    with it unimportable (configs/gpu_session.sh's path)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _WITHOUT_OIIO, str(REPO), str(tmp_path)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split("\n")[-2] == "['dagger', 'lcnet', 'ps-fcn', 'ps-fcn-n']"


@pytest.mark.parametrize("part", ["stream.pt", "optim.0.pt", "model.pt"])
def test_a_checkpoint_file_from_another_point_of_the_run_is_refused(tmp_path, part):
    """A run folder put together from parts (as the GPU workflow moves it) with one file from
    another checkpoint resumed without a word, inexactly; each file now says how far it got."""
    import shutil

    cfg = tiny(48)
    train("ps-fcn", merge(cfg, {"train": {"samples": 16}}), tmp_path / "early", device="cpu")
    train("ps-fcn", merge(cfg, {"train": {"samples": 32}}), tmp_path / "late", device="cpu")
    shutil.copy(tmp_path / "early" / part, tmp_path / "late" / part)
    with pytest.raises(PsctlError, match=f"{part}: .*(saved at|optimiser at step).*not this checkpoint's"):
        train("ps-fcn", cfg, tmp_path / "late", resume=True, device="cpu")


@pytest.mark.parametrize("part", ["optim.0.pt", "model.pt", "stream.pt"])
def test_another_runs_checkpoint_file_at_the_same_point_is_refused(tmp_path, part):
    """An audit: another run's model.pt or optimiser saved at the same sample count resumed
    without a word (validation 12.66 / 28.26 against 31.42 exactly), against docs/training.md's
    'never a silently inexact run': state.json now records each checkpoint file's sha256."""
    import shutil

    cfg = merge(tiny(48), {"train": {"samples": 16}})
    train("ps-fcn", cfg, tmp_path / "a", device="cpu")
    train("ps-fcn", merge(cfg, {"train": {"seed": 11}}), tmp_path / "b", device="cpu")
    state = json.loads((tmp_path / "a" / "state.json").read_text())
    assert set(state["files_sha256"]) >= {"model.pt", "stream.pt", "optim.0.pt"}
    shutil.copy(tmp_path / "b" / part, tmp_path / "a" / part)
    with pytest.raises(PsctlError, match=f"a/{part}: is not the file this run's last checkpoint wrote .*sha256"):
        train("ps-fcn", tiny(48), tmp_path / "a", resume=True, device="cpu")


def test_log_and_loss_average_continue_across_a_resume_and_model_pt_holds_its_own_metric(tmp_path):
    """After a hard kill the log held the killed process's lines past the checkpoint, and a resume
    wrote them again; the logged loss (an average) restarted; model.pt's metric was the run's best."""
    cfg = merge(tiny(48), {"train": {"val_every": 16}})
    a = train("ps-fcn", cfg, tmp_path / "a", device="cpu")
    from psctl.train import STOP

    calls = []  # stopped at its first logged step, with a checkpoint (as on a signal)
    train("ps-fcn", cfg, tmp_path / "b", device="cpu", progress=lambda rec: calls.append(rec) or STOP)
    assert len(calls) == 1
    log = tmp_path / "b" / "log.jsonl"
    with open(log, "a") as f:  # what a process killed after its checkpoint had logged
        f.write('{"step": 99, "samples": 400, "loss": 1.0}\n')
    b = train("ps-fcn", cfg, tmp_path / "b", resume=True, device="cpu")
    assert a["samples"] == b["samples"] == 48
    def lines(path):  # what does not depend on the clock
        return [{k: v for k, v in json.loads(x).items() if k not in ("samples_per_s", "seconds")}
                for x in path.read_text().splitlines()]

    assert lines(log) == lines(tmp_path / "a" / "log.jsonl")  # no line twice, the same average losses
    c = train("ps-fcn", merge(tiny(32), {"train": {"val_every": 8}}), tmp_path / "c", device="cpu")
    vals = dict(map(tuple, c["val"]))
    assert vals[32] > min(vals.values())  # its last validation is not its best
    assert read_weights(tmp_path / "c" / "model.pt").metadata["metrics"]["synthetic_val_mae"] == vals[32]
    assert read_weights(tmp_path / "c" / "best.pt").metadata["metrics"]["synthetic_val_mae"] == min(vals.values())


def test_a_run_without_training_meshes_says_so_and_keeps_to_its_data(tmp_path, monkeypatch):
    """No lucy.obj: the stream drew procedural shapes only and nobody was told (docs/synthetic.md
    says it says so); a resume that would now draw meshes too is refused."""
    cfg = merge(tiny(16), {"data": {"shapes": {"blobby": 1.0, "mesh": 0.5}}})
    monkeypatch.setenv("PSCTL_MESHES", str(tmp_path / "none"))
    (tmp_path / "none").mkdir()
    said = []
    st = train("ps-fcn", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu", note=said.append)
    assert len(said) == 1 and said[0].startswith("data: no training meshes under") and "procedural shapes only" in said[0]
    assert st["data_sources"] == [["blobby", 1.0]]
    assert read_weights(tmp_path / "run" / "model.pt").metadata["data_notes"] == [said[0].removeprefix("data: ")]
    elsewhere = tmp_path / "other-none"  # another machine's folder, also without meshes: the same data
    elsewhere.mkdir()
    monkeypatch.setenv("PSCTL_MESHES", str(elsewhere))
    assert train("ps-fcn", merge(cfg, {"train": {"samples": 12}}), tmp_path / "run", resume=True, device="cpu")["samples"] == 12
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    from tests.test_synth import uv_sphere, write_obj

    write_obj(meshes / "lucy.obj", *uv_sphere(8, 16))
    monkeypatch.setenv("PSCTL_MESHES", str(meshes))
    with pytest.raises(PsctlError, match="the run's data differ from its start"):
        train("ps-fcn", cfg, tmp_path / "run", resume=True, device="cpu")


def test_a_ps_fcn_dagger_run_refuses_a_frozen_lcnet_whose_file_changed(tmp_path):
    """state.json kept only the LCNet's path; `psctl train lcnet --install --force` replaces the
    file at that path, and a resume then trained on another LCNet's lights without a word."""
    from psctl.models.lcnet import LCNet
    from psctl.models.weights import save_weights

    torch.manual_seed(0)
    lc = tmp_path / "lc.pt"
    save_weights(lc, LCNet({"size": 32}), {"method": "lcnet", "train_images": 8})
    cfg = tiny(16)
    cfg = merge(cfg, {"data": {**cfg["data"], "size": 32, "windows": 16}})
    train("ps-fcn-dagger", merge(cfg, {"train": {"samples": 8}}), tmp_path / "run", device="cpu", lcnet=lc)
    same = lc.read_bytes()
    torch.manual_seed(1)
    save_weights(lc, LCNet({"size": 32}), {"method": "lcnet", "train_images": 8})
    with pytest.raises(PsctlError, match="lc.pt: is not the frozen LCNet this run started with"):
        train("ps-fcn-dagger", cfg, tmp_path / "run", resume=True, device="cpu")
    # finished, resumed to be installed: still refused (helper-184: the early return skipped the check)
    with pytest.raises(PsctlError, match="lc.pt: is not the frozen LCNet this run started with"):
        train("ps-fcn-dagger", None, tmp_path / "run", resume=True, device="cpu")
    lc.write_bytes(same)
    assert train("ps-fcn-dagger", cfg, tmp_path / "run", resume=True, device="cpu")["samples"] == 16


def test_a_resume_that_would_end_before_the_samples_seen_and_a_missing_start_are_one_line(tmp_path):
    train("ps-fcn", tiny(16), tmp_path / "run", device="cpu")
    with pytest.raises(PsctlError, match="the run has seen 16 samples; a recipe of 8 would end before them"):
        train("ps-fcn", tiny(8), tmp_path / "run", resume=True, device="cpu")
    with pytest.raises(PsctlError, match=r"gone.pt: not found: the recipe's train.init"):
        train("ps-fcn", merge(tiny(8), {"train": {"init": str(tmp_path / "gone.pt")}}), tmp_path / "new", device="cpu")
    assert not (tmp_path / "new").exists()
    (tmp_path / "adir").mkdir()  # a folder is said as such (it said 'not found'; a QA helper)
    with pytest.raises(PsctlError, match=r"adir: is a folder, not a weights file: the recipe's train.init"):
        train("ps-fcn", merge(tiny(8), {"train": {"init": str(tmp_path / "adir")}}), tmp_path / "new", device="cpu")
    assert not (tmp_path / "new").exists()


def test_resume_checks_hold_after_a_fresh_moments_resume_an_edited_log_and_a_finished_run(tmp_path):
    """A review's cases: a resume with fresh Adam moments ("optim_files": [], configs/gpu_session.sh)
    made every later resume 'not this checkpoint's'; a log the user rotated or edited must not be
    cut; a finished run overshooting its train.samples resumes with its own recipe; a bad value
    is one line, not a TypeError."""
    run = tmp_path / "run"
    train("ps-fcn", tiny(16), run, device="cpu")
    st = json.loads((run / "state.json").read_text())
    st["optim_files"] = []
    (run / "state.json").write_text(json.dumps(st))
    assert train("ps-fcn", tiny(32), run, resume=True, device="cpu")["samples"] == 32
    assert train("ps-fcn", tiny(48), run, resume=True, device="cpu")["samples"] == 48
    log = run / "log.jsonl"
    with open(log, "a") as f:  # the user's own line after the checkpoint: not a later step's
        f.write('{"comment": "rotated here"}\n')
    before = log.read_text()
    assert train("ps-fcn", tiny(56), run, resume=True, device="cpu")["samples"] == 56
    assert log.read_text().startswith(before)
    odd = merge(tiny(10), {"train": {"batch_size": 4}})  # ends at 12
    assert train("ps-fcn", odd, tmp_path / "odd", device="cpu")["samples"] == 12
    assert train("ps-fcn", odd, tmp_path / "odd", resume=True, device="cpu")["samples"] == 12
    # finished: a resume (to --install it) renders no data and leaves the checkpoint as it is
    state = (tmp_path / "odd" / "state.json").read_bytes()
    st = train("ps-fcn", odd, tmp_path / "odd", resume=True, device="cpu",
               make_stream=lambda *a, **k: pytest.fail("rendered data for a finished run"))
    assert st["finished"] and st["signal"] is None and st["samples"] == 12
    assert (tmp_path / "odd" / "state.json").read_bytes() == state
    bad = tiny(64)
    bad["train"]["samples"] = "1e5"
    with pytest.raises(PsctlError, match="'train.samples' must be a finite integer"):
        train("ps-fcn", bad, run, resume=True, device="cpu")


def test_ps_fcn_dagger_files_from_before_and_after_the_lcnet_digest_average():
    from psctl.train import _same_lcnet

    old = {"path": "weights/lcnet.pt", "official": False, "decode": "soft"}
    new = {**old, "sha256": "ab" * 32}
    assert _same_lcnet(old, new) and _same_lcnet(new, {**new, "path": "copy/lcnet.pt"})
    assert not _same_lcnet(new, {**new, "sha256": "cd" * 32}) and not _same_lcnet(old, {**old, "decode": "argmax"})


def test_a_callers_own_signal_handler_hears_of_the_signal_that_stopped_the_run(tmp_path):
    """train() takes SIGTERM to checkpoint and stop; a service that had its own SIGTERM handler
    (its shutdown hook) never heard of it (an audit). Now the signal is raised again once the
    handler is back; Python's and the system's defaults are not (the run stopped as asked)."""
    import os
    import signal

    heard = []
    mine = signal.signal(signal.SIGTERM, lambda s, f: heard.append(s))
    try:
        sent = []

        def progress(rec):
            if not sent:
                sent.append(os.kill(os.getpid(), signal.SIGTERM))

        st = train("ps-fcn", tiny(48), tmp_path / "run", device="cpu", progress=progress)
        assert st["signal"] == signal.SIGTERM and not st["finished"]
        assert heard == [signal.SIGTERM] and signal.getsignal(signal.SIGTERM) is not None
    finally:
        signal.signal(signal.SIGTERM, mine)
    sent.clear()  # Ctrl-C with Python's default handler: no KeyboardInterrupt after the run's own stop
    # (set here: a test run started as a background job inherits SIGINT ignored, and train leaves it so)
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        st = train("ps-fcn", tiny(96), tmp_path / "run", resume=True, device="cpu",
                   progress=lambda rec: sent or sent.append(os.kill(os.getpid(), signal.SIGINT)))
    finally:
        signal.signal(signal.SIGINT, inherited)
    assert st["signal"] == signal.SIGINT


def test_a_partial_recipe_from_python_is_merged_with_the_defaults(tmp_path):
    """train(method, {"train": {...}}) raised KeyError: 'model' (a review's side note): a dict of
    the keys that differ is merged as load_config merges a YAML file; a non-dict is one line."""
    cfg = tiny(8)
    st = train("ps-fcn", {"data": cfg["data"], "train": cfg["train"], "val": cfg["val"]}, tmp_path / "run", device="cpu")
    assert st["samples"] == 8 and st["config"]["model"] == {"fuse": "max"}
    with pytest.raises(PsctlError, match="config must be a recipe .* not a str"):
        train("ps-fcn", "configs/tiny.yaml", tmp_path / "other", device="cpu")


class _Killed(BaseException):
    """A kill at a chosen file operation (raised, so this process goes on to resume)."""


def test_a_kill_anywhere_in_a_checkpoint_leaves_a_run_that_resumes_exactly(tmp_path, monkeypatch):
    """A checkpoint is five files; each was replaced atomically, the set was not, and a hard kill
    while they were written left parts of two checkpoints that no resume could continue (a QA
    helper, 3 of 3 times). Now they are staged and committed by one journal write: a kill at any
    file operation of the checkpoint leaves the earlier checkpoint or the new one, and the resume
    gives the weights of a run never stopped. Staged files a kill left without a journal go."""
    import os
    import shutil


    def small(samples: int) -> dict:  # a smaller validation set: 14 runs
        return merge(tiny(samples), {"val": {"samples": 2, "batch_size": 2}})

    cfg = small(16)
    whole = tmp_path / "whole"
    train("ps-fcn", cfg, whole, device="cpu")
    want = read_weights(whole / "model.pt").state_dict
    start = tmp_path / "start"
    train("ps-fcn", small(8), start, device="cpu")
    real = os.replace
    calls = []

    def replace(a, b):
        calls.append(Path(b).name)
        if len(calls) == kill_at:
            raise _Killed()
        return real(a, b)

    monkeypatch.setattr(os, "replace", replace)
    kill_at = 0  # none: count the file operations of a resume from 8 to 16 samples
    shutil.copytree(start, tmp_path / "count")
    train("ps-fcn", cfg, tmp_path / "count", resume=True, device="cpu")
    names = list(calls)  # best.pt, then the checkpoint's staged files, its journal, their moves, state.json
    assert "checkpoint.json" in names and names[-1] == "state.json", names
    journal = names.index("checkpoint.json")
    # one of each kind: at a staged file, at the journal, at the first and the last move, at state.json
    points = [names.index(next(n for n in names if n.startswith(".next."))) + 1, journal + 1, journal + 2,
              len(names) - 1, len(names)]
    assert names[journal + 1] in ("optim.0.pt", "stream.pt", "model.pt") and names[-2] == "model.pt", names
    for kill_at in points:
        run = tmp_path / f"k{kill_at}"
        shutil.copytree(start, run)
        calls.clear()
        with pytest.raises(_Killed):
            train("ps-fcn", cfg, run, resume=True, device="cpu")
        if not (run / "checkpoint.json").exists():  # killed before the commit: as a hard kill leaves it
            (run / ".next.model.pt").write_bytes(b"half")
            (run / ".next.optim.0.pt").write_bytes(b"half")
        (run / "..next.optim.1.ab_cd123.tmp.pt").write_bytes(b"half")  # atomic_path's, killed while it wrote
        copy = kill_at == journal + 2 and (run / "checkpoint.json").exists()
        if copy:  # a copy that drops hidden files (cp DIR/*) keeps the journal and not what it commits
            shutil.copytree(run, tmp_path / "copy", ignore=lambda d, names: [n for n in names if n.startswith(".")])
            with pytest.raises(PsctlError, match=r"checkpoint.json: commits a checkpoint whose \S+ is missing .*a "
                                                 r"copy without the hidden files\?"):
                train("ps-fcn", cfg, tmp_path / "copy", resume=True, device="cpu")
        calls.clear()
        kill_at_now, kill_at = kill_at, 0
        st = train("ps-fcn", cfg, run, resume=True, device="cpu")
        kill_at = kill_at_now
        assert st["samples"] == 16 and not list(run.glob(".*")) and not (run / "checkpoint.json").exists()
        got = read_weights(run / "model.pt").state_dict
        diff = max((want[k] - got[k]).abs().max().item() for k in want)
        assert diff < 1e-5, (kill_at, names[kill_at - 1], diff)
    monkeypatch.undo()
    # a journal that cannot be read is one line naming it
    run = tmp_path / "bad"
    shutil.copytree(start, run)
    (run / "checkpoint.json").write_text("{")
    with pytest.raises(PsctlError, match=r"checkpoint.json: is not a readable checkpoint journal .*removing it "
                                         r"resumes the checkpoint before"):
        train("ps-fcn", cfg, run, resume=True, device="cpu")
    with pytest.raises(PsctlError, match="already holds a run"):
        train("ps-fcn", cfg, run, device="cpu")
    # a first checkpoint killed while staged: the folder (its log, staged and temporary files) starts again
    run = tmp_path / "first"
    run.mkdir()
    (run / "log.jsonl").write_text('{"step": 2}\n')
    (run / ".next.model.pt").write_bytes(b"half")
    (run / "..next.optim.0.ybamlrlu.tmp.pt").write_bytes(b"")
    assert train("ps-fcn", small(8), run, device="cpu")["samples"] == 8
    assert not list(run.glob(".*"))
    # a full disk while staging names the file, not its staged name (a reviewer)
    import psctl.models.weights as weights

    real_save = weights.save_weights

    def full_disk(path, *a, **k):
        if Path(path).name == ".next.model.pt":
            raise PsctlError(path, "cannot write (no space left on device)")
        return real_save(path, *a, **k)

    monkeypatch.setattr(weights, "save_weights", full_disk)
    with pytest.raises(PsctlError, match=r"first/model.pt: cannot write \(no space left on device\)"):
        train("ps-fcn", small(16), run, resume=True, device="cpu")
    monkeypatch.undo()
    assert not list(run.glob(".*")) and train("ps-fcn", small(16), run, resume=True, device="cpu")["samples"] == 16


def test_a_checkpoint_torn_by_a_hard_kill_is_named_as_such_on_resume(tmp_path):
    """A SIGKILL while a checkpoint's parts are written leaves optimiser parts of two checkpoints
    (a QA helper, 3 of 3 times with checkpoint_minutes 0): the error said 'step 1, state.json at step
    1' (the smaller of the two) and no way on. Now it gives both steps, says what likely happened,
    and names the inexact way to continue."""
    import json as _json
    import shutil

    run = tmp_path / "run"
    train("ps-fcn", tiny(8), run, device="cpu")
    later = tmp_path / "later"
    shutil.copytree(run, later)
    train("ps-fcn", tiny(16), later, resume=True, device="cpu")
    st = _json.loads((run / "state.json").read_text())
    part = st["optim_files"][0]
    shutil.copy(later / part, run / part)  # one part of the later checkpoint, the rest of the earlier
    step, step2 = st["optim_step"], _json.loads((later / "state.json").read_text())["optim_step"]
    assert step2 > step
    with pytest.raises(PsctlError, match=rf"{part}: holds the optimiser at step {step} and {step2} \(parts of two "
                                         rf"checkpoints\), state.json at step "
                                         rf"{step}: .*\"optim_files\": \[\] in state.json continues"):
        train("ps-fcn", tiny(16), run, resume=True, device="cpu")
    st["optim_files"] = []  # the way out it names: fresh Adam moments
    (run / "state.json").write_text(_json.dumps(st))
    train("ps-fcn", tiny(16), run, resume=True, device="cpu")
    assert _json.loads((run / "state.json").read_text())["samples"] == 16


def test_check_train_options_from_python(tmp_path):
    """psctl train's option rules are a library function (the command only calls it): the method
    as the command line takes it, the recipe loaded, and one line naming the option otherwise."""
    from psctl.errors import PsctlError
    from psctl.train import DEFAULT_CONFIG, check_train_options

    assert check_train_options("PS-FCN-N", resume=tmp_path / "run") == ("ps-fcn-n", None)  # keeps its own recipe
    method, cfg = check_train_options("ps-fcn", out=tmp_path / "run")
    assert method == "ps-fcn" and cfg == DEFAULT_CONFIG and cfg is not DEFAULT_CONFIG
    assert check_train_options("lcnet", out=tmp_path / "avg", average=[tmp_path / "a.pt"]) == ("lcnet", None)
    for kwargs, named in (({"force": True}, "--force"), ({"max_minutes": float("nan")}, "--max-minutes"),
                          ({"average": ["a.pt"], "max_minutes": 1.0, "out": tmp_path}, "--max-minutes"),
                          ({"average": ["a.pt"]}, "--average"),
                          ({"out": tmp_path / "x", "resume": tmp_path / "y"}, str(tmp_path / "x"))):
        with pytest.raises(PsctlError) as e:
            check_train_options("ps-fcn", **kwargs)
        assert str(e.value).startswith(named), (kwargs, str(e.value))


def test_a_second_train_of_a_running_folder_is_refused(tmp_path):
    """Two `psctl train --resume RUN` at once: the second finished the first's checkpoint under it
    and stopped with "committed but not carried out" (session 79). The run folder is locked while
    a run lives; the lock is on the folder itself, so the folder's listing is unchanged."""
    pytest.importorskip("fcntl")
    from psctl.checkpoint import run_lock

    torch.set_num_threads(2)
    run = tmp_path / "run"
    train("ps-fcn", tiny(8), run, device="cpu")
    listing = sorted(p.name for p in run.iterdir())
    with run_lock(run):  # another process's run, as far as flock can tell (another open file)
        with pytest.raises(PsctlError, match=r"is locked by another process \(another psctl train of this run folder\?\)"):
            train("ps-fcn", tiny(16), run, resume=True, device="cpu")
        with pytest.raises(PsctlError, match="is locked by another process"):
            train("ps-fcn", tiny(16), tmp_path / "run", device="cpu")  # a new run into it waits its turn too
    assert sorted(p.name for p in run.iterdir()) == listing
    st = train("ps-fcn", tiny(16), run, resume=True, device="cpu")  # the lock went with the first
    assert st["finished"] and st["samples"] == 16


def test_a_run_folder_made_by_another_run_during_set_up_is_refused(tmp_path):
    """Two fresh `psctl train --out X` at once: the second passed its checks before the first made
    X, then trained into it unlocked (helper-198: both finished, one log holding both runs)."""
    pytest.importorskip("fcntl")
    torch.set_num_threads(2)
    run = tmp_path / "run"
    with pytest.raises(PsctlError, match="started in this run folder while this one was setting up"):
        train("ps-fcn", tiny(8), run, device="cpu", started=lambda: (run.mkdir(), (run / "log.jsonl").write_text("")))
    assert [p.name for p in run.iterdir()] == ["log.jsonl"]  # the other run's folder, untouched
    st = train("ps-fcn", tiny(8), tmp_path / "empty", device="cpu", started=(tmp_path / "empty").mkdir)
    assert st["finished"]  # an empty folder made meanwhile is as an empty --out: used


def test_checkpoint_journal_log_state_and_signal_rules_without_a_run(tmp_path):
    """psctl.checkpoint's own rules, each of which a mutation audit could drop without a failing
    test: a journal naming a file outside the run folder is refused; the log after a checkpoint
    is cut only at a line's end and only when every later line is a later step's; state.json's
    counts are not negative; a listed optimiser part that is missing is named as such; and a
    signal the caller ignores (nohup's SIGHUP) stays ignored while a run checkpoints on signals."""
    import signal

    from psctl.checkpoint import JOURNAL, Stop, check_state, drop_lines_after_checkpoint, finish_checkpoint, load_optimizer

    run = tmp_path / "run"
    run.mkdir()
    for name in ("../model.pt", "sub\\model.pt"):
        (run / JOURNAL).write_text(json.dumps({"files": {name: "00"}, "state": {}, "remove": []}))
        with pytest.raises(PsctlError, match="is not a readable checkpoint journal"):
            finish_checkpoint(run)
    (run / JOURNAL).write_text(json.dumps({"files": {}, "state": {}, "remove": ["../optim.0.pt"]}))
    with pytest.raises(PsctlError, match="is not a readable checkpoint journal"):
        finish_checkpoint(run)

    log = tmp_path / "log.jsonl"
    head = '{"samples": 8, "loss": 1.0}\n'
    for tail, cut in (('{"samples": 12}\n{"samples": 16}\n', True),  # a killed run's later steps: cut
                      ('{"samples": 12}\n{"samples": 8}\n', False),  # a step at the checkpoint's count: not later
                      ('{"samples": 12}\n{"note": "mine"}\n', False)):  # the user's own line
        log.write_text(head + tail)
        drop_lines_after_checkpoint(log, len(head), 8)
        assert log.read_text() == (head if cut else head + tail), tail
    log.write_text(head + ' {"samples": 12}\n')  # the size is not at a line's end (an edited log): left alone,
    drop_lines_after_checkpoint(log, len(head) + 1, 8)  # though what follows it reads as a later step
    assert log.read_text() == head + ' {"samples": 12}\n'

    for key in ("step", "samples", "log_bytes"):
        with pytest.raises(PsctlError, match=f"holds a bad '{key}' \\(-1\\)"):
            check_state(run / "state.json", {key: -1})
    check_state(run / "state.json", {"step": 0, "samples": 0, "log_bytes": 0, "seconds": 0.0})

    p = torch.nn.Parameter(torch.zeros(2))
    with pytest.raises(PsctlError, match=r"optim.0.pt: optimiser state listed in state.json is missing"):
        load_optimizer(run, torch.optim.Adam([p]), ["optim.0.pt"], torch.device("cpu"))

    if hasattr(signal, "SIGHUP"):
        old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
        try:
            with Stop():
                assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
                assert signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN
        finally:
            signal.signal(signal.SIGHUP, old)


def test_a_read_only_out_folder_is_named_by_train_and_average(tmp_path, monkeypatch):
    """A folder that cannot be written: one line naming it, as every other command says, not the
    run's log.jsonl or the temporary file best.pt goes through (helper-201). os.access is made to
    say no (the tests may run as root, whom permissions do not stop)."""
    import os
    import shutil

    import psctl.io.atomic
    from psctl.train import average_weights

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(psctl.io.atomic.os, "access", lambda p, mode: False if Path(p) == ro else real(p, mode))
    src = Path(__file__).resolve().parents[1] / "weights" / "ps_fcn.pt"
    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    shutil.copy(src, a)
    shutil.copy(src, b)
    with pytest.raises(PsctlError, match=r"ro: output folder is not writable$") as e:
        average_weights([a, b], ro, method="ps-fcn")
    assert e.value.path == str(ro)
    with pytest.raises(PsctlError, match="cannot create output folder: .*ro is not writable"):
        train("ps-fcn", tiny(), ro / "run", device="cpu")
    assert not any(ro.iterdir())

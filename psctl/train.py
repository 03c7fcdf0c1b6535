"""Training loops: PS-FCN, PS-FCN+N, UPS-FCN, LCNet and PS-FCN† on psctl's synthetic stream
(nanoGPT style).

    psctl train ps-fcn-n --config configs/ps_fcn_n.yaml [--resume runs/ps_fcn_n] [--device cuda]
    psctl train lcnet --config configs/lcnet.yaml
    psctl train ps-fcn-dagger --config configs/ps_fcn_dagger.yaml [--lcnet runs/lcnet/best.pt]

The recipe is one YAML file (see configs/); defaults follow the paper: Adam(0.9, 0.999), lr 1e-3
halved at regular intervals, batch 32, 32 images per sample, 32 x 32 crops, noise augmentation,
cosine loss 1 - n.n_gt over the object's pixels. The schedule is counted in samples seen.

One loop trains every network; what differs is a ``Task`` (model, loss of a stream batch,
validation items and error): ``normals_task`` (PS-FCN family, the cosine loss; PS-FCN† takes
its lights from a frozen LCNet: discretised directions, images divided by the estimated
intensities) and ``lcnet_task`` (cross-entropy on the three heads, validated by the mean
angular error of the decoded light directions).

A run folder holds
    model.pt            psctl weights (release format) of the latest state, with metadata
    optim.0.pt, ...     Adam state split in parts of < 16 MB (files returned from the GPU machine are capped)
    stream.pt           the synthetic stream's state (generator state, geometry-pool seeds)
    state.json          step, samples seen, wall time, RNG state of the stream, best validation
    best.pt             weights with the best synthetic-validation MAE so far
    log.jsonl           one line per log interval and per validation
A checkpoint is written every few minutes, at the end, and on SIGINT/SIGTERM/SIGHUP; ``--resume``
continues exactly (same data order, same optimiser state). ``psctl.checkpoint`` has the files'
mechanics (staged names and a journal, optimiser parts, signals); this module decides what goes
in them and what a resumed recipe may change. Release weights (``average_weights``,
``install_weights``) are written at the end of this module.

This module must not import OpenImageIO: it runs on the GPU machine, which lacks it.
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from psctl.checkpoint import (JOURNAL, OPTIM_PART, STAGED, TEMP_FILE, Stop, adam_steps, check_state, commit_checkpoint,
                              drop_lines_after_checkpoint, finish_checkpoint, no_half_run, restore_checkpoint,
                              restore_stream, run_lock, save_optimizer)
from psctl.errors import PsctlError, few, like_default, moved_names, naming, not_a_file
from psctl.models.lcnet import DEFAULT_CONFIG as LCNET_DEFAULT
from psctl.models.weights import file_sha256, normalization_allowed, save_torch
from psctl.synth.stream import MAX_SEED

if TYPE_CHECKING:
    from psctl.models.lcnet import LCNet
    from psctl.synth.stream import SynthStream

DEFAULT_CONFIG: dict[str, Any] = {
    "model": {"fuse": "max"},
    "normalization": None,  # None: the method's default (ps-fcn-n: per-channel)
    "data": {},  # passed to psctl.synth.stream (see there for keys)
    "train": {
        "batch_size": 32,
        "images_per_sample": 32,  # q
        "crop": 32,
        "lr": 1.0e-3,
        "betas": [0.9, 0.999],
        "weight_decay": 0.0,
        "lr_halve_every": 420_000,  # samples (the paper: every 5 epochs of ~84k samples)
        "warmup": 0,  # samples: lr ramps up linearly over the run's first ones (0: none, the paper's)
        "samples": 2_500_000,  # the paper: 30 epochs of ~84k samples
        "seed": 0,
        "log_every": 20,  # steps
        "checkpoint_minutes": 5.0,
        "val_every": 50_000,  # samples
        "amp": "bf16",  # bf16 autocast on CUDA and on CPUs with native bf16; "none": float32
        "channels_last": True,
        "init": None,  # a weights file of the same network to start from (fine-tuning); None: random
    },
    # val.data: stream options that differ from the recipe's data for validation only (e.g.
    # {lights: diligent}: select checkpoints under the narrow light cone of real captures)
    "val": {"samples": 64, "seed": 1_000_003, "images": 32, "size": 64, "batch_size": 16, "data": {}},
    "lcnet": {  # LCNet: the network trained by `train lcnet`, or the frozen one of `train ps-fcn-dagger`
        # the network's classes and inputs, as psctl.models.lcnet's defaults (one place: no drift)
        **{k: copy.deepcopy(LCNET_DEFAULT[k]) for k in ("dirs_cls", "ints_cls", "ints_range", "in_mask")},
        "loss_weights": [1.0, 1.0, 1.0],  # cross-entropy weights: azimuth, elevation, intensity
        "weights": None,  # ps-fcn-dagger: the frozen LCNet file (None: weights/lcnet.pt; --lcnet overrides)
        "decode": "argmax",  # ps-fcn-dagger: how the frozen LCNet's classes become lights (argmax | soft)
    },
}



def merge(base: dict, override: dict | None) -> dict:
    """Merge ``override`` into a copy of ``base`` section by section; unknown top-level/section
    keys are errors, except in ``data``, whose keys the synthetic stream itself checks."""
    out = copy.deepcopy(base)
    for k, v in (override or {}).items():
        if k == "data" and isinstance(out.get(k), dict) and isinstance(v, dict):
            out[k] = {**out[k], **copy.deepcopy(v)}  # stream options: merged, not replaced
        elif k in out and isinstance(out[k], dict) and not isinstance(v, dict):
            raise PsctlError(None, f"config section {k!r} must be a mapping of keys, not {v!r}")
        elif k in out and isinstance(out[k], dict) and isinstance(v, dict):
            unknown = set(v) - set(out[k])
            if unknown:
                raise PsctlError(None, f"unknown config keys in '{k}': {', '.join(sorted(unknown))}")
            out[k] = {**out[k], **v}
        elif k in out or k == "method":
            out[k] = v
        else:
            raise PsctlError(None, f"unknown config section {k!r}")
    return out


# recipe values that must be 0 or more, or positive (sizes, counts); the others only need their
# default's kind (check_recipe)
_NON_NEGATIVE = {("train", "lr"), ("train", "weight_decay"), ("train", "seed"), ("val", "seed"),
                 ("train", "checkpoint_minutes"), ("train", "warmup")}  # lr 0: frozen weights; checkpoint_minutes 0: every step
_POSITIVE = {("train", k) for k in ("batch_size", "images_per_sample", "crop", "lr_halve_every", "samples",
                                    "log_every", "val_every")} | \
    {("val", k) for k in ("samples", "images", "size", "batch_size")} | {("lcnet", "dirs_cls"), ("lcnet", "ints_cls")}
_CHOICES = {("train", "amp"): ("bf16", "fp16", "none"), ("model", "fuse"): ("max", "mean"),
            ("lcnet", "decode"): ("argmax", "soft")}


MAX_CLASSES = 3600  # LCNet's classes per head at most (0.05 degrees a direction class; the paper: 36 and 20)


def check_method(method: str, verb: str = "train") -> str:
    """A method ``psctl train`` trains (psctl.models.WEIGHTS_METHODS), in lower case as the
    command line takes it (PS-FCN is ps-fcn), or a one-line error ("cannot ``verb`` ...")."""
    from psctl.models import WEIGHTS_METHODS

    if isinstance(method, str):
        method = method.lower()
    if method not in WEIGHTS_METHODS:
        raise PsctlError(None, f"cannot {verb} {method!r}; choose from {', '.join(WEIGHTS_METHODS)}")
    return method


def check_recipe(config: dict) -> dict:
    """Each value of the train / val / lcnet / model sections of the kind of its default (YAML
    reads ``1e-3`` without a dot as a string, ``4.5`` as a float): a one-line error naming the key,
    before the run folder exists, instead of a torch error minutes later. Returns a copy with
    whole numbers given as floats (2.5e+6) turned into ints and tuples into lists."""
    config = copy.deepcopy(config)
    for section in ("model", "train", "val", "lcnet"):
        for key, value in config[section].items():
            default = DEFAULT_CONFIG[section].get(key)
            where = f"config '{section}.{key}'"
            if default is None or key == "data":
                continue
            value = config[section][key] = like_default(where, value, default,
                                                        " (write 1.0e-3, not 1e-3: YAML reads that as text)")
            if (section, key) in _POSITIVE and not value > 0:
                raise PsctlError(None, f"{where} must be positive, not {value!r}")
            if (section, key) in _NON_NEGATIVE and not value >= 0:
                raise PsctlError(None, f"{where} must be 0 or more, not {value!r}")
            if (section, key) in _CHOICES and value not in _CHOICES[section, key]:
                raise PsctlError(None, f"{where} must be one of {', '.join(_CHOICES[section, key])}, not {value!r}")
            if key == "seed" and value > MAX_SEED:  # the stream seeds generators with seed + k; torch takes 64 bits
                raise PsctlError(None, f"{where} must be at most 2^62, not {value!r}")
    if not isinstance(config["val"].get("data") or {}, dict):
        raise PsctlError(None, f"config 'val.data' must be a mapping of synth stream options, not "
                               f"{config['val']['data']!r}")
    for where, value in (("train.init", config["train"].get("init")), ("lcnet.weights", config["lcnet"].get("weights"))):
        if value is not None and not (isinstance(value, str) and value.strip()):  # a number, a list or "" (read
            # as no file, silently random weights) would fail later or quietly, unnamed
            raise PsctlError(None, f"config '{where}' must be a weights file's path (or null), not {value!r}")
    lc = config["lcnet"]
    lw = lc["loss_weights"]
    if not (len(lw) == 3 and all(w >= 0 for w in lw) and sum(lw) > 0):  # negative: the loss runs away; all 0: no learning
        raise PsctlError(None, f"config 'lcnet.loss_weights' must be three weights (azimuth, elevation, intensity), "
                               f"0 or more and not all 0, not {lw!r}")
    tr = config["train"]
    if tr["warmup"] > tr["samples"]:  # the lr would stay near 0 for the whole run
        raise PsctlError(None, f"config 'train.warmup' ({tr['warmup']:,} samples) is longer than the run "
                               f"('train.samples', {tr['samples']:,})")
    lo_hi = lc["ints_range"]
    if not (len(lo_hi) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in lo_hi)
            and 0 < lo_hi[0] < lo_hi[1] and math.isfinite(lo_hi[1])):  # reversed, the classes would run backwards
        raise PsctlError(None, f"config 'lcnet.ints_range' must be two intensities 0 < low < high, not {lo_hi!r}")
    for key in ("dirs_cls", "ints_cls"):  # one class cannot tell anything apart (and bin centres need two)
        # ... and a typo's millions would be heads of gigabytes, past the memory guard (a review)
        if not 2 <= lc[key] <= MAX_CLASSES:
            raise PsctlError(None, f"config 'lcnet.{key}' must be 2 to {MAX_CLASSES:,} classes, not {lc[key]!r}")
    betas = config["train"]["betas"]
    if not all(0 <= b < 1 for b in betas):
        raise PsctlError(None, f"config 'train.betas' must be two numbers in [0, 1) (Adam's decay rates), not {betas!r}")
    if config["val"]["seed"] == config["train"]["seed"]:  # the stream's seed: the same draws (a QA helper)
        raise PsctlError(None, f"config 'val.seed' equals 'train.seed' ({config['train']['seed']}): the validation "
                               f"set would be drawn as the first training samples; give it a seed of its own")
    from psctl.models.ps_fcn import NORMALIZATIONS

    if config["normalization"] is not None and config["normalization"] not in NORMALIZATIONS:
        raise PsctlError(None, f"config 'normalization' must be one of {', '.join(NORMALIZATIONS)} or null (the "
                               f"method's own), not {config['normalization']!r}")
    return config


def _full_recipe(config: dict | None) -> dict | None:
    """A recipe given as a dict from Python, perhaps only the keys that differ from the defaults
    ({"train": {"samples": 64}}), as load_config would merge it (a KeyError before)."""
    if config is None:
        return None
    if not isinstance(config, dict):
        raise PsctlError(None, f"config must be a recipe (a dict, e.g. psctl.train.load_config(PATH)), not a "
                               f"{type(config).__name__}")
    return merge(DEFAULT_CONFIG, config)


def _other_method(config: dict, method: str) -> Any:
    """The recipe's own ``method`` label where it names another network than ``method`` (in any
    case, as the command line takes names), else None."""
    label = config.get("method")
    return label if label is not None and (label.lower() if isinstance(label, str) else label) != method else None


def check_sizes(method: str, config: dict) -> None:
    """The recipe against the method: its own ``method`` key, if any, must agree, and PS-FCN's
    training crops and validation windows must be multiples of 4 (two stride-2 layers: another
    size comes back from the network a few pixels off, a torch error minutes into the run)."""
    label = _other_method(config, method)
    if label is not None:
        raise PsctlError(None, f"config 'method' is {label!r}: the recipe is for another network than {method}; "
                               f"train {label} with it, or choose a {method} recipe")
    norm = config.get("normalization")
    # the weights' loader refuses these: refused here, before the run, not at its first save with
    # the run folder removed (a QA helper's finding)
    if norm is not None and not normalization_allowed(method, norm):
        raise PsctlError(None, f"config 'normalization' is {norm!r}, which {method} cannot train with (ps-fcn-n "
                               f"needs +N, ps-fcn and lcnet have none); leave it out (null) for the method's own")
    if method == "lcnet":  # LCNet resizes every view to its input size
        return
    from psctl.models import STRIDE

    for where, size in (("train.crop", config["train"]["crop"]), ("val.size", config["val"]["size"])):
        if size % STRIDE:
            raise PsctlError(None, f"config '{where}' must be a multiple of {STRIDE} for {method} (two stride-2 "
                                   f"layers), not {size}")


# synth stream options that each run sets from its own sections (synth_stream), and where they go
_RUN_OPTIONS = {"batch_size": ("train.batch_size", "val.batch_size"), "n_images": ("train.images_per_sample", "val.images"),
                "crop": ("train.crop", "val.size"), "seed": ("train.seed", "val.seed"),
                "device": ("psctl train --device", "psctl train --device")}


def check_method_recipe(method: str, config: dict, stream: bool = True) -> None:
    """What a checked recipe must hold for ``method``, before any run folder exists (``psctl
    train`` names the recipe's file in these errors): its ``method`` label and PS-FCN's multiples
    of 4 (``check_sizes``), data.windows only for PS-FCN†, wrong listed lights only for the
    calibrated networks, and (``stream``: psctl's synth stream) the stream's options with the
    training crop and the validation size."""
    check_sizes(method, config)
    if config["data"].get("windows") is not None and method != "ps-fcn-dagger":
        raise PsctlError(None, f"config 'data.windows' is for ps-fcn-dagger (PS-FCN† trains on windows of the "
                               f"view its LCNet sees); {method} trains on the stream's crops (train.crop)")
    val_data = {**config["data"], **(config["val"].get("data") or {})}
    for key, what in (("intensity_error", "intensities"), ("direction_error", "directions")):
        if (config["data"].get(key) or val_data.get(key)) and method not in ("ps-fcn", "ps-fcn-n"):
            # only the calibrated networks are told the listed lights: LCNet learns them (its labels
            # would be wrong), UPS-FCN never sees them and PS-FCN† gets LCNet's estimates
            raise PsctlError(None, f"config 'data.{key}' (wrong listed {what}) is for calibrated training "
                                   f"(ps-fcn, ps-fcn-n), not {method}")
    if stream:  # bad stream options fail here, before the run folder exists
        from psctl.synth.stream import make_config

        for part, options in (("data", config["data"]), ("val.data", config["val"].get("data") or {})):
            for key, homes in _RUN_OPTIONS.items():
                if key in options:  # the run sets these on the stream: given here they were silently overridden
                    raise PsctlError(None, f"config '{part}.{key}' is set by the run, not the stream's options: "
                                           f"give it as {homes[part == 'val.data']}")
        make_config(config["data"], crop=config["train"]["crop"])
        make_config(val_data, crop=config["val"]["size"])


# Host bytes of one CPU training step (forward and backward) per pixel of the network's input
# side, per image, per sample, float32. Measured 2026-12-01 on the 2-core VM (session 67) as the
# slope of psctl train's peak RSS over train.images_per_sample (batch 4, one step): PS-FCN about
# 1,400 (crop 16) to 1,900 (crop 16 -> 32), LCNet about 330 at 64. The guard takes less (it is a
# lower bound: configs/lcnet.yaml peaks at 5.3 GiB in all), and half that where amp runs.
_STEP_BYTES = {"lcnet": 160.0}
_STEP_BYTES_PS_FCN = 1000.0


def memory_needed(config: dict, device: torch.device, method: str | None = None) -> float:
    """Bytes of host memory a run holds at least: the validation set (its stream batches and
    their network inputs side by side while it is made, float32), the validation stream's
    geometry pool, the training stream's where it lives on the CPU, and with ``method`` a CPU
    training step's activations (_STEP_BYTES: ``images_per_sample: 100000`` passed the guard and
    ran out of memory after half a minute). Python, torch and rendering come on top. Against peak
    RSS on the CPU (2026-11-29, 2-core VM, the validation set made batch by batch): 0.95 GiB here
    (without the step) and 1.7 GiB peak for configs/ps_fcn_n.yaml, 3.29 GiB and 5.3 GiB for
    configs/lcnet.yaml."""
    from psctl.synth.stream import make_config

    def pool(data: dict, crop: int) -> float:
        c = make_config(data, crop=crop)
        return c["pool"] * c["size"] ** 2 * (20 + 2 * c["horizon_dirs"] + (40 if c["interreflection"] else 0))

    v, t = config["val"], config["train"]
    val_data = {**config["data"], **(v.get("data") or {})}
    n = math.ceil(v["samples"] / v["batch_size"]) * v["batch_size"]
    need = 2 * n * (3 * v["images"] + 4) * v["size"] ** 2 * 4 + pool(val_data, v["size"])
    if device.type != "cpu":
        return need
    need += pool(config["data"], t["crop"])
    if method is not None:
        side = (config["data"].get("windows") or t["crop"]) if method == "ps-fcn-dagger" else t["crop"]
        per = _STEP_BYTES.get(method, _STEP_BYTES_PS_FCN) * (0.5 if amp_settings(t["amp"], device)[0] else 1.0)
        need += per * t["batch_size"] * t["images_per_sample"] * side ** 2
    return need


def check_memory(config: dict, device: torch.device, method: str | None = None) -> None:
    """A recipe that needs more memory than the machine has is one line before minutes of
    rendering (``val.images: 100000`` was an out-of-memory kill, no word said)."""
    from psctl.synth import physical_memory

    total = physical_memory()
    need = memory_needed(config, device, method)
    if need > 0.8 * total:
        raise PsctlError(None, f"the recipe needs at least {need / 2**30:,.0f} GiB of memory, this machine has "
                               f"{total / 2**30:.0f} GiB: ask for less (the validation set: config 'val' samples, "
                               f"images, size; the geometry pools: 'data' pool, size; a training step: 'train' "
                               f"batch_size, images_per_sample, crop)")


def _unique_key_loader():
    """yaml.SafeLoader, except that a key given twice in one mapping is an error (PyYAML keeps
    the last without a word: `lr` twice in a recipe is a mistake, not a choice)."""
    import yaml

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # <<: *defaults, resolved by SafeLoader
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    if key in seen:
                        raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}",
                                                                key_node.start_mark)
                    seen.add(key)
                except TypeError:  # an unhashable key: SafeLoader's own error says so
                    pass
            return super().construct_mapping(node, deep)

    return Loader


def load_config(path: str | os.PathLike | None) -> dict:
    """YAML recipe merged over DEFAULT_CONFIG."""
    if path is None:
        return copy.deepcopy(DEFAULT_CONFIG)
    import yaml

    path = Path(path)
    if path.is_dir():
        raise PsctlError(path, "is a folder; --config takes a YAML file")
    if not path.is_file():
        raise PsctlError(path, not_a_file(path, "config file is missing"))
    try:
        raw = yaml.load(path.read_text(encoding="utf-8"), Loader=_unique_key_loader())
    except yaml.YAMLError as e:
        raise PsctlError(path, f"not valid YAML ({' '.join(str(e).split())})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise PsctlError(path, f"cannot read the config ({e})") from None
    if raw is None:  # an empty file would silently mean the full default recipe (2.5 M samples)
        raise PsctlError(path, "config file is empty")
    if not isinstance(raw, dict):
        raise PsctlError(path, "a config must be a mapping of sections")
    try:
        config = check_recipe(merge(DEFAULT_CONFIG, raw))
        # the stream options are checked again by train(); here a bad one is named with its file
        from psctl.synth.stream import make_config

        make_config(config["data"], crop=config["train"]["crop"])  # with the crops the run gives them
        make_config({**config["data"], **(config["val"].get("data") or {})}, crop=config["val"]["size"])
    except PsctlError as e:  # named with its file; an error about another file (a missing mesh) keeps it
        if e.path is not None and Path(e.path) != path:
            raise PsctlError(e.path, f"{e.message} (in the recipe {path})") from None
        raise PsctlError(path, e.message) from None
    return config


def amp_settings(amp: str, device: torch.device) -> tuple[bool, torch.dtype]:
    """Recipe ``train.amp`` -> (autocast on?, dtype). bf16 runs on CUDA and on CPUs with native
    bf16 (about 2x faster than float32 for PS-FCN on a 2-core AVX512-BF16 machine); fp16 on CUDA only."""
    from psctl.infer import cpu_has_bf16

    if amp == "bf16":
        return (device.type == "cuda" or (device.type == "cpu" and cpu_has_bf16())), torch.bfloat16
    if amp == "fp16":
        return device.type == "cuda", torch.float16
    return False, torch.float32


def cpu_name() -> str:
    """The CPU's model name (weights metadata: training rates differ threefold between VMs)."""
    import platform

    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown model"


def cosine_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """mean over object pixels of 1 - n.n_gt. pred, gt [B, 3, H, W], mask [B, 1, H, W]."""
    cos = (pred * gt).sum(1, keepdim=True)
    m = mask.to(pred.dtype)
    return ((1 - cos) * m).sum() / m.sum().clamp_min(1)


def mae_degrees(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean angular error (degrees) over the object pixels of a batch."""
    cos = (pred.double() * gt.double()).sum(1, keepdim=True).clamp(-1, 1)
    err = torch.rad2deg(torch.acos(cos))
    m = mask.bool()
    return err[m].mean()


def network_inputs(batch: dict, lights: bool, normalization: str) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Stream batch -> (images [B, N, 3, H, W] as the network sees them, lights [B, N, 3] or None).

    Images arrive divided by their light intensities for calibrated methods (the capture reader
    does the same for real data); +N then removes albedo.
    """
    from psctl.models.ps_fcn import normalize_observations

    images = batch["images"]
    if lights and "intensities" in batch:
        images = images / batch["intensities"][:, :, None, None, None].clamp_min(1e-6)
    images = normalize_observations(images, normalization)
    return images, (batch["lights"] if lights else None)



def _differences(a: Any, b: Any, where: str = "") -> list[str]:
    """The dotted keys at which two recipes (plain JSON) differ: what a refused resume names."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in _differences(a.get(k), b.get(k), f"{where}.{k}" if where else str(k))]
    return [] if a == b else [where or "the recipe"]


def _plain_json(obj: Any) -> Any:
    """What ``obj`` looks like after a JSON round trip (tuples become lists), for comparisons."""
    return json.loads(json.dumps(obj))


RESUME_MAY_CHANGE = ("samples", "checkpoint_minutes", "log_every", "val_every")  # train.* keys a resume may set anew


def _recipe_core(config: dict) -> Any:
    core = _plain_json(config)
    core.pop("method", None)  # a label the run's own method already checks (runs from before recipes had it resume)
    for k in RESUME_MAY_CHANGE:
        core["train"].pop(k, None)
    return core


def _portable(path: str | os.PathLike) -> str:
    """A path as recorded in state.json: relative to the working directory when inside it, so a
    run folder copied to another machine (run from the repository root there) still finds it."""
    p = Path(path).resolve()
    try:
        return p.relative_to(Path.cwd().resolve()).as_posix()  # a run started on Windows resumes elsewhere
    except ValueError:
        return str(p)


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed memory for reuse instead of returning it to the kernel.

    Each CPU training step allocates and frees activations of hundreds of MB; by default glibc
    maps such blocks fresh every time (mmap) and gives them back (munmap), so the kernel zeroes
    every page again: on the 2-core VM that was about 110,000 page faults per second and 30-40 %
    of the CPU time in the kernel (docs/performance.md). Raising the mmap and trim thresholds
    makes the heap keep the memory: the process stays at its peak size, which training reaches
    anyway. Returns False (and changes nothing) where the C library is not glibc.
    """
    import ctypes
    import ctypes.util
    import platform

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return False
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # <malloc.h>
    big = ctypes.c_int(2**30)  # mallopt takes an int: 1 GiB, above any single activation here
    return bool(libc.mallopt(M_MMAP_THRESHOLD, big)) and bool(libc.mallopt(M_TRIM_THRESHOLD, big))


def lr_at(samples: int, cfg: dict) -> float:
    """The learning rate for the step that starts at ``samples`` (of this run): ``lr`` halved every
    ``lr_halve_every``; with ``warmup``, ramped up linearly over the first ``warmup`` samples (a
    fine-tuning stage starts Adam afresh, whose first updates are about lr whatever the gradient)."""
    t = cfg["train"]
    lr = t["lr"] * 0.5 ** (samples // max(1, t["lr_halve_every"]))
    if t.get("warmup", 0) > 0:
        lr *= min(1.0, (samples + t["batch_size"]) / t["warmup"])
    return lr


def synth_stream(data: dict, *, batch_size: int, images: int, crop: int, seed: int,
                 device: torch.device) -> "SynthStream":
    """The synthetic training stream (psctl.synth.stream.SynthStream) for a recipe's ``data`` section."""
    from psctl.synth.stream import SynthStream

    try:
        return SynthStream(data, batch_size=batch_size, n_images=images, crop=crop, seed=seed, device=str(device))
    except TypeError as e:  # duplicate keys between data and the train section
        raise PsctlError(None, f"config 'data' section: {e}") from None


@dataclass
class Task:
    """What differs between the networks; ``train`` runs the same loop for all of them."""

    model: torch.nn.Module
    loss: Callable[[dict], torch.Tensor]  # stream batch -> scalar loss (forward under autocast)
    val_item: Callable[[dict], tuple]  # stream batch -> a stored validation item
    val_error: Callable[[tuple], tuple[float, float]]  # item -> (sum of errors in degrees, count)
    metric: str  # validation metric (degrees, lower is better): "mae" (normals), "light_mae" (LCNet)
    metadata: dict = field(default_factory=dict)  # method-specific weights metadata


def frozen_lcnet(config: dict, path: str | os.PathLike | None, device: torch.device) -> tuple["LCNet", dict]:
    """The LCNet that estimates PS-FCN†'s training lights: ``path``, else the recipe's
    ``lcnet.weights``, else the installed weights/lcnet.pt. Returns (model, provenance)."""
    from psctl.models.lcnet import DECODINGS
    from psctl.models.weights import installed_path, load_network, no_weights_error

    if config["lcnet"]["decode"] not in DECODINGS:
        raise PsctlError(None, f"lcnet.decode is {config['lcnet']['decode']!r}; choose from {', '.join(DECODINGS)}")
    path = path or config["lcnet"]["weights"]
    if path is None and installed_path("lcnet") is None:
        raise no_weights_error("lcnet", "--lcnet")
    model, _, w = load_network("lcnet", path, device=device)
    model.requires_grad_(False)
    info = {"path": str(w.path), "sha256": file_sha256(w.path), "official": w.official, "date": w.metadata.get("date"),
            "samples_seen": w.metadata.get("samples_seen"), "metrics": w.metadata.get("metrics"),
            "decode": config["lcnet"]["decode"]}
    return model.eval(), info


def crop_windows(x: torch.Tensor, windows: torch.Tensor, side: int) -> torch.Tensor:
    """Cut one side x side window per sample out of x [B, ..., H, W]; windows [B, 2] long holds
    each window's top row and left column. Returns [B, ..., side, side]."""
    ar = torch.arange(side, device=x.device)
    rows = (windows[:, 0, None] + ar)[:, :, None]  # [B, side, 1]
    cols = (windows[:, 1, None] + ar)[:, None, :]  # [B, 1, side]
    flat = x.flatten(1, -3)  # [B, K, H, W]
    b = torch.arange(x.shape[0], device=x.device)[:, None, None]
    out = flat.permute(0, 2, 3, 1)[b, rows, cols]  # [B, side, side, K]
    return out.permute(0, 3, 1, 2).reshape(*x.shape[:-2], side, side)


def normals_task(method: str, config: dict, device: torch.device, amp: Callable,
                 lcnet: str | os.PathLike | None = None) -> Task:
    """PS-FCN, PS-FCN+N, UPS-FCN (lights from the stream) and PS-FCN† (lights from a frozen LCNet)."""
    from psctl.models import NETWORK_METHODS
    from psctl.models.ps_fcn import PSFCN, normalize_observations

    spec = NETWORK_METHODS[method]
    normalization = config.get("normalization") or spec["normalization"]
    model = PSFCN({**config["model"], "lights": spec["lights"]}).to(device)  # first: it draws the initial weights
    meta: dict = {"normalization": normalization}
    if normalization == "none":
        # the stream scales each sample to a mean in data.exposure (log-uniform): inference scales
        # each capture to the range's centre, so the network sees the brightness it was trained at
        from psctl.synth.stream import DEFAULT_CONFIG as STREAM_DEFAULTS

        lo, hi = config["data"].get("exposure", STREAM_DEFAULTS["exposure"])
        meta["input_mean"] = round(math.sqrt(lo * hi), 6)

    if method == "ps-fcn-dagger":
        estimator, meta["lcnet"] = frozen_lcnet(config, lcnet, device)
        mode = config["lcnet"]["decode"]
        side = config["data"].get("windows")

        def inputs(b: dict, crop: bool = True) -> tuple:
            # LCNet sees the whole view; PS-FCN† then trains on the stream's windows when it draws
            # them (the CPU recipe: LCNet on a 64 px view, PS-FCN† on 32 x 32 windows of it)
            with amp():
                dirs, ints = estimator.estimate(b["images"], b["masks"], mode)
            images = b["images"] / ints.float()[:, :, None, None, None].clamp_min(1e-6)
            normals, masks = b["normals"], b["masks"]
            if crop and side and "windows" in b:
                images, normals, masks = (crop_windows(t, b["windows"], int(side)) for t in (images, normals, masks))
            return normalize_observations(images, normalization), dirs.float(), normals, masks
    else:
        def inputs(b: dict, crop: bool = True) -> tuple:
            return (*network_inputs(b, spec["lights"], normalization), b["normals"], b["masks"])

    def loss(b: dict) -> torch.Tensor:
        x, l, n, m = inputs(b)
        with amp():
            pred = model(x, l).float()
        return cosine_loss(pred, n, m)

    def val_item(b: dict) -> tuple:
        return inputs(b, crop=False)  # validated on the whole view

    def val_error(item: tuple) -> tuple[float, float]:
        x, l, n, m = item
        with amp():
            pred = model(x, l).float()
        count = m.sum().item()
        return mae_degrees(pred, n, m).item() * count, count

    return Task(model, loss, val_item, val_error, "mae", meta)


def lcnet_task(config: dict, device: torch.device, amp: Callable) -> Task:
    """LCNet: cross-entropy on the azimuth, elevation and intensity classes of each image;
    validated by the mean angle between the argmax-decoded and the true directions."""
    from psctl.models.lcnet import LCNet, classification_loss, decode, resize_stack

    lc, t = config["lcnet"], config["train"]
    arch = {k: lc[k] for k in ("dirs_cls", "ints_cls", "ints_range", "in_mask")}
    try:  # the network's input side is the training crop (128 in the paper)
        model = LCNet({**arch, "fuse": config["model"]["fuse"], "size": t["crop"]}).to(device)
    except ValueError as e:
        raise PsctlError(None, f"lcnet recipe: {e} (train.crop is LCNet's input side)") from None
    weights = tuple(float(w) for w in lc["loss_weights"])
    size = int(model.config["size"])

    def loss(b: dict) -> torch.Tensor:
        with amp():
            logits = model(b["images"], b["masks"])
        return classification_loss(logits, b["lights"], b["intensities"], model.config, weights)[0]

    def val_item(b: dict) -> tuple:
        x, m = resize_stack(b["images"], b["masks"], size)
        return x, m, b["lights"]

    def val_error(item: tuple) -> tuple[float, float]:
        x, m, l = item
        with amp():
            logits = model(x, m)
        dirs, _ = decode(logits, model.config)
        cos = (dirs.double() * l.double()).sum(-1).clamp(-1, 1)
        return torch.rad2deg(torch.acos(cos)).sum().item(), float(cos.numel())

    return Task(model, loss, val_item, val_error, "light_mae", {"normalization": "none"})


def init_from(model: torch.nn.Module, path: str | os.PathLike) -> dict:
    """Load ``path`` (psctl weights of the same architecture) into ``model``; returns its
    provenance for the new weights' metadata."""
    from psctl.models.weights import read_weights

    if not Path(path).is_file():  # the recipes' starts are git-ignored .cache files their comments say how to make
        what = not_a_file(path, "not found", "is a folder, not a weights file")  # a folder is not 'not found'
        raise PsctlError(path, f"{what}: the recipe's train.init (the weights to start from); make it as the "
                               f"recipe's comment says, or set train.init to another weights file")
    try:
        w = read_weights(path)
    except PsctlError as e:  # said as the recipe's start, not only as a weights file
        raise PsctlError(e.path, f"{e.message} (the recipe's train.init)") from None
    arch, own = dict(w.metadata.get("architecture", {})), dict(model.config)
    state = {k: v.float() for k, v in w.state_dict.items()}
    adapted = None
    if arch != own and {**arch, "lights": False} == own and "extractor.conv1.0.weight" in state:
        # UPS-FCN from PS-FCN weights: the same network without the light input. conv1 sees
        # [image (3), light direction (3)]; its image filters are kept and the light ones dropped
        # (a constant per image: what they added is left for fine-tuning to relearn from shading)
        state["extractor.conv1.0.weight"] = state["extractor.conv1.0.weight"][:, :3].contiguous()
        adapted = "light input channels of extractor.conv1 dropped (PS-FCN -> UPS-FCN)"
    elif arch != own:  # names the network family too
        raise PsctlError(path, f"train.init: holds {w.method or w.kind} weights with architecture "
                               f"{w.metadata.get('architecture')}; this run's network is {own}")
    model.load_state_dict(state)
    m = w.metadata
    out = {"path": _portable(path), "method": w.method, "samples_seen": m.get("samples_seen"),
           "wall_seconds": m.get("wall_seconds"), "device": m.get("device"), "metrics": m.get("metrics"),
           "normalization": m.get("normalization")}
    return {**out, "adapted": adapted} if adapted else out


def validation_batches(cfg: dict, device: torch.device, make_stream: Callable = synth_stream) -> list[dict]:
    """The stream batches of a recipe's fixed validation set (``val``: its seed, size, images and
    ``val.data`` over ``data``); benchmarks/val_compare.py measures other methods on the same."""
    return list(_validation_stream(cfg, device, make_stream))


def _validation_stream(cfg: dict, device: torch.device, make_stream: Callable) -> Iterator[dict]:
    v = cfg["val"]
    stream = make_stream({**cfg["data"], **(v.get("data") or {})}, batch_size=v["batch_size"], images=v["images"],
                         crop=v["size"], seed=v["seed"], device=device)
    for _ in range(math.ceil(v["samples"] / v["batch_size"])):
        yield stream.next_batch()


def validation_set(cfg: dict, task: Task, device: torch.device, make_stream: Callable) -> list[tuple]:
    """A fixed synthetic validation set: training-distribution shapes and materials, a held-out seed.

    Rendered on the CPU whatever the training device, then moved there: CUDA's generator draws
    other numbers from the same seed, so a set rendered on the GPU was another set, and runs on
    the two could not be compared (256 samples: 0.24 degrees apart between two seeds, session 44).
    Each batch becomes the network's input as it comes: the raw batches are never all held (the
    set's peak memory was twice its size)."""
    with torch.no_grad():
        return [task.val_item({k: v.to(device) if torch.is_tensor(v) else v for k, v in b.items()})
                for b in _validation_stream(cfg, torch.device("cpu"), make_stream)]


@torch.no_grad()
def evaluate(task: Task, val: list[tuple]) -> float:
    """The task's validation metric over the fixed set (degrees)."""
    task.model.eval()
    total, count = 0.0, 0.0
    for item in val:
        s, c = task.val_error(item)
        total, count = total + s, count + c
    task.model.train()
    return total / max(1.0, count)


# what a progress callback returns to stop the run at a checkpoint (train's ``progress``)
STOP = "psctl.train.STOP"


def _resumed_state(state_file: Path, method: str, config: dict | None,
                   lcnet: str | os.PathLike | None) -> tuple[dict, dict]:
    """A run's state.json, checked against the resume's arguments: the same method, the recipe
    it started with (``config`` may only lengthen it), the same frozen LCNet. Returns (state,
    the recipe to go on with)."""
    try:
        saved = json.loads(state_file.read_text(encoding="utf-8"))
        if not isinstance(saved, dict) or "method" not in saved:
            raise ValueError("not a run's state")
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise PsctlError(state_file, f"is not a readable run state ({e}); the run cannot be resumed") from None
    check_state(state_file, saved)
    if saved["method"] != method:
        raise PsctlError(state_file, f"is a {saved['method']} run, not {method}")
    if "config" not in saved:
        raise PsctlError(state_file, "records no recipe (a run from an older psctl): cannot resume it safely")
    # a run started by an older psctl lacks keys added since: they take their defaults
    # (which reproduce the old behaviour), so it resumes, and compares equal to its recipe
    saved["config"] = _plain_json(merge(DEFAULT_CONFIG, saved["config"]))
    # keys an older psctl let a recipe give the stream, which the run always set itself
    # (_RUN_OPTIONS, refused since session 67): dropped, which changes nothing the run did
    for part in (saved["config"].get("data"), (saved["config"].get("val") or {}).get("data")):
        for key in _RUN_OPTIONS if isinstance(part, dict) else ():
            part.pop(key, None)
    if config is not None:
        # only the length of the run and its bookkeeping may change on resume
        changed = _differences(_recipe_core(config), _recipe_core(saved["config"]))
        if changed:
            raise PsctlError(state_file, f"the run was started with another recipe ({few(changed)} "
                                         f"{'differs' if len(changed) == 1 else 'differ'}); resume "
                                         f"without --config (a run keeps its recipe) or start a new run with --out")
        config = check_recipe(config)  # a bad value is its one line, not a TypeError here
        label = _other_method(config, method)  # the one key the comparison leaves out
        if label is not None:
            raise PsctlError(state_file, f"is a {method} run, and the recipe's 'method' is {label!r}: resume "
                                         f"without --config (a run keeps its recipe)")
        asked = config["train"]["samples"]
        if asked < saved["samples"] and asked != saved["config"]["train"]["samples"]:
            # a shorter recipe would "finish" without its last samples validated (a run's own
            # length may be passed a little: its last batch)
            raise PsctlError(state_file, f"the run has seen {saved['samples']:,} samples; a recipe of "
                                         f"{asked:,} would end before them (train.samples)")
        saved["config"]["train"].update({k: config["train"][k] for k in RESUME_MAY_CHANGE})
    config = saved["config"]
    if lcnet is not None and saved.get("lcnet") and _portable(lcnet) != saved["lcnet"]:
        raise PsctlError(lcnet, f"the run's frozen LCNet is {saved['lcnet']}; resume without --lcnet")
    return saved, config


def _run_log(path: Path) -> bool:
    """Whether ``path`` reads as a run's log.jsonl: each whole line a JSON object (a line cut short
    by a kill may end it)."""
    try:
        with open(path, "rb") as f:
            text = f.read(64 << 20)
        lines = text.split(b"\n")[:-1]  # the last piece: "" after a whole line, else a cut one
        return all(isinstance(json.loads(line), dict) for line in lines if line.strip())
    except (OSError, ValueError):
        return False


def _data_sources(stream: Any) -> tuple[list[str], list[list]]:
    """What the stream says it left out (its notes), and its geometry sources with their weights
    (not where the meshes are, which may differ between machines)."""
    data_notes = list(dict.fromkeys(getattr(stream, "notes", None) or []))
    pool = getattr(stream, "pool", None)
    sources = [list(x) for x in getattr(pool, "sources", [])]
    if any(x[0] == "mesh" for x in sources):  # .obj files and a view cache draw their views differently
        bank = getattr(pool, "mesh_bank", None)
        sources.append(["mesh_from", "cache" if bank is not None else "obj",
                        sorted(set(bank.names)) if bank is not None else sorted(m[0] for m in pool.mesh_data)])
    return data_notes, sources


def train(method: str, config: dict | None, run_dir: str | os.PathLike, resume: bool = False, device: str = "auto",
          max_seconds: float | None = None, progress: Callable[[dict], object] | None = None,
          make_stream: Callable = synth_stream, lcnet: str | os.PathLike | None = None,
          note: Callable[[str], object] | None = None, started: Callable[[], object] | None = None,
          recipe: str | os.PathLike | None = None) -> dict:
    """Train ``method`` with ``config``; checkpoints and logs in ``run_dir``; returns the final state.

    Args:
        method: "ps-fcn", "ps-fcn-n", "ups-fcn", "lcnet" or "ps-fcn-dagger".
        config: merged recipe (see ``load_config``). A resumed run keeps the recipe it started
            with (saved in state.json): pass None, or the same recipe (another one is an error).
        run_dir: run folder; with ``resume`` its checkpoint is continued.
        device: "auto" (CUDA where there is one), "cpu", "cuda" or "cuda:N".
        max_seconds: stop (with a checkpoint) after this much wall time in this call, so a run
            can be split into commands of a fixed length.
        progress: called with a status dict after each logged step; if it returns ``STOP`` (it
            can no longer report: the CLI's stderr lost its reader), the run stops at a checkpoint
            as on a signal, and the returned state's ``signal`` is SIGPIPE's number. Any other
            value is ignored (tqdm's ``update`` returns True when it redraws).
        make_stream: the stream factory (default ``synth_stream``): returns an object with
            ``next_batch()``, and ``state_dict()`` / ``load_state_dict()`` for exact resumption.
        lcnet: ps-fcn-dagger only: the frozen LCNet's weights file (default: the recipe's
            ``lcnet.weights``, else weights/lcnet.pt; a resumed run keeps the file it started with,
            and refuses it if its contents changed).
        note: called with each note on the data at the start (the stream had no training
            meshes: procedural shapes only); the notes are also in state.json and the weights'
            metadata (``data_notes``).
        started: called once when every check has passed, before the data notes, the validation
            set and the run folder (a log's first line: a run refused at once prints none).
        recipe: the file ``config`` was read from, named in the errors about the recipe that
            name no other file (a resumed run's recipe is its state.json's, named instead).

    Side effects on the process: torch's global generator is seeded (the initial weights), and
    on a CPU ``keep_freed_memory`` keeps the heap at its peak size afterwards.
    """
    with contextlib.ExitStack() as held:  # the run folder's lock (psctl.checkpoint.run_lock), held to the end
        return _train(method, config, run_dir, resume, device, max_seconds, progress, make_stream, lcnet, note,
                      started, recipe, held)


def _train(method: str, config: dict | None, run_dir: str | os.PathLike, resume: bool, device: str,
           max_seconds: float | None, progress: Callable[[dict], object] | None, make_stream: Callable,
           lcnet: str | os.PathLike | None, note: Callable[[str], object] | None,
           started: Callable[[], object] | None, recipe: str | os.PathLike | None,
           held: contextlib.ExitStack) -> dict:
    from psctl.infer import pick_device
    from psctl.io.atomic import atomic_path
    from psctl.models.weights import save_weights

    method = check_method(method)
    config = _full_recipe(config)
    if lcnet is not None and method != "ps-fcn-dagger":
        raise PsctlError(lcnet, f"--lcnet is for ps-fcn-dagger (the frozen LCNet), not {method}")
    dev = pick_device(device)
    if dev.type == "cpu":
        keep_freed_memory()  # about 20 % faster CPU steps (see keep_freed_memory)
    run = Path(run_dir)
    if run.exists() and not run.is_dir():
        raise PsctlError(run, f"is a file; {'--resume' if resume else '--out'} takes a run folder")
    state_file = run / "state.json"
    existed = run.is_dir()
    if existed:  # before any of its files is touched (finish_checkpoint below)
        held.enter_context(run_lock(run))
    if resume and run.is_dir():
        finish_checkpoint(run)  # one a hard kill left committed but not carried out (or only staged)
    if resume and not run.exists():
        raise PsctlError(run, "no such run folder to resume")
    if resume and not state_file.is_file():
        began = (run / "log.jsonl").is_file()  # a run of ours, stopped (kill -9?) before its first checkpoint
        raise PsctlError(state_file, "no checkpoint to resume (state.json missing)" + (
            ": the run stopped before its first checkpoint (train.checkpoint_minutes apart); start it again in a "
            "new folder, or remove this one" if began else ""))
    if not resume and (state_file.is_file() or (run / JOURNAL).is_file()):
        raise PsctlError(run, "already holds a run; pass --resume to continue it or choose another --out")
    # a run writes log.jsonl, optim.*.pt, ... there; a folder with only a log.jsonl is a run of
    # ours that stopped before its first checkpoint (configs/gpu_session.sh starts it again),
    # perhaps killed while it was staged (its staged files go)
    if not resume and run.is_dir() and not (run / JOURNAL).exists() and all(
            p.name in ("log.jsonl", "best.pt") or p.name.startswith(STAGED) or TEMP_FILE.fullmatch(p.name)
            for p in run.iterdir()):
        finish_checkpoint(run)
    if not resume and (run / "log.jsonl").is_file() and not _run_log(run / "log.jsonl"):  # appended to (a review)
        raise PsctlError(run / "log.jsonl", "is not a psctl training log (a line that is not a JSON record); a new "
                                            "run needs a new or empty folder")
    if not resume and run.is_dir() and [p.name for p in run.iterdir()] not in ([], ["log.jsonl"]):
        if sorted(p.name for p in run.iterdir()) == ["best.pt", "log.jsonl"]:  # kept by no_half_run
            raise PsctlError(run, "holds the best.pt of a run that failed before its first checkpoint (nothing to "
                                  "resume); keep it and choose another --out, or remove the folder")
        raise PsctlError(run, "is not empty and holds no run (no state.json); a new run needs a new or empty folder")
    from psctl.io.atomic import check_output_dir

    check_output_dir(run)  # one line naming the folder, not its log or a temporary file (helper-201)
    saved = None
    if resume:
        saved, config = _resumed_state(state_file, method, config, lcnet)
    if config is None:
        config = load_config(None)
    source = state_file if resume else recipe  # where the recipe's errors point
    with naming(source) if source is not None else contextlib.nullcontext():
        config = check_recipe(config)  # a recipe given as a dict, not through load_config
        check_method_recipe(method, config, stream=make_stream is synth_stream)
        if make_stream is synth_stream:
            check_memory(config, dev, method)
    t = config["train"]

    use_amp, amp_dtype = amp_settings(t["amp"], dev)

    def amp():
        return torch.autocast(dev.type, dtype=amp_dtype, enabled=use_amp)

    st: dict[str, Any] = {"step": 0, "samples": 0, "seconds": 0.0, "best_val": None, "best_samples": None,
                          "stream_seed": t["seed"], "method": method, "val": [], "config": _plain_json(config)}
    if saved is not None:
        st = saved
        lcnet = saved.get("lcnet") or lcnet  # the frozen LCNet the run started with

    torch.manual_seed(t["seed"])  # initial weights (the stream has its own generator)
    task = lcnet_task(config, dev, amp) if method == "lcnet" else normals_task(method, config, dev, amp, lcnet)
    model = task.model
    if "lcnet" in task.metadata:
        st["lcnet"] = _portable(task.metadata["lcnet"]["path"])
        digest = task.metadata["lcnet"]["sha256"]
        if saved is not None and saved.get("lcnet_sha256") not in (None, digest):
            # the documented flow replaces weights/lcnet.pt (train lcnet --install --force)
            raise PsctlError(task.metadata["lcnet"]["path"], "is not the frozen LCNet this run started with (its "
                                                              "contents changed since); put that file back to resume")
        st["lcnet_sha256"] = digest
    if saved is not None and st["samples"] >= t["samples"]:
        # finished already (`--resume RUN --install` installs it): nothing to train, so no stream or
        # validation set is rendered (6 of 7 s with the docs' 2-step recipe, helper-183; tens of
        # seconds at a real recipe's sizes) and the checkpoint is left as it is; after the frozen
        # LCNet's check above (PS-FCN† is installed to run on that LCNet's lights, helper-184)
        st["finished"], st["signal"] = True, None
        return st
    if t["init"] and not resume:  # fine-tuning: start from another run's weights (recorded)
        st["init"] = init_from(model, t["init"])
    if st.get("init"):
        task.metadata["init"] = st["init"]
    if t["channels_last"]:
        model.to(memory_format=torch.channels_last)  # in place: the task's closures hold this module
    optim = torch.optim.Adam(model.parameters(), lr=t["lr"], betas=tuple(t["betas"]), weight_decay=t["weight_decay"])
    if resume:
        restore_checkpoint(run, st, method, model, optim, dev)

    stream = make_stream(config["data"], batch_size=t["batch_size"], images=t["images_per_sample"],
                         crop=t["crop"], seed=st["stream_seed"], device=dev)
    if resume and hasattr(stream, "load_state_dict"):  # without it the run would go on, but not exactly
        restore_stream(run, st, stream)
    # what the stream had to leave out (no training meshes: procedural shapes only), said and
    # recorded; a resume must see the same data as the run's start
    data_notes, sources = _data_sources(stream)
    if saved is not None and "data_sources" in saved and saved["data_sources"] != sources:
        was = "; ".join(saved.get("data_notes") or []) or "every source"
        raise PsctlError(state_file, f"the run's data differ from its start (then: {was}; now: "
                                     f"{'; '.join(data_notes) or 'every source'}): it cannot continue exactly")
    st["data_notes"], st["data_sources"] = data_notes, sources
    if started is not None:
        started()
    if note is not None:
        for n in data_notes:
            note(f"data: {n}")
    val = validation_set(config, task, dev, make_stream)
    # where fine-tuning starts from, measured before the folder exists (Ctrl-C here leaves none)
    init_mae = evaluate(task, val) if st.get("init") and st["samples"] == 0 and not st["val"] else None
    metric = f"synthetic_val_{task.metric}"

    def metadata(metrics: dict) -> dict:
        return {"method": method, "architecture": dict(model.config), **task.metadata,
                "train_images": t["images_per_sample"], "recipe": config,
                "data": "psctl synthetic stream (psctl.synth), generated on the fly",
                "samples_seen": st["samples"], "wall_seconds": round(st["seconds"], 1),
                "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"cpu: {cpu_name()} ({os.cpu_count()} cores)",
                "precision": f"{str(amp_dtype).removeprefix('torch.')} autocast" if use_amp else "float32",
                "metrics": metrics, **({"data_notes": data_notes} if data_notes else {})}

    def stage() -> list[str]:
        files = save_optimizer(run, optim, STAGED)
        if hasattr(stream, "state_dict"):
            with atomic_path(run / (STAGED + "stream.pt")) as tmp:
                save_torch({"samples": st["samples"], "stream": stream.state_dict()}, tmp)
            files.append("stream.pt")
        # model.pt's own validation (at this very sample count), not the run's best so far
        own = st["val"][-1][1] if st["val"] and st["val"][-1][0] == st["samples"] else None
        save_weights(run / (STAGED + "model.pt"), model, metadata({metric: own}))
        return files + ["model.pt"]

    def checkpoint() -> None:
        previous = st.get("optim_files") or []
        try:
            files = stage()
        except PsctlError as e:  # a full disk: the file by its own name (its staged one is removed)
            name = Path(e.path).name if e.path else ""
            if not name.startswith(STAGED):
                raise
            raise PsctlError(run / name[len(STAGED):], e.message) from None
        st["optim_files"] = [n for n in files if OPTIM_PART.fullmatch(n)]
        st["optim_step"] = max(adam_steps(optim), default=None)
        log.flush()
        st["log_bytes"] = os.fstat(log.fileno()).st_size  # a resume after a hard kill drops what was logged after this
        st["loss_avg"] = loss_avg
        commit_checkpoint(run, files, st, previous)

    t_call = time.perf_counter()
    t_start = t_ckpt = t_call
    t_log, samples_log = t_call, st["samples"]
    next_val = (st["samples"] // t["val_every"] + 1) * t["val_every"]
    # the logged loss: an exponential moving average (0.9) of the steps' losses, kept across a resume
    loss_avg = st.get("loss_avg")
    if resume and st.get("log_bytes") is not None:
        drop_lines_after_checkpoint(run / "log.jsonl", st["log_bytes"], st["samples"])
    # the folder is made only now: a bad recipe (crop > size, ...) leaves none behind
    def kept() -> str:
        return ("the last checkpoint is kept" if state_file.is_file() else
                f"no checkpoint had been written; best.pt (validated at {st['best_samples']:,} samples) is kept"
                if st["best_val"] is not None else "no checkpoint had been written, so nothing is kept")

    if init_mae is not None and not math.isfinite(init_mae):  # before the run folder exists
        raise PsctlError(run, f"validation {task.metric} of train.init's weights is {init_mae} (no object pixel in "
                              f"the validation views? see val.data, data.shapes, data.blobby): nothing was trained")
    with no_half_run(run, None if existed else held) as log, Stop() as stop:
        if init_mae is not None:
            st["val"].append([0, round(init_mae, 4)])
            log.write(json.dumps({"samples": 0, f"val_{task.metric}": round(init_mae, 4), "init": st["init"]["path"]}) + "\n")
            log.flush()
        model.train()
        while st["samples"] < t["samples"]:
            for g in optim.param_groups:
                g["lr"] = lr_at(st["samples"], config)
            batch = stream.next_batch()
            if "masks" in batch and not bool(batch["masks"].any()):  # a loss of exactly 0: nothing learnt
                raise PsctlError(run, f"training batch {st['step'] + 1} has no object pixel ({st['samples']:,} samples "
                                      f"seen; see data.shapes, data.blobby): stopped; {kept()}")
            loss = task.loss(batch)
            if not torch.isfinite(loss):  # stop before the step spoils the weights; the last checkpoint stays
                raise PsctlError(run, f"training loss is {loss.item()} at step {st['step'] + 1} "
                                      f"({st['samples']:,} samples seen): stopped; {kept()}")
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            st["step"] += 1
            st["samples"] += batch["images"].shape[0]
            loss_avg = loss.item() if loss_avg is None else 0.9 * loss_avg + 0.1 * loss.item()
            now = time.perf_counter()
            if st["step"] % t["log_every"] == 0 or st["samples"] >= t["samples"]:
                rate = (st["samples"] - samples_log) / max(now - t_log, 1e-9)
                rec = {"step": st["step"], "samples": st["samples"], "loss": round(loss_avg, 5),
                       "lr": optim.param_groups[0]["lr"], "samples_per_s": round(rate, 1),
                       "seconds": round(st["seconds"] + now - t_call, 1)}
                log.write(json.dumps(rec) + "\n")
                log.flush()
                if progress and progress({**rec, "total": t["samples"]}) is STOP and not stop.requested:
                    # the caller can no longer report (its reader went away): stop as on a signal,
                    # at a checkpoint, as if SIGPIPE had been caught
                    stop.requested, stop.signal = True, int(signal.SIGPIPE) if hasattr(signal, "SIGPIPE") else 13
                t_log, samples_log = now, st["samples"]
            if st["samples"] >= next_val or st["samples"] >= t["samples"]:
                mae = evaluate(task, val)
                if not math.isfinite(mae):  # never a best.pt, never installed (an audit: steps 0 shapes, exit 0)
                    raise PsctlError(run, f"validation {task.metric} is {mae} at {st['samples']:,} samples (no object "
                                          f"pixel in the validation views? see data.shapes, data.blobby): stopped; "
                                          f"{kept()}")
                st["val"].append([st["samples"], round(mae, 4)])
                log.write(json.dumps({"samples": st["samples"], f"val_{task.metric}": round(mae, 4)}) + "\n")
                log.flush()
                if st["best_val"] is None or mae < st["best_val"]:
                    st["best_val"], st["best_samples"] = mae, st["samples"]
                    st["seconds"] += now - t_call
                    t_call = now
                    save_weights(run / "best.pt", model, metadata({metric: round(mae, 4)}))
                next_val += t["val_every"]
            out_of_time = max_seconds is not None and now - t_start >= max_seconds
            if stop.requested or out_of_time or now - t_ckpt > 60 * t["checkpoint_minutes"]:
                st["seconds"] += now - t_call
                t_call = now
                with stop.whole():
                    checkpoint()
                t_ckpt = time.perf_counter()
                if stop.requested or out_of_time:
                    break
        else:
            st["seconds"] += time.perf_counter() - t_call
            with stop.whole():
                checkpoint()
    st["finished"] = st["samples"] >= t["samples"]
    st["signal"] = stop.signal  # not in state.json: how this call ended (None, or SIGINT / SIGTERM / SIGHUP's number)
    stop.pass_on()  # the caller's own handler of that signal (a service's shutdown hook) hears of it too
    return st


def _same_lcnet(a: Any, b: Any) -> bool:
    """Two PS-FCN† files' frozen LCNet records (``frozen_lcnet``'s) name one network: the same
    sha256 where both record it (a copy at another path is the same), else the same record
    without it (files from before the sha256 was kept)."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return a == b
    if a.get("sha256") and b.get("sha256"):
        return a["sha256"] == b["sha256"] and a.get("decode") == b.get("decode")
    strip = lambda d: {k: v for k, v in d.items() if k != "sha256"}  # noqa: E731
    return strip(a) == strip(b)


RELEASE_MAX_BYTES = 10_000_000  # the project's limit per release weights file


# metadata that must agree for an average to be one network with one input convention (and, for
# PS-FCN†, one frozen LCNet, which sdps reads from it)
AVERAGE_SAME = ("method", "architecture", "normalization", "train_images", "input_mean", "lcnet")


def average_weights(files: list[str | os.PathLike], out_dir: str | os.PathLike, config: dict | None = None,
                    device: str = "cpu", method: str | None = None,
                    recipe_name: str | os.PathLike | None = None) -> Path:
    """Write the uniform parameter average of trained weight files as ``out_dir/best.pt``.

    Averaging fine-tuned descendants of one state (a "model soup"; SWA averages along one run)
    can generalise better than any one of them. The files must hold the same method and
    architecture with the same input convention (``AVERAGE_SAME``); tensors are averaged in
    float32 (float16 release files included). The result's metadata lists each member (path,
    sha256, samples seen, wall time, its validation) and adds up their samples and wall time.
    With ``config`` (a recipe) it measures the average on that recipe's validation set, in
    float32, as ``metrics`` (the training loop's metric) and records the set as ``validation``;
    without, ``metrics`` is empty. With ``method``, every file must hold that method's weights. A
    rule decides on it like on any run's ``best.pt``, and ``install_weights(out_dir, method)``
    installs it.
    """
    import torch

    from psctl.models.weights import _training_clip, read_weights, save_weights

    if method is not None:
        method = check_method(method, "average")
    if len(files) < 2:
        raise PsctlError(None, f"averaging needs at least two weight files, got {len(files)}")
    seen: dict = {}
    for f in files:  # one file twice would weigh it double and count its samples twice
        key = Path(f).resolve()
        if key in seen:
            raise PsctlError(f, f"is given twice (as {seen[key]} and {f}); average distinct files")
        seen[key] = f
    members = [read_weights(f) for f in files]
    for w in members:
        if method is not None and w.method != method:
            raise PsctlError(w.path, f"holds {w.method} weights, not {method}")
    first = members[0]
    if first.official:
        raise PsctlError(first.path, "only psctl's own weights can be averaged (their metadata says what they are)")
    for w in members[1:]:
        if w.official:
            raise PsctlError(w.path, "only psctl's own weights can be averaged (their metadata says what they are)")
        for key in AVERAGE_SAME:
            if key == "lcnet" and _same_lcnet(w.metadata.get(key), first.metadata.get(key)):
                continue
            if w.metadata.get(key) != first.metadata.get(key):
                raise PsctlError(w.path, f"metadata {key!r} is {w.metadata.get(key)!r}, but {first.path} has "
                                         f"{first.metadata.get(key)!r}: only the same network can be averaged")
        if set(w.state_dict) != set(first.state_dict) or any(
                w.state_dict[k].shape != v.shape for k, v in first.state_dict.items()):
            raise PsctlError(w.path, f"its parameters do not match {first.path}'s (names or shapes)")
        if _training_clip(w.metadata) != _training_clip(first.metadata):  # inference clips inputs there
            raise PsctlError(w.path, f"was trained with inputs clipped at {_training_clip(w.metadata)}, "
                                     f"{first.path} at {_training_clip(first.metadata)}: they cannot be averaged")
    avg = {}
    for k, v in first.state_dict.items():
        if v.is_floating_point():
            avg[k] = torch.stack([w.state_dict[k].float() for w in members]).mean(0)
        else:  # integer buffers (none in psctl's networks today) cannot be averaged
            if any(not torch.equal(w.state_dict[k], v) for w in members):
                raise PsctlError(None, f"integer tensor {k!r} differs between the files; it cannot be averaged")
            avg[k] = v.clone()

    def member(w) -> dict:
        m = w.metadata
        # where and how each member trained, and what it started from: without them an average
        # loses which member ran on which device (its `device` joins the set) and the lineage
        # cannot check a member's start (weights/lineage.yaml, ps_fcn.gpu14)
        return {"path": str(w.path), "sha256": file_sha256(w.path),
                "samples_seen": m.get("samples_seen"), "wall_seconds": m.get("wall_seconds"),
                "device": m.get("device"), "precision": m.get("precision"), "init": m.get("init"),
                "metrics": m.get("metrics", {}), "date": m.get("date"), "recipe": m.get("recipe")}

    meta = {key: first.metadata[key] for key in AVERAGE_SAME if key in first.metadata}
    meta.update({
        "averaged_from": [member(w) for w in members],
        "data": "the uniform parameter average of the files in averaged_from (psctl.train.average_weights)",
        "samples_seen": sum(int(w.metadata.get("samples_seen") or 0) for w in members),
        "wall_seconds": round(sum(float(w.metadata.get("wall_seconds") or 0.0) for w in members), 1),
        "device": "; ".join(sorted({str(w.metadata.get("device")) for w in members})),
        # the members' training precisions (the average itself is taken in float32); None where
        # no member recorded one
        "precision": "; ".join(sorted({str(w.metadata["precision"]) for w in members
                                       if w.metadata.get("precision")})) or None,
        "metrics": {},
    })
    # what inference reads from a recipe (the training clip, psctl.models.weights.for_method)
    recipe = first.metadata.get("recipe")
    data = recipe.get("data") if isinstance(recipe, dict) else None
    meta["recipe"] = {"average_of": len(members), "data": {
        "intensities": data.get("intensities", "unit") if isinstance(data, dict) else "unit",
        "clip": _training_clip(first.metadata)}}
    out = Path(out_dir) / "best.pt"
    if out.exists():
        raise PsctlError(out, "already exists; averaging writes a new run folder's best.pt")
    if Path(out_dir).is_dir() and any(Path(out_dir).iterdir()):  # as a new training run: never beside others' files
        raise PsctlError(out_dir, "is not empty; averaging writes best.pt into a new or empty folder")
    from psctl.io.atomic import check_output_dir

    check_output_dir(out_dir)  # named, not the temporary file best.pt is written through (helper-201)
    if config is not None:  # the training loop's validation, on the recipe's fixed set
        from psctl.infer import pick_device

        method, dev = first.metadata["method"], pick_device(device)
        with naming(recipe_name) if recipe_name is not None else contextlib.nullcontext():  # as training's
            config = check_recipe(_full_recipe(config))
            check_method_recipe(method, config)  # as training's: keys the run sets, windows, stream options
            norm = first.metadata.get("normalization") or "none"
            if config["normalization"] not in (None, norm):  # it would be measured with other inputs
                raise PsctlError(None, f"config 'normalization' is {config['normalization']!r} but the averaged "
                                       f"files were trained with {norm!r}; measure them on a recipe with "
                                       f"normalization {norm!r} or null")
            config["normalization"] = norm  # the files' inputs, whatever the method's default
        amp = lambda: torch.autocast(dev.type, enabled=False)  # noqa: E731 (float32)
        # PS-FCN† is measured on the lights of the LCNet its members were trained with (AVERAGE_SAME
        # makes them agree), not the recipe's or the installed one
        frozen = (first.metadata.get("lcnet") or {}).get("path") if method == "ps-fcn-dagger" else None
        task = lcnet_task(config, dev, amp) if method == "lcnet" else normals_task(method, config, dev, amp, frozen)
        try:
            task.model.load_state_dict(avg)
        except RuntimeError as e:
            raise PsctlError(None, f"the recipe builds another network than the averaged files "
                                   f"({' '.join(str(e).split())[:160]})") from None
        mae = evaluate(task, validation_set(config, task, dev, synth_stream))
        meta["metrics"] = {f"synthetic_val_{task.metric}": round(mae, 4)}
        meta["validation"] = {"val": config["val"], "data": config["data"]}
    out.parent.mkdir(parents=True, exist_ok=True)
    return save_weights(out, avg, meta)


def check_install(method: str, replace: bool = False) -> None:
    """Before a run whose weights will be installed (``psctl train --install``; in Python, call
    it before ``train`` and ``install_weights``): hours of training must not end in a refusal. The
    weights folder must be a folder (or not exist yet), and ``method``'s release file absent
    unless ``replace``."""
    from psctl.models.weights import installed_path, weights_dir

    method = check_method(method, "install")
    if weights_dir().exists() and not weights_dir().is_dir():
        raise PsctlError(weights_dir(), "is not a folder: --install writes the weights there ($PSCTL_WEIGHTS)")
    if not replace and installed_path(method) is not None:
        raise PsctlError(installed_path(method), "already installed: --install replaces it only with --force "
                                                 "(in Python: replace=True)")


def check_train_options(method: str, config: str | os.PathLike | None = None, out: str | os.PathLike | None = None,
                        resume: str | os.PathLike | None = None, device: str = "auto",
                        max_minutes: float | None = None, install: bool = False, force: bool = False,
                        lcnet: str | os.PathLike | None = None,
                        average: Sequence[str | os.PathLike] | None = None) -> tuple[str, dict | None]:
    """The rules ``psctl train``'s options follow, checked before any work (hours of training must
    not end in a refusal): one line naming the option, or ``(method, recipe)``: the method as the
    command line takes it and the loaded recipe. The recipe is None for a resumed run without
    ``config`` (it keeps its own, in state.json) and for an average without one (then nothing is
    measured). ``average``: files to average into ``out`` instead of training. The errors name the
    command's options (``--max-minutes`` for ``max_minutes``)."""
    if force and not install:
        raise PsctlError("--force", "only replaces an installed file together with --install")
    if max_minutes is not None and (isinstance(max_minutes, bool) or not isinstance(max_minutes, (int, float))
                                    or not (math.isfinite(max_minutes) and max_minutes > 0)):
        raise PsctlError("--max-minutes", f"must be a positive number of minutes, not {max_minutes}")
    if install:  # said before hours of training
        check_install(method, replace=force)
    method = check_method(method)  # before anything else is said about the other options
    if average:
        if resume is not None or out is None:
            raise PsctlError("--average", "takes weight files and --out RUN (and --config RECIPE to measure it on "
                                          "the recipe's validation set)" + (", not --resume" if resume else ""))
        if max_minutes is not None or lcnet is not None:  # averaging trains nothing: they would do nothing
            raise PsctlError("--max-minutes" if max_minutes is not None else "--lcnet",
                             "is for training; --average only averages" +
                             (" (the members keep their own LCNet)" if max_minutes is None else ""))
        from psctl.infer import pick_device

        pick_device(device)  # --device tpu, or cuda without CUDA: refused even when nothing is measured
        if install and config is None:  # install_weights would refuse the result afterwards
            raise PsctlError("--install", "with --average needs --config RECIPE: a release file records "
                                          "its validation on the recipe's set")
        return method, load_config(config) if config is not None else None
    if resume is not None and out is not None and Path(out).resolve() != Path(resume).resolve():
        raise PsctlError(out, "--out is for a new run; --resume continues the run in its own folder")
    # a resumed run keeps its own recipe (state.json); --config then only has to agree with it
    cfg = load_config(config) if config is not None or resume is None else None
    if cfg is not None and config is not None:  # the recipe against the network, named by its file
        with naming(config):
            check_method_recipe(method, cfg)
    return method, cfg


def install_weights(run_dir: str | os.PathLike, method: str, replace: bool = False) -> Path:
    """Copy a run's best weights into the weights folder as the release file for ``method``.

    An installed file is replaced only with ``replace=True``: the release files are chosen by
    rules on synthetic sets (docs/training.md), and a smoke run must not overwrite them silently.
    A file over RELEASE_MAX_BYTES (LCNet's 4.4 M parameters take 17.6 MB in float32) is stored
    with float16 tensors instead, recorded as ``stored_dtype`` in its metadata; loading casts
    them back to the network's float32 parameters. A file without its own synthetic validation
    (an average made without a recipe) is refused: the model card quotes it for every file.
    """
    import shutil

    import torch

    from psctl.io.atomic import atomic_path
    from psctl.models.weights import file_name, installed_path, read_weights, save_weights, weights_dir

    method = check_method(method, "install")
    src = Path(run_dir) / "best.pt"
    if not src.is_file():
        validated = False  # which of the two: the run's state says
        with contextlib.suppress(OSError, ValueError, AttributeError):
            validated = json.loads((Path(run_dir) / "state.json").read_text(encoding="utf-8")).get("best_val") is not None
        if validated:
            raise PsctlError(src, "is missing: the run's best validation was saved there, and the file was removed since")
        raise PsctlError(src, "no best weights in this run yet")
    w = read_weights(src)
    if w.method != method:
        raise PsctlError(src, f"holds {w.method} weights, not {method}")
    metrics = w.metadata.get("metrics") or {}
    if not any(k.startswith("synthetic_val_") and v is not None for k, v in metrics.items()):
        # the model card quotes every release file's own validation; an average has one only if measured
        raise PsctlError(src, "records no synthetic validation metric, which a release file needs "
                              "(for an average: psctl train METHOD --average ... --config RECIPE)")
    dst = weights_dir() / file_name(method)
    if installed_path(method) is not None and not replace:
        raise PsctlError(dst, f"already installed; {src} was not copied (replace it on purpose with --install --force)")
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.stat().st_size <= RELEASE_MAX_BYTES:
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
        return dst
    half = {k: v.to(torch.float16) if v.is_floating_point() else v for k, v in w.state_dict.items()}
    with atomic_path(dst) as tmp:  # the size is checked before anything is replaced
        save_weights(tmp, half, {**w.metadata, "stored_dtype": "float16"})
        if tmp.stat().st_size > RELEASE_MAX_BYTES:
            raise PsctlError(src, f"needs {tmp.stat().st_size / 1e6:.1f} MB even in float16 "
                                  f"(limit {RELEASE_MAX_BYTES / 1e6:.0f} MB per release file)")
    return dst


# names that moved to psctl.checkpoint on 2026-12-01, still found here (with a warning)
__getattr__ = moved_names(__name__, "psctl.checkpoint")

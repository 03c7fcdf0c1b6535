"""Network weights: where installed weights live, the two file formats psctl reads, saving ours.

Installed weights are found by method name: ``<weights dir>/<method>.pt`` with ``-`` written as
``_`` (``ps-fcn-n`` -> ``ps_fcn_n.pt``). The weights dir is ``$PSCTL_WEIGHTS`` when set, else
``weights/`` at the repository root (an editable install; a wheel carries no weights).

psctl's format, a ``torch.save`` of plain containers, read with ``torch.load(weights_only=True)``
(tensors, dicts, lists, strings and numbers only: loading never runs pickled code):

    {"format": "psctl-weights", "version": 1,
     "state_dict": {parameter name: tensor},
     "metadata": {"method": "ps-fcn-n", "architecture": {PSFCN config},
                  "normalization": "per-channel", "train_images": q,
                  "input_mean": m (without +N: the mean observation it was trained at),
                  "recipe": {...}, "data": ..., "date": "...", "metrics": {...}, ...}}

The authors' release format, ``*.pth.tar`` = ``{"state_dict": ..., "model": "PS_FCN"}``, loads too
(``--weights FILE``); it records neither the method nor +N, so the method given by the user
decides the normalisation, with q = 32 (the authors' ``train_img_num``).

LCNet (method ``lcnet``, SDPS-Net's lighting calibration network) uses the same format with its
own architecture config; the authors' ``LCNet_CVPR2019.pth.tar`` is recognised by its
``featExtractor.*`` keys and checked as strictly. Their stage-2 ``NENet_CVPR2019.pth.tar`` has
PS-FCN's keys and runs as ``ps-fcn-dagger``.
"""

from __future__ import annotations

import datetime
import errno
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from psctl.errors import PsctlError, check_path, not_a_file
from psctl.models import NETWORK_METHODS, WEIGHTS_METHODS

if TYPE_CHECKING:  # torch is imported inside the functions: finding files must stay cheap
    import torch

    from psctl.models.lcnet import LCNet
    from psctl.models.ps_fcn import PSFCN

FORMAT = "psctl-weights"
VERSION = 1
SUFFIX = ".pt"
OFFICIAL_TRAIN_IMAGES = 32  # the authors' --train_img_num default, the q of their +N model
ENV_VAR = "PSCTL_WEIGHTS"
_SHOW = 3  # how many offending keys an error message names


@dataclass
class Weights:
    """A weights file, read and checked for format (not yet against an architecture)."""

    path: Path
    state_dict: dict[str, "torch.Tensor"]
    metadata: dict[str, Any]
    official: bool  # the authors' *.pth.tar format (no psctl metadata)

    @property
    def method(self) -> str | None:
        return self.metadata.get("method")

    @property
    def lights(self) -> bool:
        return bool(self.metadata["architecture"].get("lights", True))

    @property
    def kind(self) -> str:
        """The architecture family: "ps-fcn" (PS-FCN, UPS-FCN, PS-FCN†) or "lcnet"."""
        return self.metadata.get("kind") or WEIGHTS_METHODS[self.metadata["method"]]["architecture"]


# --- where ------------------------------------------------------------------------------------

def weights_dir() -> Path:
    """$PSCTL_WEIGHTS if set, else weights/ of the source checkout psctl runs from (next to the
    psctl package), else (an installed wheel) weights/ in the user's data folder,
    ~/.local/share/psctl/weights (``psctl.paths``)."""
    from psctl.paths import checkout_root, user_data_dir

    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser()
    root = checkout_root()
    return root / "weights" if root is not None else user_data_dir() / "weights"


def install_hint() -> str:
    """For a weights-not-found message of an installed wheel (``pip install .`` copies the package,
    not the release weights beside it): where to put them. Empty in a checkout or with $PSCTL_WEIGHTS."""
    from psctl.paths import checkout_root

    if os.environ.get(ENV_VAR) or checkout_root() is not None:
        return ""
    return (f"; psctl's release weights are in the weights/ folder of its source checkout: copy the .pt files "
            f"into {weights_dir()}, or set ${ENV_VAR} to the checkout's weights/ folder")


def source_files_note() -> str:
    """For a message that names configs/ or docs/ files: an installed wheel has neither."""
    from psctl.paths import checkout_root

    return "" if checkout_root() is not None else " (configs/ and docs/ are in psctl's source checkout, not in the wheel)"


def weights_where() -> str:
    """The weights folder for a message: with $PSCTL_WEIGHTS, says so, and whether it is missing
    (a mistyped variable would otherwise look like weights that were never installed)."""
    d = weights_dir()
    if not os.environ.get(ENV_VAR):
        return f"{d}{install_hint()}"
    return f"{d} (${ENV_VAR}" + ("" if d.is_dir() else _not_a_folder(d)) + ")"


def missing_folder_note() -> str:
    """For a weights-not-found message: when $PSCTL_WEIGHTS names a folder that does not exist
    (a mistyped variable, not weights never installed), say so."""
    if os.environ.get(ENV_VAR) and not weights_dir().is_dir():
        return f", in ${ENV_VAR}'s folder{_not_a_folder(weights_dir())}"
    return ""


def _not_a_folder(d: Path) -> str:
    return ", which is a file, not a folder" if d.exists() else ", which does not exist"


def file_name(method: str) -> str:
    """The release file name of ``method``'s weights: ps-fcn-n -> ps_fcn_n.pt."""
    return method.replace("-", "_") + SUFFIX


def file_sha256(path: str | os.PathLike) -> str:
    """A file's sha256 (hex), read in blocks: which weights produced a result, whatever their name."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def installed_path(method: str) -> Path | None:
    """The installed weights file of a network method, or None."""
    p = weights_dir() / file_name(method)
    return p if p.is_file() else None


# what to suggest when the uncalibrated networks' weights are missing: the recipe and the
# authors' release file
_TRAIN_HINTS = {"lcnet": ("configs/lcnet.yaml", "LCNet_CVPR2019.pth.tar"),
                "ps-fcn-dagger": ("configs/ps_fcn_dagger.yaml", "NENet_CVPR2019.pth.tar")}


def no_weights_error(method: str, flag: str = "--weights") -> PsctlError:
    """The error for ``method`` with nothing installed: where it looked, and how to train or pass a file."""
    # where it looked; then how to point psctl elsewhere (a wheel's hint says it already)
    where = f"{weights_dir() / file_name(method)}{missing_folder_note()}" + (
        install_hint() or f"; set ${ENV_VAR} to use another folder")
    if method in _TRAIN_HINTS:
        recipe, official = _TRAIN_HINTS[method]
        return PsctlError(
            None,
            f"no weights are installed for {method} (looked for {where}). Train them with `psctl train {method} "
            f"--config {recipe} --install` (a GPU is needed, see docs/training.md), or pass a weights file with "
            f"{flag} FILE: psctl's own or the authors' {official} (docs/uncalibrated.md){source_files_note()}",
        )
    if method == "ups-fcn":  # no lights: l2 is no alternative, sdps is
        return PsctlError(
            None,
            f"no weights are installed for ups-fcn (looked for {where}). Pass a weights file with --weights FILE: "
            f"psctl's own format or the authors' UPS-FCN_B_S_32.pth.tar (docs/models.md), or use --method sdps",
        )
    return PsctlError(
        None,
        f"no weights are installed for {method} (looked for {where}). Pass a weights file with --weights FILE: "
        f"psctl's own format or the authors' released checkpoint (e.g. PS-FCN_B_S_32.pth.tar for ps-fcn, "
        f"PS-FCN_B_S_32_normalize.pth.tar for ps-fcn-n; see docs/models.md), or use --method l2",
    )


# --- read -------------------------------------------------------------------------------------

def _torch_load(path: Path) -> Any:
    import pickle
    import re
    import warnings

    import torch

    def detail(e: BaseException, limit: int) -> str:
        if isinstance(e, LookupError):  # KeyError(101) from inside the unpickler says "101"
            return f"the unpickler failed: {type(e).__name__}"
        text = " ".join(str(e).split()).split(". This is an internal")[0] or type(e).__name__  # torch's advice to itself
        return text if len(text) <= limit else text[:limit].rsplit(" ", 1)[0] + " ..."

    try:
        with warnings.catch_warnings():
            # torch warns about the pickle protocol of a file that is not its own, then fails on it
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        text = " ".join(str(e).split())
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        if found:  # weights_only refuses anything beyond tensors and plain containers
            raise PsctlError(path, f"refused: the file holds a Python object ({found.group(1)}) besides tensors "
                                   "and plain data, and psctl never unpickles arbitrary objects") from None
        inner = re.search(r"WeightsUnpickler error: (.*?)(?: Check the documentation|$)", text)
        raise PsctlError(path, "cannot read weights file: not a torch file, or damaged ("
                               f"{detail(ValueError(inner.group(1)) if inner else e, 120)})") from None
    except MemoryError:
        raise
    except OSError as e:  # the file system's say (permissions, a folder, I/O), not the file's content
        if e.errno == errno.EINVAL:  # torch's zip reader on a cut file (an audit: "[Errno 22] Invalid argument")
            raise PsctlError(path, "cannot read weights file: damaged (cut short?)") from None
        raise PsctlError(path, f"cannot read weights file ({detail(e, 160)})") from None
    except Exception as e:  # a file that is not torch's fails in many ways (OSError, EOFError, KeyError, ...)
        empty = path.stat().st_size == 0 if path.exists() else False
        raise PsctlError(path, "cannot read weights file: " + ("the file is empty" if empty else
                               f"not a torch file, or damaged ({detail(e, 120)})")) from None


def read_weights(path: str | os.PathLike) -> Weights:
    """Read psctl's format or the authors' ``{'state_dict': ...}`` format."""
    import torch

    path = Path(check_path("weights", path))
    if not path.is_file():
        raise PsctlError(path, not_a_file(path, "weights file not found", "is a folder, not a weights file"))
    obj = _torch_load(path)
    if not isinstance(obj, dict) or "state_dict" not in obj:
        raise PsctlError(path, "not a weights file: expected a dict with a 'state_dict' entry "
                               "(psctl's format or the authors' *.pth.tar)")
    sd = obj["state_dict"]
    if not isinstance(sd, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in sd.items()):
        raise PsctlError(path, "'state_dict' is not a mapping of parameter names to tensors")
    sd = dict(sd)
    if sd and all(k.startswith("module.") for k in sd):  # saved from nn.DataParallel
        sd = {k[len("module."):]: v for k, v in sd.items()}
    check_finite(sd, path)

    if obj.get("format") == FORMAT:
        if obj.get("version") != VERSION:
            raise PsctlError(path, f"psctl weights version {obj.get('version')!r}; this psctl reads version {VERSION}")
        meta = obj.get("metadata")
        if not isinstance(meta, dict):
            raise PsctlError(path, "psctl weights without a metadata dict")
        _check_metadata(meta, path)
        return Weights(path, sd, meta, official=False)

    source = f"authors' checkpoint ({obj.get('model', 'unnamed')})"
    if any(k.startswith("featExtractor.") for k in sd):  # SDPS-Net's LCNet: 4 input channels = mask in
        w1 = sd.get("featExtractor.conv1.0.weight")
        in_mask = not (w1 is not None and w1.ndim == 4 and w1.shape[1] == 3)
        meta = {"method": "lcnet", "kind": "lcnet", "architecture": {"in_mask": in_mask, "fuse": "max"},
                "normalization": "none", "train_images": OFFICIAL_TRAIN_IMAGES, "source": source}
        return Weights(path, sd, meta, official=True)
    # The authors' PS-FCN file: the first layer's input channels say whether it takes lights.
    w1 = sd.get("extractor.conv1.0.weight")
    lights = not (w1 is not None and w1.ndim == 4 and w1.shape[1] == 3)
    meta = {"method": None, "kind": "ps-fcn", "architecture": {"lights": lights, "fuse": "max"}, "normalization": None,
            "train_images": OFFICIAL_TRAIN_IMAGES, "source": source}
    return Weights(path, sd, meta, official=True)


def check_finite(state: dict, path: Path | None) -> None:
    """PsctlError naming the first tensor with NaN or infinite entries. Such a file can still give
    finite outputs with kernels that skip zero padding (0 * NaN never computed) and NaN with
    others, so it is refused rather than trusted."""
    import numpy as np
    import torch

    for k, v in state.items():
        if not v.is_floating_point():
            continue
        # NumPy's check of CPU float32/64 tensors (no copy): torch.isfinite took 25 ms to 1 s for
        # PS-FCN's 2.2 M values on a loaded 2-core CPU, NumPy under 1 ms (helper-165)
        if v.device.type == "cpu" and v.dtype in (torch.float16, torch.float32, torch.float64):  # LCNet's file is float16
            if np.isfinite(v.detach().numpy()).all():
                continue
        elif torch.isfinite(v).all():
            continue
        bad = int((~torch.isfinite(v)).sum())
        raise PsctlError(path, f"{k} has {bad:,} NaN or infinite values (of {v.numel():,}): not usable weights")


def normalization_allowed(method: str, norm: str) -> bool:
    """Whether ``method``'s weights may take inputs normalised by ``norm``: LCNet and PS-FCN have no
    +N, PS-FCN+N needs it (the two differ only by it); UPS-FCN and PS-FCN† may be trained with or
    without it. The loader below and psctl train's recipe check share this rule."""
    if method not in NETWORK_METHODS:  # lcnet
        return norm == "none"
    return method not in ("ps-fcn", "ps-fcn-n") or (method == "ps-fcn-n") == (norm != "none")


def _check_metadata(meta: dict, path: Path | None) -> None:
    from psctl.models.ps_fcn import NORMALIZATIONS

    method = meta.get("method")
    if method not in WEIGHTS_METHODS:
        raise PsctlError(path, f"metadata 'method' is {method!r}; expected one of {', '.join(WEIGHTS_METHODS)}")
    if not isinstance(meta.get("architecture"), dict):
        raise PsctlError(path, "metadata 'architecture' must be a dict (the network config)")
    norm = meta.get("normalization")
    if norm not in NORMALIZATIONS:
        raise PsctlError(path, f"metadata 'normalization' is {norm!r}; expected one of {', '.join(NORMALIZATIONS)}")
    q = meta.get("train_images")
    if not isinstance(q, int) or isinstance(q, bool) or q < 1:
        raise PsctlError(path, f"metadata 'train_images' (q, images per training sample) must be a positive integer, got {q!r}")
    im = meta.get("input_mean")
    if im is not None and (isinstance(im, bool) or not isinstance(im, (int, float)) or not math.isfinite(im) or im <= 0):
        raise PsctlError(path, f"metadata 'input_mean' must be a positive number, got {im!r}")
    if method not in NETWORK_METHODS:  # lcnet: no lights input, no +N
        if not normalization_allowed(method, norm):
            raise PsctlError(path, f"metadata says {method} with normalization {norm!r}; it has none")
        return
    if bool(meta["architecture"].get("lights", True)) != NETWORK_METHODS[method]["lights"]:
        raise PsctlError(path, f"metadata says {method} but the architecture's 'lights' is {meta['architecture'].get('lights')}")
    if not normalization_allowed(method, norm):
        raise PsctlError(path, f"metadata says {method} with normalization {norm!r}: ps-fcn-n needs +N, ps-fcn has none")


def for_method(weights: Weights, method: str) -> dict:
    """How to run ``weights`` as ``method``: {"normalization", "train_images", "architecture", "input_mean",
    "input_clip"}.

    ``input_mean`` (our files without +N): the mean observation the network was trained at;
    inference scales each capture to it, then clips at ``input_clip`` (the training data's sensor
    saturation, the recipe's ``data.clip``). None for the authors' files and for +N.

    Our files must match the method they were trained for; the authors' files take the
    normalisation from the method (they do not record it).
    """
    if method not in WEIGHTS_METHODS:
        raise PsctlError(None, f"{method!r} is not a network method ({', '.join(WEIGHTS_METHODS)})")
    spec = WEIGHTS_METHODS[method]
    if weights.kind != spec["architecture"]:
        what = "LCNet (light estimation)" if weights.kind == "lcnet" else "a PS-FCN-style network (normals)"
        raise PsctlError(weights.path, f"holds the weights of {what}; they cannot run as {method}")
    if weights.official and spec["architecture"] == "lcnet":
        return {"normalization": "none", "train_images": OFFICIAL_TRAIN_IMAGES,
                "architecture": dict(weights.metadata["architecture"])}
    if weights.official:
        if weights.lights != spec["lights"]:
            has = "takes light directions (PS-FCN)" if weights.lights else "takes no lights (UPS-FCN)"
            raise PsctlError(weights.path, f"this checkpoint {has}; it cannot run as {method}")
        return {"normalization": spec["normalization"], "train_images": OFFICIAL_TRAIN_IMAGES,
                "architecture": dict(weights.metadata["architecture"])}
    if weights.method != method:
        use = {"ps-fcn-dagger": "--method sdps (with --weights)", "lcnet": "psctl lights, or --lcnet with --method sdps"}
        instead = use.get(weights.method, f"--method {weights.method}")
        if Path(weights.path).resolve() == (weights_dir() / file_name(method)).resolve():  # installed, not --weights
            raise PsctlError(weights.path, f"holds {weights.method} weights, not {method}: the file installed for "
                                           f"{method} is another network's; replace it (docs/training.md), or use "
                                           f"{instead} with --weights {weights.path}")
        raise PsctlError(weights.path, f"holds {weights.method} weights, not {method}; use {instead} "
                                       f"(or --method auto, which takes the method from the file)")
    input_mean = weights.metadata.get("input_mean")
    return {"normalization": weights.metadata["normalization"], "train_images": weights.metadata["train_images"],
            "architecture": dict(weights.metadata["architecture"]), "input_mean": input_mean,
            "input_clip": None if input_mean is None else _training_clip(weights.metadata)}


def _training_clip(meta: dict) -> float | None:
    """The sensor level the training stream clipped each exposure-scaled sample at (the recipe's
    ``data.clip``, the stream's default 1.0); None: the recipe did not clip, or drew random light
    intensities (the network then saw each image divided by its intensity after the clip, so no
    single level bounds its inputs)."""
    recipe = meta.get("recipe")
    data = recipe.get("data") if isinstance(recipe, dict) else None
    if not isinstance(data, dict):
        return 1.0
    if data.get("intensities", "unit") != "unit":
        return None
    clip = data.get("clip", 1.0)
    return float(clip) if isinstance(clip, (int, float)) and not isinstance(clip, bool) else None


def method_of(path: str | os.PathLike) -> tuple[str, str | None]:
    """The method a weights file is for, and a note when that is a guess (the authors' files)."""
    w = read_weights(path)
    if not w.official or w.kind == "lcnet":
        return w.method, None
    if not w.lights:  # --method ps-fcn-n takes lights: no advice that cannot work for a 3-channel file
        return "ups-fcn", (f"{Path(path).name}: the authors' checkpoints do not record +N; running it as ups-fcn, "
                           f"without +N")
    return "ps-fcn", (f"{Path(path).name}: the authors' checkpoints do not record +N; running it as ps-fcn "
                      f"(pass --method ps-fcn-n for a +N checkpoint such as PS-FCN_B_S_32_normalize.pth.tar)")


def check_state_dict(path: Path | None, state_dict: dict, model: "torch.nn.Module", name: str = "PS-FCN") -> None:
    """Strict key and shape check; the error names the file and the first offending keys."""
    want = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    have = {k: tuple(v.shape) for k, v in state_dict.items()}
    missing = [k for k in want if k not in have]
    unexpected = [k for k in have if k not in want]
    shapes = [f"{k} {list(have[k])} (expected {list(want[k])})" for k in want if k in have and have[k] != want[k]]
    problems = []
    for what, items in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", shapes)):
        if items:
            more = f" and {len(items) - _SHOW} more" if len(items) > _SHOW else ""
            problems.append(f"{what}: {', '.join(items[:_SHOW])}{more}")
    if problems:
        raise PsctlError(path, f"does not match the {name} architecture: " + "; ".join(problems))


def build_network(weights: Weights, method: str,
                  device: "str | torch.device" = "cpu") -> tuple["PSFCN | LCNet", dict]:
    """The network with ``weights`` loaded (eval mode), and how to run it (see ``for_method``).

    The layers are made on the meta device (shapes, no values), then given fresh memory holding
    the file's values: building them on the CPU drew throwaway initial weights from torch's global
    generator, which shifted a caller's seeded stream (and saving and restoring it instead would
    replay numbers to the caller's other threads). Copied into fresh memory, not assigned: the
    file's own tensors gave LCNet outputs 1e-5 apart (the same values, other allocations)."""
    run = for_method(weights, method)
    model, name = _network(weights, method, run)
    check_state_dict(weights.path, weights.state_dict, model, name)
    import torch

    # fresh CPU memory per tensor (not Module.to_empty: its empty_like of meta tensors imports torch's
    # meta registrations and sympy, 0.9 s of every run); copy_ casts an LCNet stored in float16
    with torch.no_grad():
        fresh = {k: torch.empty(t.shape, dtype=t.dtype).copy_(weights.state_dict[k])
                 for k, t in model.state_dict().items()}
    model.load_state_dict(fresh, strict=True, assign=True)
    return model.to(device).eval(), run


def _network(weights: Weights, method: str, run: dict) -> tuple["PSFCN | LCNet", str]:
    """The network ``method``'s weights ``run`` describe (their architecture), on the meta device
    (shapes, no values; its module imported first, so no module-level tensor is made there)."""
    import torch

    if WEIGHTS_METHODS[method]["architecture"] == "lcnet":
        from psctl.models.lcnet import DEFAULT_CONFIG, LCNet

        try:
            with torch.device("meta"):
                return LCNet({k: v for k, v in run["architecture"].items() if k in DEFAULT_CONFIG}), "LCNet"
        except (ValueError, TypeError) as e:
            raise PsctlError(weights.path, f"bad LCNet architecture in the metadata ({e})") from None
    from psctl.models.ps_fcn import PSFCN

    with torch.device("meta"):
        return PSFCN({k: v for k, v in run["architecture"].items() if k in ("lights", "fuse", "slope")}), "PS-FCN"


def load_network(method: str, weights_file: str | os.PathLike | None = None,
                 device: "str | torch.device" = "cpu") -> tuple["PSFCN | LCNet", dict, Weights]:
    """Find (or read ``weights_file``), check and load the network for ``method``."""
    if weights_file is None:
        path = installed_path(method)
        if path is None:
            raise no_weights_error(method)
    else:
        path = Path(check_path("weights", weights_file))
    weights = read_weights(path)
    model, run = build_network(weights, method, device)
    return model, run, weights


# --- write ------------------------------------------------------------------------------------

def _plain(value: Any, where: str) -> Any:
    """Check that metadata holds only plain data (what weights_only loading accepts)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise PsctlError(None, f"metadata key {where}.{k!r} is not a string")
            out[k] = _plain(v, f"{where}.{k}")
        return out
    raise PsctlError(None, f"metadata {where} is a {type(value).__name__}; only plain data "
                           f"(str, int, float, bool, None, list, dict) can be stored")


def save_weights(path: str | os.PathLike, model: "torch.nn.Module | dict", metadata: dict) -> Path:
    """Write psctl weights atomically.

    Args:
        path: the file to write (``weights/<method>.pt`` to install).
        model: a PSFCN or LCNet (its config becomes ``architecture``) or a state dict.
        metadata: at least ``method`` and ``train_images`` (q); ``normalization`` defaults to
            the method's; put the training ``recipe``, ``data`` and ``metrics`` here too. ``date``
            (UTC, ISO 8601) is added when absent.
    """
    import torch

    from psctl.io.atomic import atomic_path

    path = Path(path)
    meta = _plain(dict(metadata), "metadata")
    method = meta.get("method")
    if method not in WEIGHTS_METHODS:
        raise PsctlError(None, f"metadata 'method' must be one of {', '.join(WEIGHTS_METHODS)}, got {method!r}")
    if isinstance(model, torch.nn.Module):
        state = model.state_dict()
        meta.setdefault("architecture", _plain(dict(getattr(model, "config", {})), "architecture"))
    else:
        state = model
    check_finite(state, path)
    if method in NETWORK_METHODS:
        meta.setdefault("architecture", {"lights": NETWORK_METHODS[method]["lights"], "fuse": "max"})
    else:
        from psctl.models.lcnet import DEFAULT_CONFIG

        meta.setdefault("architecture", _plain(dict(DEFAULT_CONFIG), "architecture"))
    meta.setdefault("normalization", WEIGHTS_METHODS[method]["normalization"])
    meta.setdefault("date", datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
    for key, default in (("recipe", {}), ("data", None), ("metrics", {})):
        meta.setdefault(key, default)
    _check_metadata(meta, None)
    # clone: a view would drag its whole storage into the file
    tensors = {k: v.detach().to("cpu").contiguous().clone() for k, v in state.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        save_torch({"format": FORMAT, "version": VERSION, "state_dict": tensors, "metadata": meta}, tmp)
    return path


def save_torch(obj: Any, tmp: str | os.PathLike) -> None:
    """``torch.save`` by way of memory: on a full disk torch's own file writer fails with a
    RuntimeError naming nothing ("unexpected pos"); a plain write raises the OSError that
    psctl.io.atomic.atomic_path turns into one line naming the file."""
    import io

    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    Path(tmp).write_bytes(buf.getbuffer())

"""Write synthetic objects as DiLiGenT-style capture folders (what ``psctl synth`` does).

Each object folder holds 001.png ... (16-bit RGB), filenames.txt, light_directions.txt,
light_intensities.txt, mask.png, Normal_gt.mat (key Normal_gt), Normal_gt.png and synth.json
(how it was made). OUT/objects.txt lists the objects, so OUT is a benchmark root:

    psctl synth out/syntest --preset syntest --materials 4
    psctl eval --benchmark folder --root out/syntest --method l2

Presets
    syntest        sphere, bunny, dragon, armadillo x K MERL materials, 100 upper-hemisphere
                   lights (the paper's SynTest; K = 100 is the full set)
    dragon-svbrdf  dragon x {ramp, checker, irregular} blends of two MERL materials, K pairs
    blobby         K procedural blobby shapes with training-distribution materials
Images come from the same renderer as the training stream, with exact cast shadows (depth-map
marching per light) and, with ``interreflections``, exact diffuse bounces. The whole set is
built in a hidden temporary folder and moved into place at the end (objects.txt last), so an
interrupted run leaves the earlier set as it was. This is the only synth module that reads or
writes image files (OpenImageIO is imported lazily, the training stream never needs it).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from psctl.errors import ProgressFactory, PsctlError, few
from psctl.synth import DEFAULT_K, check_preset, physical_memory
from psctl.synth import lights as L
from psctl.synth import materials as M
from psctl.synth import render as R
from psctl.synth.shapes import GBuffer, blobby_gbuffers, sphere_gbuffer
from psctl.synth.stream import MAX_SEED

# Canonical test views: rotation about the vertical axis (degrees) of each test mesh.
TEST_VIEWS = {"bunny": 0.0, "dragon": 45.0, "armadillo": 180.0}
EXPOSURE_QUANTILE = 0.995  # this quantile of an object's pixel values is written as ...
EXPOSURE_LEVEL = 0.9  # ... this 16-bit level (brighter highlights saturate, as in a camera)
MAX_BOUNCES = 100  # --interreflections: more only costs time (linear in the count)


@dataclass
class SynthObject:
    """One object to write: a view, its material(s) and its lights."""

    name: str
    view: GBuffer  # one view
    mat: M.Material  # one material
    lights: torch.Tensor  # [N, 3]
    intensities: torch.Tensor  # [N]
    mat_b: M.Material | None = None
    weights: torch.Tensor | None = None  # [1, 1, H, W]
    texture: torch.Tensor | None = None  # [1, 3, H, W]
    meta: dict = field(default_factory=dict)


def _roty(deg: float) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def canonical_view(name: str, size: int) -> GBuffer:
    """The canonical view of a test shape (sphere, bunny, dragon, armadillo)."""
    if name == "sphere":
        return sphere_gbuffer(size)
    from psctl.synth import meshes

    v, f = meshes.load_obj(meshes.find_mesh(name))
    return meshes.mesh_views(v, f, _roty(TEST_VIEWS[name])[None], size, name=name)


def _merl_subset(table: M.MerlTable, k: int, gen: torch.Generator) -> list[int]:
    if not 1 <= k <= len(table.names):
        raise PsctlError(None, f"--materials must be in 1..{len(table.names)} (got {k})")
    return sorted(torch.randperm(len(table.names), generator=gen)[:k].tolist())


def render_bytes(size: int, n_lights: int) -> float:
    """Peak memory of psctl synth for one object, roughly: measured 0.62 GB at 256 px and 1.48 GB
    at 512 px with 100 lights (blobby, peak RSS, 2026-11-27), i.e. about 44 bytes per pixel and
    light over 0.4 GB."""
    return 0.4e9 + 44.0 * n_lights * size * size


def _lower(*names: str) -> tuple:
    """Names in lower case, as the command line takes them (DILIGENT is diligent); others as given."""
    return tuple(n.lower() if isinstance(n, str) else n for n in names)


def preset_objects(preset: str, seed: int = 0, size: int = 128, n_lights: int = 100,
                   k: int | None = None, light_dist: str = "hemisphere", intensities: str = "unit") -> list[SynthObject]:
    """The objects of a preset (geometry, materials, lights), not yet rendered.

    ``light_dist`` names the zenith band the lights are drawn from (psctl.synth.lights:
    hemisphere, diligent, poles, equator); the presets use the hemisphere, as the paper.
    ``intensities`` (psctl.synth.lights: unit, random, directional, mixed): the lights'
    intensities, drawn per object (each object its own rig), for uncalibrated methods; unit
    keeps the presets as they were.
    """
    preset, light_dist, intensities = _lower(preset, light_dist, intensities)
    check_preset(preset)
    L.zenith_band(light_dist)  # validates the name before any work
    L.check_intensities(intensities, "--intensities")
    if size < 8 or n_lights < 3:
        raise PsctlError(None, f"need --size >= 8 and --lights >= 3 (got {size}, {n_lights})")
    if not 0 <= seed <= MAX_SEED:  # seed + 1 and seed + 2 seed generators too; torch takes 64 bits
        raise PsctlError(None, f"--seed must be from 0 to 2^62 (got {seed})")
    need = render_bytes(size, n_lights)
    total = physical_memory()
    if need > 0.8 * total:  # before minutes of work, and an out-of-memory kill or traceback
        raise PsctlError(None, f"--size {size} with {n_lights} lights needs about {need / 2**30:.0f} GiB of memory "
                               f"to render one object; this machine has {total / 2**30:.0f} GiB")
    k = DEFAULT_K[preset] if k is None else k
    if k < 1:
        raise PsctlError(None, f"--materials must be at least 1 (got {k})")
    # every object's geometry is made before the first is rendered: blobby's G-buffers (17 bytes a
    # pixel, copied once per object while they are split: ~40 at the peak; blends and textures
    # add ~5), dragon-svbrdf's blend weights (three per K, 4 bytes a pixel: 13 measured)
    held = k * size * size * {"blobby": 40.0, "dragon-svbrdf": 13.0}.get(preset, 0.0)
    if held + need > 0.8 * total:  # -k 100000000: an out-of-memory kill after hours, not a line
        raise PsctlError(None, f"--materials {k} at --size {size} needs about {(held + need) / 2**30:,.0f} GiB of "
                               f"memory (each object's geometry is held until it is written); this machine has "
                               f"{total / 2**30:.0f} GiB: render fewer objects per folder")
    gen = torch.Generator().manual_seed(seed)
    lights = L.sample_lights((n_lights,), gen, light_dist)
    ones = torch.ones(n_lights)
    objs: list[SynthObject] = []
    if preset == "syntest":
        table = M.load_merl()
        rows = _merl_subset(table, k, gen)
        for shape in ("sphere", "bunny", "dragon", "armadillo"):
            view = canonical_view(shape, size)
            for r in rows:
                name = f"{shape}_{table.names[r]}"
                objs.append(SynthObject(name, view, M.merl_materials(table, [r]), lights, ones,
                                        meta={"shape": shape, "material": table.names[r]}))
    elif preset == "dragon-svbrdf":
        table = M.load_merl()
        view = canonical_view("dragon", size)
        for i in range(k):
            pair = torch.randperm(len(table.names), generator=gen)[:2].tolist()
            for kind in M.BLENDS:
                w = M.blend_weights([kind], size, size, gen)
                name = f"dragon_{kind}_{i + 1:02d}"
                objs.append(SynthObject(name, view, M.merl_materials(table, pair[:1]), lights, ones,
                                        M.merl_materials(table, pair[1:]), w,
                                        meta={"shape": "dragon", "blend": kind,
                                              "materials": [table.names[j] for j in pair]}))
    else:  # blobby
        table = M.load_merl()
        views = blobby_gbuffers(k, size, gen)
        for i in range(k):
            mat = M.sample_materials(1, gen, table)
            meta = {"shape": "blobby", "material": _describe(mat, table)}
            mat_b = w = tex = None
            if float(torch.rand(1, generator=gen)) < 0.25:
                kind = M.BLENDS[int(torch.randint(3, (1,), generator=gen))]
                mat_b, w = M.sample_materials(1, gen, table), M.blend_weights([kind], size, size, gen)
                meta.update(blend=kind, material_b=_describe(mat_b, table))
            if float(torch.rand(1, generator=gen)) < 0.3:
                tex = M.albedo_texture(1, size, size, gen)
                meta["texture"] = True
            objs.append(SynthObject(f"blobby_{i + 1:02d}", views.take([i]), mat, lights, ones, mat_b, w, tex, meta))
    # a generator of their own: the unit presets' draws stay as they were (seed + 2 is also the
    # lights' generator of the preset with seed + 2; sets of neighbouring seeds share draws)
    gen_e = None if intensities == "unit" else torch.Generator().manual_seed(seed + 2)
    for o in objs:
        o.meta.update(preset=preset, seed=seed, size=size, n_lights=n_lights, light_dist=light_dist)
        if gen_e is not None:
            o.intensities = L.sample_intensities((1, n_lights), gen_e, intensities, lights=lights[None])[0]
            o.meta["intensities"] = intensities
    return objs


def _describe(mat: M.Material, table: M.MerlTable) -> str:
    if bool(mat["abc"][0]):
        match = (table.a == mat["c1"][0]).all(1) & (table.b == mat["b"][0])
        return f"merl:{table.names[int(match.nonzero()[0, 0])]}" if match.any() else "merl"
    if bool(mat["metal"][0]):
        return f"ggx-metal alpha={float(mat['alpha'][0]):.3f}"
    if float(mat["c1"][0].abs().sum()) == 0:
        return "lambertian"
    return f"ggx-dielectric alpha={float(mat['alpha'][0]):.3f} ior={float(mat['ior'][0]):.2f}"


def diffuse_albedo(obj: SynthObject) -> torch.Tensor:
    """kd per pixel, [3, H*W] (texture and blend applied, 0 off the object)."""
    g = obj.view
    h, w = g.size
    kd = obj.mat["kd"][0][:, None].expand(3, h * w)
    if obj.mat_b is not None:
        wt = obj.weights.reshape(1, h * w)
        kd = wt * kd + (1 - wt) * obj.mat_b["kd"][0][:, None]
    if obj.texture is not None:
        kd = kd * obj.texture.reshape(3, h * w)
    return kd * g.mask.reshape(1, h * w)


def render_object(obj: SynthObject, visibility: torch.Tensor | None = None, shadows: bool = True,
                  chunk: int = 16, bounces: int = 0, kernel: torch.Tensor | None = None,
                  ir_albedo: float | None = None, light_distance: float | None = None) -> torch.Tensor:
    """e * radiance, [N, 3, H, W] (not yet exposed or quantised).

    ``visibility`` [1, N, H*W] may be passed in when several objects share a view and lights;
    otherwise it is computed here (with ``shadows``) by marching the depth map. ``bounces`` > 0
    adds that many diffuse interreflection bounces (``R.interreflection_kernel``; ``kernel``
    may be passed in as visibility). ``ir_albedo`` a: the surface lights itself as a source of
    albedo a * kd / max(kd) (the training stream's ``interreflection`` option) instead of kd;
    the camera still sees the indirect light reflected by kd. ``light_distance`` (pixels): point
    lights that far from the object's centre along its light directions (``R.near_light_field``:
    per-pixel directions and falloff; cast shadows still follow the listed directions).
    """
    g = obj.view
    h, w = g.size
    if light_distance is not None and bounces > 0:
        raise PsctlError(None, "near lights and interreflections together are not supported")
    field_dirs = field_fall = None
    if light_distance is not None:
        field_dirs, field_fall = R.near_light_field(obj.lights, light_distance, g.mask[0, 0])
    if visibility is None and shadows:
        visibility = R.march_shadows(g.depth, obj.lights[None]).reshape(1, -1, h * w)
    n = g.normals.reshape(1, 3, h * w)
    tex = None if obj.texture is None else obj.texture.reshape(1, 3, h * w)
    if bounces > 0:
        kernel = kernel if kernel is not None else R.interreflection_kernel(g.depth, g.normals)
        kd = diffuse_albedo(obj)
        src = kd if ir_albedo is None else ir_albedo * kd / kd.amax(0, keepdim=True).clamp_min(1e-6)
    out = []
    for s in range(0, len(obj.lights), chunk):
        lc, ec = obj.lights[None, s:s + chunk], obj.intensities[None, s:s + chunk]
        vc = None if visibility is None else visibility[:, s:s + chunk]
        fc = None
        if field_dirs is not None:
            lc, fc = field_dirs[None, s:s + chunk], field_fall[None, s:s + chunk]
        img = R.shade(n, lc, obj.mat, vc, ec, tex, falloff=fc)
        if obj.mat_b is not None:
            wt = obj.weights.reshape(1, 1, 1, h * w)
            img = wt * img + (1 - wt) * R.shade(n, lc, obj.mat_b, vc, ec, tex, falloff=fc)
        img = img[0]
        if bounces > 0:  # the first bounce's source: the lights' diffuse reflection kd / pi * e * cos * vis
            cos = torch.einsum("cp,nc->np", n[0], lc[0]).clamp_min(0.0) * (n[0, 2] > 0) * ec[0][:, None]
            if vc is not None:
                cos = cos * vc[0]
            img = img + R.diffuse_bounces(kernel, src[None] / math.pi * cos[:, None], src, bounces, receiver=kd)
        out.append(img.reshape(-1, 3, h, w))
    return torch.cat(out)


def exposure_scale(images: torch.Tensor, mask: torch.Tensor, gen: torch.Generator | None = None) -> float:
    """The factor that maps the EXPOSURE_QUANTILE of the object's pixel values to EXPOSURE_LEVEL."""
    vals = images.permute(1, 0, 2, 3)[:, :, mask].reshape(-1)
    if vals.numel() > 4_000_000:  # torch.quantile has a size limit: a seeded subsample
        gen = gen or torch.Generator().manual_seed(0)
        vals = vals[torch.randint(vals.numel(), (4_000_000,), generator=gen)]
    q = float(torch.quantile(vals, EXPOSURE_QUANTILE)) if vals.numel() else 0.0
    return EXPOSURE_LEVEL / q if q > 0 else 1.0


def write_object(folder: Path, obj: SynthObject, images: torch.Tensor) -> None:
    """Write one capture folder (images already exposed, values in [0, 1])."""
    import io

    import scipy.io

    from psctl.io.atomic import write_bytes_atomic, write_text_atomic
    from psctl.io.images import write_image
    from psctl.io.normals import write_normal_map

    g = obj.view
    mask = g.mask[0, 0].numpy()
    normals = g.normals[0].permute(1, 2, 0).numpy().astype(np.float32)
    n = images.shape[0]
    width = max(3, len(str(n)))
    names = [f"{i + 1:0{width}d}.png" for i in range(n)]
    arr = images.permute(0, 2, 3, 1).numpy()
    for name, img in zip(names, arr):
        write_image(folder / name, img, "uint16", kind="linear")
    write_text_atomic(folder / "filenames.txt", "".join(f"{x}\n" for x in names))
    write_text_atomic(folder / "light_directions.txt",
                      "".join(f"{a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in obj.lights.tolist()))
    write_text_atomic(folder / "light_intensities.txt",
                      "".join(f"{e:.6f} {e:.6f} {e:.6f}\n" for e in obj.intensities.tolist()))
    write_image(folder / "mask.png", mask.astype(np.float32), "uint8", kind="data")
    mat = io.BytesIO()
    scipy.io.savemat(mat, {"Normal_gt": np.where(mask[..., None], normals, 0.0).astype(np.float64)})
    # the header's 116 bytes of text carry the time of writing: without it the same seed gives
    # the same bytes (a dataset's checksums match between runs; readers skip this text)
    data = bytearray(mat.getvalue())
    data[:116] = b"MATLAB 5.0 MAT-file, written by psctl synth".ljust(116, b" ")
    write_bytes_atomic(folder / "Normal_gt.mat", bytes(data))  # a full disk: one error naming the file
    write_normal_map(folder / "Normal_gt.png", normals, mask, "png16")
    write_text_atomic(folder / "synth.json", json.dumps(obj.meta, indent=2) + "\n")


def _check_synth_root(out: Path) -> None:
    """``out`` must be new, empty, or a folder psctl synth wrote before (objects.txt, preview.png
    and object folders holding synth.json): it never writes into a capture or someone's data."""
    if not out.is_dir():
        return
    for entry in sorted(out.iterdir()):
        if entry.name.startswith(".") or entry.name in ("objects.txt", "preview.png"):
            continue
        if entry.is_dir() and (entry / "synth.json").is_file():
            if not entry.is_symlink():  # a link is only unlinked, never emptied: what it holds is safe
                _check_synth_object(entry)
            continue
        raise PsctlError(out, f"is not empty and not a psctl synth folder ({entry.name} is there, which psctl synth "
                              "did not write); choose a new or empty folder, or move it away")


OBJECT_FILES = ("filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png", "Normal_gt.mat",
                "Normal_gt.png", "synth.json")  # write_object's, beside the images filenames.txt lists


def _check_synth_object(folder: Path) -> None:
    """A rerun replaces (or removes) an earlier object folder whole: refuse when it holds what
    psctl synth did not write there (psctl normals' default output folder, psctl/, say)."""
    try:
        listed = set((folder / "filenames.txt").read_text(encoding="utf-8").split())
    except (OSError, UnicodeDecodeError):
        listed = set()
    other = sorted(e.name + ("/" if e.is_dir() else "") for e in folder.iterdir()
                   if not e.name.startswith(".") and e.name not in OBJECT_FILES and e.name not in listed)
    if other:
        shown = few(other)
        raise PsctlError(folder, f"holds {shown}, which psctl synth did not write; a new set here would delete "
                                 "it with the earlier object: move it away, or choose a new or empty folder")


class _RollbackFailed(PsctlError):
    """A failed swap that could not put the earlier set back: its files are left in the backup
    folder this names, which the caller must not delete."""


def _swap_in(stage: Path, out: Path, names: list[str], listing: str) -> None:
    """Move the staged ``names`` into ``out``, objects.txt (``listing``) last. What they replace
    goes to a backup inside ``stage`` first; should a move fail (disk full, Ctrl-C), everything
    is put back as it was, so ``out`` holds the earlier set or the new one, never a mix."""
    from psctl.io.atomic import write_text_atomic

    for name in names:  # before anything moves
        if (out / name).exists() and (out / name).is_dir() != (stage / name).is_dir():
            raise PsctlError(out / name, "exists and is not a " + ("folder" if (stage / name).is_dir() else "file"))
    backup = stage / ".earlier"
    backup.mkdir()
    old: list[str] = []
    new: list[str] = []
    try:
        for name in ["objects.txt", *names]:
            if (out / name).exists() or (out / name).is_symlink():
                os.replace(out / name, backup / name)
                old.append(name)
            if name != "objects.txt":
                os.replace(stage / name, out / name)
                new.append(name)
        write_text_atomic(out / "objects.txt", listing)
    except BaseException as e:
        try:
            for name in reversed(new):
                os.replace(out / name, stage / name)
                new.remove(name)
            for name in reversed(old):
                os.replace(backup / name, out / name)
                old.remove(name)
        except BaseException as again:  # (an antivirus holding a file on Windows, a full disk): keep them
            raise _RollbackFailed(backup, f"moving the new set in failed ({type(e).__name__}: {e}), and so did putting "
                                          f"the earlier one back ({type(again).__name__}: {again}): its files "
                                          f"{', '.join(old) or '(none)'} are kept here; move them back into {out}"
                                  ) from None
        raise


def _remove_stale(out: Path, names: set[str], preview: bool) -> list[str]:
    """What an earlier run into ``out`` wrote and this one did not (every object folder there is
    psctl synth's: _check_synth_root), removed so that the folder holds this set alone."""
    removed = sorted(p.name for p in out.iterdir() if p.is_dir() and not p.is_symlink() and not p.name.startswith(".")
                     and p.name not in names and (p / "synth.json").is_file())  # a link: someone else's folder
    if not preview and (out / "preview.png").is_file():
        removed.append("preview.png")
    for name in removed:
        (shutil.rmtree if (out / name).is_dir() else os.remove)(out / name)
    return removed


def write_preset(out: str | os.PathLike, preset: str, seed: int = 0, size: int = 128, n_lights: int = 100,
                 k: int | None = None, preview: bool = False, shadows: bool = True,
                 light_dist: str = "hemisphere", intensities: str = "unit",
                 interreflections: int = 0, ir_albedo: float | None = None, light_distance: float | None = None,
                 progress: "ProgressFactory | None" = None) -> dict:
    """Render a preset into ``out`` (a benchmark root: one capture folder per object + objects.txt).

    Args:
        preset: syntest | dragon-svbrdf | blobby.
        k: materials per shape (syntest), material pairs (dragon-svbrdf) or shapes (blobby).
        preview: also write out/preview.png, a contact sheet of a few images per object.
        light_dist: zenith band of the lights (hemisphere | diligent | poles | equator).
        intensities: unit | random | directional | mixed (psctl.synth.lights), per object.
        interreflections: diffuse bounces to add (0: none).
        ir_albedo: with interreflections, the albedo of the surface as a source of indirect
            light, a * kd / max(kd) (None: kd itself; see ``render_object``).
        light_distance: point lights this many pixels from each object's centre along its
            light directions (``render_object``; psctl normals --light-distance undoes the falloff).
    Returns:
        {"out", "preset", "seed", "size", "n_lights", "light_dist", "intensities", "interreflections",
        "ir_albedo", "light_distance", "objects", "preview", "seconds", "removed", "notes"} (removed: what an
        earlier psctl synth run left in ``out`` that this set does not have; same-named object
        folders are replaced and not listed).
    """
    from psctl.io.atomic import (by_final_name, check_output_dir, current_umask, ensure_writable_dir, missing_folders,
                                 folder_locks, remove_empty, signals_deferred, working_folder)

    t0 = time.perf_counter()
    preset, light_dist, intensities = _lower(preset, light_dist, intensities)
    out = Path(out)
    check_output_dir(out)
    _check_synth_root(out)
    if not 0 <= interreflections <= MAX_BOUNCES:  # (an audit: 10^8 ran for hours, no word said)
        raise PsctlError(None, f"--interreflections must be 0 to {MAX_BOUNCES} (got {interreflections}): each bounce "
                               f"is weaker than the last by the albedo and the view factor, so a few add what is seen")
    if ir_albedo is not None and not 0 <= ir_albedo < 1:
        raise PsctlError(None, f"--ir-albedo must be in [0, 1) (got {ir_albedo})")
    if ir_albedo is not None and not interreflections:  # it would be ignored without a word
        raise PsctlError(None, "--ir-albedo is the albedo of the interreflections: give --interreflections N too")
    if light_distance is not None:
        if not math.isfinite(light_distance) or light_distance <= 2 * size:
            raise PsctlError(None, f"--light-distance must be over twice the image size, {2 * size} pixels "
                                   f"(got {light_distance})")
        if interreflections:
            raise PsctlError(None, "--light-distance and --interreflections together are not supported")
    objs = preset_objects(preset, seed, size, n_lights, k, light_dist, intensities)
    created = missing_folders(out)  # removed again (when empty) if the run fails or is stopped
    ensure_writable_dir(out)
    advance = progress(f"synth {preset}", len(objs)) if progress else (lambda _: None)
    gen = torch.Generator().manual_seed(seed + 1)
    sheet_rows = []
    on_sheet = set(np.linspace(0, len(objs) - 1, min(len(objs), SHEET_ROWS)).round().astype(int).tolist())
    folder_mode = 0o777 & ~current_umask()  # a folder's mode as mkdir would give
    cache: dict[int, torch.Tensor] = {}  # visibility is shared by objects with the same view
    kernels: dict[int, torch.Tensor] = {}  # and so are the interreflection form factors
    # The whole set is written into one hidden folder and moved into place at the end: an
    # interrupted run leaves the earlier set as it was (a hidden folder at worst: a kill -9),
    # never some new objects beside old ones or a set that looks complete and is not.
    stage = working_folder(out, ".psctl-synth.")
    keep = False
    try:
        for i, obj in enumerate(objs):
            key = id(obj.view)
            if shadows and key not in cache:
                h, w = obj.view.size
                cache = {key: R.march_shadows(obj.view.depth, obj.lights[None]).reshape(1, -1, h * w)}
            if interreflections and key not in kernels:
                kernels = {key: R.interreflection_kernel(obj.view.depth, obj.view.normals)}
            images = render_object(obj, cache.get(key), shadows, bounces=interreflections, kernel=kernels.get(key),
                                   ir_albedo=ir_albedo, light_distance=light_distance)
            scale = exposure_scale(images, obj.view.mask[0, 0], gen)
            images = images * scale
            images = R.quantize(images, 16) * obj.view.mask[0]
            obj.meta["exposure"] = scale
            if light_distance is not None:
                obj.meta["light_distance"] = light_distance
            if interreflections:
                obj.meta["interreflections"] = interreflections
                if ir_albedo is not None:
                    obj.meta["ir_albedo"] = ir_albedo
            (stage / obj.name).mkdir(mode=folder_mode)
            write_object(stage / obj.name, obj, images)
            if preview and i in on_sheet:
                sheet_rows.append(_sheet_row(images, obj))
            advance(1)
        preview_path = None
        if preview:
            from psctl.io.images import write_image

            write_image(stage / "preview.png", _sheet(sheet_rows), "uint8")
            preview_path = out / "preview.png"
        # under the folder's lock and with signals held, as staged_outputs moves a run's outputs
        # (helper-177: two runs into one folder swapped each other's objects out and one lost half
        # its set; a SIGTERM in the clean-up left the earlier set's files in a hidden folder)
        with folder_locks([out]), signals_deferred():
            try:
                _swap_in(stage, out, [o.name for o in objs] + (["preview.png"] if preview else []),
                         "".join(f"{o.name}\n" for o in objs))
            except _RollbackFailed:
                keep = True  # the earlier set's files are in the stage's backup: never deleted
                raise
            created = []  # the set is in place: the folders are its
            shutil.rmtree(stage, ignore_errors=True)
            removed = _remove_stale(out, {o.name for o in objs}, preview)
    except _RollbackFailed:
        raise  # it names the kept backup in the stage, which is where the files are
    except PsctlError as e:  # a write that failed (a full disk): named in the set, not in the stage
        renamed = by_final_name(e, [(stage, out)])
        if renamed is e:
            raise
        raise renamed from None
    finally:
        if not keep:
            shutil.rmtree(stage, ignore_errors=True)
            remove_empty(created)
    notes = []
    if stage.exists():  # an earlier object's file that could not be deleted (read-only, immutable)
        notes.append(f"outputs: {stage} could not be removed (it holds the earlier set's files that could not be "
                     "deleted): the new set is in place; remove that folder by hand")
    return {"out": os.path.abspath(out), "preset": preset, "seed": seed, "size": size, "n_lights": n_lights, "light_dist": light_dist,
            "intensities": intensities, "interreflections": interreflections, "ir_albedo": ir_albedo,
            "light_distance": light_distance, "objects": [o.name for o in objs],
            "preview": None if preview_path is None else os.path.abspath(preview_path),
            "seconds": round(time.perf_counter() - t0, 3), "removed": removed, "notes": notes}


# --------------------------------------------------------------------------------------------
# Contact sheet
# --------------------------------------------------------------------------------------------

SHEET_IMAGES = 6  # images per object on the contact sheet
SHEET_ROWS = 24  # objects on the contact sheet at most (evenly spread over the set)
SHEET_TEXT = 2  # text scale: 14 px letters, legible at 100 % (at 1, 7 px: a QA helper's finding)
SHEET_TILE = 128  # pixels: tiles of larger renders are shown every k-th pixel, so the sheet stays viewable


def _sheet_row(images: torch.Tensor, obj: SynthObject) -> np.ndarray:
    """One row: the object's name, then SHEET_IMAGES images (lights spread from left to right)
    and its normal map, each at most SHEET_TILE px."""
    from psctl.io.report import _stamp, text_bitmap

    lx = obj.lights[:, 0]
    picks = torch.argsort(lx)[torch.linspace(0, len(lx) - 1, SHEET_IMAGES).round().long()]
    k = -(-max(images.shape[-2:]) // SHEET_TILE)  # a preview: every k-th pixel is enough
    tiles = []
    for i in picks.tolist():
        tiles.append(images[i, :, ::k, ::k].permute(1, 2, 0).clamp(0, 1).numpy() ** (1 / 2.2))  # display gamma
    g = obj.view
    tiles.append(((g.normals[0, :, ::k, ::k].permute(1, 2, 0).numpy() + 1) / 2) * g.mask[0, 0, ::k, ::k].numpy()[..., None])
    gap = np.full((tiles[0].shape[0], 2, 3), 0.25, np.float32)
    row = []
    for t in tiles:
        row += [t.astype(np.float32), gap]
    row = np.concatenate(row[:-1], 1)
    name = text_bitmap(obj.name, SHEET_TEXT)  # its name: rows are a sample of a large set
    if name.shape[1] + 4 > row.shape[1]:  # small tiles: the row grows to its name
        row = np.pad(row, ((0, 0), (0, name.shape[1] + 4 - row.shape[1]), (0, 0)), constant_values=0.12)
    label = np.full((11 * SHEET_TEXT + 2, row.shape[1], 3), 0.12, np.float32)  # room for tails (g, p, y)
    _stamp(label, name, 2, 2)
    return np.concatenate([label, row], 0)


def _sheet(rows: list[np.ndarray]) -> np.ndarray:
    """The rows under a header saying what the columns are."""
    from psctl.io.report import _stamp, text_bitmap

    text = text_bitmap(f"{SHEET_IMAGES} IMAGES, LIGHT LEFT TO RIGHT | NORMALS", SHEET_TEXT)
    width = max(text.shape[1] + 4, *(r.shape[1] for r in rows))  # rows grown to their names, or to the header
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=0.12) for r in rows]
    header = np.full((9 * SHEET_TEXT + 2, width, 3), 0.12, np.float32)
    _stamp(header, text, 2, 2)
    gap = np.full((2, width, 3), 0.25, np.float32)
    out = [header]
    for r in rows:
        out += [r, gap]
    return np.concatenate(out[:-1], 0)


def render_synth(report: dict) -> None:
    """The human-readable summary of ``write_preset``'s report (stdout)."""
    n = len(report["objects"])
    print(f"wrote {n} object{'s' if n != 1 else ''} to {report['out']} ({report['seconds']:.1f} s)")
    if report["preview"]:
        print(f"preview: {report['preview']}")
    if report.get("removed"):
        print(f"removed {', '.join(report['removed'])}, left by an earlier psctl synth run")
    for note in report.get("notes", []):
        print(f"note: {note}")

"""Training data made on the fly from a forward model, seeded per sample.

Volume ``index`` of data set ``seed`` is :func:`~cm2optics.synth.generate.synthesize_sample`'s
sample (emitters, per-lenslet images, noise, nine views at the chief rays: every random number
from ``(seed, index)``), so any worker or rank makes the same one. Its ``patches_per_volume``
patches are drawn from the same per-sample stream as the synth package's; each target is the
block of voxels imaged onto the patch at the focal plane, in the views' orientation
(:func:`~cm2optics.synth.views.volume_patch`), rasterised straight on that block (the emitters
moved to its centre) rather than on the whole grid — the same voxels, without making a
full-field volume per sample. The block's lateral pitch is the model's object-side pixel
(:func:`pixel_voxel_um`; the config's voxel within 2 %), so the targets stay aligned with the
views across the whole field. With ``register_views`` the views and demixed views are first
registered onto the model's geometry (:mod:`~cm2optics.recon.net.register`), as at inference.

Order: per epoch the volumes are shuffled and each volume's patches shuffled (generator
``(seed, epoch)``), and consecutive patches share a volume (one synthesis serves them). The global
batch at step s is items ``[s·B, (s+1)·B)``; DDP rank r of w takes the r-th contiguous B/w of it.
Epoch e uses volumes ``e·train_volumes + v`` (``fresh_volumes``) or ``v``; the curriculum sets
the density range per epoch. With a mixed source (``mix_forward_model``), round(mix_fraction ·
train_volumes) of an epoch's volume slots (drawn from ``(seed, epoch)``) are that source's volumes
(:meth:`~cm2optics.recon.net.config.NetConfig.mix_config`: its own model and recipe, data seed
``seed + MIX_SEED_OFFSET``, its own patches per volume). With ``interleave_volumes`` G > 1, consecutive batches cycle over
groups of G volumes instead (batch j of a group from its volume j mod G), so that G DataLoader
workers, which take the batches in turn, each render one volume of the group. Validation is a
fixed set from a separate seed.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.recon.net.config import ConfigError, NetConfig

__all__ = [
    "Item",
    "PatchDataset",
    "PatchSource",
    "epoch_items",
    "inference_model",
    "forward_imaging",
    "pixel_voxel_um",
    "sensor_window",
    "validation_items",
    "validation_volumes",
]

#: Offset between the training and validation data seeds.
VALIDATION_SEED_OFFSET = 7919
#: Offset between the training data seed and the mixed source's.
MIX_SEED_OFFSET = 1299709
STREAM_PATCHES = 2  # the synth package's per-sample patch stream


@dataclass(frozen=True)
class Item:
    """One training patch: data seed, volume index, patch number, density range (per mm²),
    source (0: the config's forward model, 1: the mixed source)."""

    seed: int
    volume: int
    patch: int
    density: tuple[float, float]
    source: int = 0


def _analytic_lsv(preset: str, binning: int, grid_key: tuple, fov_mm: float, depth_um: float):
    from cm2optics.design import load_preset
    from cm2optics.lsv.toy import AnalyticCM2, analytic_lsv_model

    design = load_preset(preset)
    probe = AnalyticCM2.from_design(design, binning=binning)
    # a focus narrower than a pixel cannot be sampled: σ₀ at least one (binned) pixel
    model = AnalyticCM2.from_design(design, binning=binning, sigma0_um=max(probe.sigma0_um, probe.pixel_um))
    half = max(fov_mm / 2.0 + 0.3, 0.6)
    n_lateral = max(3, int(np.ceil(2 * half / 1.2)) + 1)  # ≤ 1.2 mm between nodes
    xs = np.linspace(-half, half, n_lateral)
    zs = np.linspace(-depth_um / 2000.0 - 0.05, depth_um / 2000.0 + 0.05, 5)
    return analytic_lsv_model(model, xs, xs, zs, rank=8, axial_um=float(grid_key[1][0]))


def sensor_window(model: Any, view_px: int, margin_px: int = 8) -> Any:
    """The 3D-LSV ``model`` on the smallest sensor window that holds every view (its geometry
    moved with the window's corner), or ``model`` itself when the window is the whole sensor.

    The views cropped from the window are those of the full sensor (zeros beyond it either
    way), and the per-sample rendering (FFTs over the sensor) costs the window's area only."""
    from dataclasses import replace

    if not (hasattr(model, "geometry") and hasattr(model, "forward_sparse")):
        return model
    rays = np.asarray(model.geometry.focus(0.0, 0.0, 0.0), float).reshape(-1, 2)
    H, W = model.sensor_shape
    half = view_px // 2 + margin_px
    top = max(int(np.floor(rays[:, 0].min())) - half, 0)
    left = max(int(np.floor(rays[:, 1].min())) - half, 0)
    bottom = min(int(np.ceil(rays[:, 0].max())) + half + 1, H)
    right = min(int(np.ceil(rays[:, 1].max())) + half + 1, W)
    if (top, left, bottom, right) == (0, 0, H, W):
        return model
    g = model.geometry
    r0 = np.array(g.r0_poly, float, copy=True)
    r0[0] -= (top, left)
    geometry = type(g)(r0, g.A_poly, g.o_poly, g.rows, g.cols)
    provenance = dict(model.provenance, sensor_window=[top, left, bottom, right])
    return replace(model, geometry=geometry, sensor_shape=(bottom - top, right - left), provenance=provenance)


@functools.lru_cache(maxsize=4)
def _source(spec: str, grid_key: tuple, toy_px: int, fov_mm: float, depth_um: float):
    """The forward model ``spec`` names, on its whole sensor: ``toy:gaussian``,
    ``analytic:<preset>:<binning>`` or a model file (3D-LSV model or PSF stack)."""
    from cm2optics.synth.imaging import load_imaging

    grid = VolumeGrid(grid_key[0], grid_key[1])
    if spec == "toy:gaussian":
        from cm2optics.lsv.toy import gaussian_lsi_operator as gaussian_cm2

        return gaussian_cm2(grid, (toy_px, toy_px), defocus_px_per_um=0.006)
    if spec.startswith("analytic:"):
        parts = spec.split(":")
        try:
            preset, binning = parts[1], int(parts[2]) if len(parts) > 2 else 1
        except (IndexError, ValueError):
            raise ConfigError(
                f"forward_model = {spec!r}: write analytic:<preset>:<binning>, e.g. analytic:cm2-v2:8"
            ) from None
        return _analytic_lsv(preset, binning, grid_key, fov_mm, depth_um)
    return load_imaging(spec, grid).source


def _source_of(config: NetConfig):
    grid = config.synth.grid
    return _source(
        config.forward_model,
        (grid.shape, grid.voxel_um),
        config.toy_sensor_px,
        config.synth.fov_mm[1],
        config.synth.depth_um,
    )


def inference_model(config: NetConfig):
    """The forward model the weights of ``config`` were trained through, on its whole sensor (not
    the training window): what ``cm2 reconstruct --method net`` uses when no ``--model`` is given."""
    return _source_of(config)


def forward_imaging(config: NetConfig):
    """The :class:`~cm2optics.synth.imaging.Imaging` of ``config.forward_model`` on the config's
    grid (cached per process; a 3D-LSV model on its :func:`sensor_window`), checked: one view pixel must image one voxel at the focal plane
    (the network maps a view patch onto a volume patch of the same size)."""
    from cm2optics.synth.imaging import Imaging

    grid = config.synth.grid
    imaging = Imaging(sensor_window(_source_of(config), config.synth.view_px), grid)
    scale = imaging.pixels_per_voxel()
    if scale is None:
        raise ConfigError(f"forward_model = {config.forward_model!r}: its views are rotated against the volume grid")
    if np.any(np.abs(np.abs(scale) - 1.0) > 0.02):
        suggestion = tuple(round(v * abs(s), 4) for v, s in zip(grid.voxel_um[1:], scale, strict=True))
        raise ConfigError(
            f"synth.voxel_um = {grid.voxel_um}: one view pixel spans {np.abs(scale)} voxels at the focal plane; "
            f"CM²Net needs 1 — set the lateral voxel to the object-side pixel, (y, x) = {suggestion} µm"
        )
    return imaging


def pixel_voxel_um(config: NetConfig, scale: np.ndarray) -> tuple[float, float, float]:
    """The voxel the network actually predicts: (dz, and the object-side pixel along y and x), µm
    — the config's lateral voxel divided by the model's pixels per voxel (within 2 % of 1)."""
    dz, dy, dx = config.synth.grid.voxel_um
    return (dz, dy / abs(float(scale[0])), dx / abs(float(scale[1])))


def _block(config: NetConfig, origin: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, int]:
    """Object-space centre (y, x) µm of the block of voxels under a view patch, and its side
    (one voxel per view pixel, at the model's object-side pixel pitch)."""
    p, V = config.synth.patch_px, config.synth.view_px
    voxel = config.synth.grid.voxel_um[1:]
    centre = [
        (origin[axis] + (p - 1) / 2.0 - V // 2) / float(s) * d
        for axis, (s, d) in enumerate(zip(scale, voxel, strict=True))
    ]
    return np.array(centre), p


def patch_emitters(
    emitters: Emitters, centre_um: np.ndarray, scale: np.ndarray, margin_um: float = 0.0, half_um: float | None = None
) -> Emitters:
    """The emitters in a patch's frame: moved to its centre and flipped as the views are; with
    ``half_um``, only those whose centre lies within ±(half_um − margin_um) laterally."""
    y = (emitters.y_um - centre_um[0]) * np.sign(scale[0])
    x = (emitters.x_um - centre_um[1]) * np.sign(scale[1])
    keep = np.ones(len(x), bool)
    if half_um is not None:
        lim = half_um - margin_um
        keep = (np.abs(x) <= lim) & (np.abs(y) <= lim)
    return Emitters(x[keep], y[keep], emitters.z_um[keep], emitters.diameter_um[keep], emitters.intensity[keep])


class PatchSource:
    """Makes (and keeps the last few) volumes' patches: views, demixed views, volume targets."""

    def __init__(self, config: NetConfig, cache: int = 2):
        self.config = config
        self.imaging = forward_imaging(config)
        self.scale = np.asarray(self.imaging.pixels_per_voxel(), float)
        self.registration = None
        if config.register_views:
            from cm2optics.recon.net.register import registration_map

            self.registration = registration_map(self.imaging.source, config.synth.view_px)
        self._cache: OrderedDict[tuple, dict[str, Any]] = OrderedDict()
        self._size = cache

    def volume(self, seed: int, index: int, density: tuple[float, float]) -> dict[str, Any]:
        key = (seed, index, density)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        out = self._make(seed, index, density)
        self._cache[key] = out
        while len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return out

    def _make(self, seed: int, index: int, density: tuple[float, float]) -> dict[str, Any]:
        from cm2optics.synth.emitters import sample_rng
        from cm2optics.synth.generate import synthesize_sample
        from cm2optics.synth.raster import rasterize_balls
        from cm2optics.synth.views import patch_origins

        c = self.config
        synth = c.synth.with_changes(density_per_mm2=tuple(density), patches_per_volume=0)
        sample = synthesize_sample(synth, self.imaging, index, seed)
        p, V = synth.patch_px, synth.view_px
        origins = patch_origins(sample_rng(seed, index, STREAM_PATCHES), V, p, c.synth.patches_per_volume)
        grid = synth.grid
        kind = "occupancy" if c.target == "occupancy" else "emission"
        volumes = []
        for origin in origins:
            centre, q = _block(c, origin, self.scale)
            local = patch_emitters(sample.draw.emitters, centre, self.scale)
            near = (np.abs(local.x_um) <= q * grid.voxel_um[2]) & (np.abs(local.y_um) <= q * grid.voxel_um[1])
            local = Emitters(*(getattr(local, n)[near] for n in ("x_um", "y_um", "z_um", "diameter_um", "intensity")))
            block_grid = VolumeGrid((grid.shape[0], q, q), pixel_voxel_um(c, self.scale))
            block = rasterize_balls(local, block_grid, supersample=synth.supersample, kind=kind)
            volumes.append(np.clip(block, 0.0, 1.0))
        views, demixed = sample.views, sample.demixed
        if self.registration is not None:
            from cm2optics.recon.net.register import register_views

            views, demixed = register_views(views, self.registration), register_views(demixed, self.registration)
        return {
            "views": np.stack([views[:, r : r + p, s : s + p] for r, s in origins]).astype(np.float32),
            "demixed": np.stack([demixed[:, r : r + p, s : s + p] for r, s in origins]).astype(np.float32),
            "volume": np.stack(volumes).astype(np.float32),
            "origins": origins,
            "emitters": sample.draw.emitters,
        }

    def patch(self, item: Item) -> dict[str, np.ndarray]:
        v = self.volume(item.seed, item.volume, item.density)
        return {k: v[k][item.patch] for k in ("views", "demixed", "volume")}

    def truth(self, item: Item, border: int) -> Emitters:
        """The true emitters of a patch in its frame, centres within the part the loss sees."""
        v = self.volume(item.seed, item.volume, item.density)
        centre, q = _block(self.config, v["origins"][item.patch], self.scale)
        voxel = pixel_voxel_um(self.config, self.scale)[1]
        return patch_emitters(v["emitters"], centre, self.scale, border * voxel, q * voxel / 2.0)


class PatchDataset(Dataset):
    """A list of :class:`Item` → dicts of float32 tensors (views, demixed, volume)."""

    def __init__(self, config: NetConfig, items: list[Item]):
        self.config = config
        self.items = list(items)
        self._sources: dict[int, PatchSource] = {}

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = self.items[i]
        if item.source not in self._sources:  # made lazily: each DataLoader worker keeps its own cache
            self._sources[item.source] = PatchSource(self.config.mix_config() if item.source else self.config)
        patch = self._sources[item.source].patch(item)
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in patch.items()}


def density_at(config: NetConfig, epoch: int) -> tuple[float, float]:
    """The curriculum's density range (per mm²) at ``epoch``: from ``curriculum_start_density``
    to ``synth.density_per_mm2`` linearly over ``curriculum_epochs`` epochs."""
    final = tuple(float(v) for v in config.synth.density_per_mm2)
    if config.curriculum_epochs <= 0:
        return final  # type: ignore[return-value]
    t = min(epoch / config.curriculum_epochs, 1.0)
    start = config.curriculum_start_density
    return (round(start[0] + t * (final[0] - start[0]), 6), round(start[1] + t * (final[1] - start[1]), 6))


def epoch_items(config: NetConfig, epoch: int) -> list[Item]:
    """Every training item of ``epoch`` in its order (see the module docstring)."""
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, epoch, 17]))
    base = epoch * config.train_volumes if config.fresh_volumes else 0
    mixed = _mixed_slots(config, epoch)
    sources = {0: config, 1: config.mix_config() if mixed else config}
    per_volume = []
    for v in rng.permutation(config.train_volumes):
        source = int(v in mixed)
        c = sources[source]
        seed = config.seed + MIX_SEED_OFFSET * source
        density = density_at(c, epoch)
        per_volume.append(
            [Item(seed, int(base + v), int(k), density, source) for k in rng.permutation(c.synth.patches_per_volume)]
        )
    G = config.interleave_volumes
    return [
        item
        for start in range(0, len(per_volume), G)
        for item in _interleaved(per_volume[start : start + G], config.batch_size)
    ]


def _interleaved(volumes: list[list[Item]], batch: int) -> list[Item]:
    """The items of a group of volumes, batch after batch cycling over the volumes (each batch
    from one volume); each volume's last partial batch, if any, at the end."""
    n_full = [len(items) // batch for items in volumes]
    out = [
        item
        for j in range(max(n_full, default=0))
        for items, n in zip(volumes, n_full, strict=True)
        if j < n
        for item in items[j * batch : (j + 1) * batch]
    ]
    return out + [item for items, n in zip(volumes, n_full, strict=True) for item in items[n * batch :]]


def _mixed_slots(config: NetConfig, epoch: int) -> set[int]:
    """The volume slots of ``epoch`` that the mixed source fills (none without one)."""
    n = round(config.mix_fraction * config.train_volumes) if config.mix_forward_model else 0
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, epoch, 29]))
    return {int(v) for v in rng.choice(config.train_volumes, n, replace=False)} if n else set()


def steps_per_epoch(config: NetConfig) -> int:
    n_mixed = len(_mixed_slots(config, 0))
    mixed = config.mix_config().synth.patches_per_volume * n_mixed if n_mixed else 0
    return ((config.train_volumes - n_mixed) * config.synth.patches_per_volume + mixed) // config.batch_size


def rank_items(config: NetConfig, items: list[Item], rank: int, world: int, start_step: int = 0) -> list[Item]:
    """Rank ``rank``'s share of whole global batches from step ``start_step`` on."""
    B = config.batch_size
    if B % world:
        raise ConfigError(f"batch_size = {B}: must be a multiple of the {world} ranks")
    b = B // world
    out: list[Item] = []
    for s in range(start_step, len(items) // B):
        out.extend(items[s * B + rank * b : s * B + (rank + 1) * b])
    return out


def validation_items(config: NetConfig, source: int = 0) -> list[Item]:
    """The fixed validation patches: ``val_volumes`` volumes of the config's source (``source``
    0), or ``val_mix_volumes`` of the mixed source (1: its recipe, seed ``seed + MIX_SEED_OFFSET
    + VALIDATION_SEED_OFFSET``)."""
    seed = config.seed + VALIDATION_SEED_OFFSET
    n, c = config.val_volumes, config
    if source:
        n, c, seed = config.val_mix_volumes, config.mix_config(), seed + MIX_SEED_OFFSET
    density = tuple(float(v) for v in c.synth.density_per_mm2)
    return [Item(seed, v, k, density, source) for v in range(n) for k in range(c.synth.patches_per_volume)]


def validation_volumes(config: NetConfig, n_volumes: int):
    """The first ``n_volumes`` full-field validation volumes (the run's validation seed, never a
    test set's) imaged through the config's forward model: yields ``(sample, imaging)``."""
    from cm2optics.synth.generate import synthesize_sample

    imaging = forward_imaging(config)
    synth = config.synth.with_changes(view_px=0, patch_px=0, patches_per_volume=0, store_volume=False)
    seed = config.seed + VALIDATION_SEED_OFFSET
    for index in range(n_volumes):
        yield synthesize_sample(synth, imaging, index, seed), imaging

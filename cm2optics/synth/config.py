"""Parameters of a synthetic data set: one frozen, validated dataclass; every size is a field.

:meth:`SynthConfig.paper` is the paper's full-size recipe (Section 2.4): field of view
U[6.5, 7.5] mm, 800 µm deep, 4.12 × 4.12 × 10 µm voxels (the cm2-v2 object pixel and axial step), balls made on a 5× finer grid and
averaged down, diameter U[8, 20] µm, intensity ∝ diameter² × U[0.8, 1.2], density U[10, 100]
per mm², mixed Poisson (≈ 500 peak photons) and Gaussian (mean 0.048, sd 0.017) noise, nine
1920 × 1920 views cropped at the chief rays, 320 × 320 training patches.
:meth:`SynthConfig.scaled` keeps the recipe and shrinks the field, the views and the patches
(and coarsens the grid to a binned model's pixel) so that sets fit a small machine.

The volume grid is the same for every sample (its side fits the largest field); each sample
draws its own field, and its emitters lie within it (a disc by default: the illuminated circle).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from cm2optics.design import default_design
from cm2optics.formats.volume import VolumeGrid
from cm2optics.optics import first_order

__all__ = ["NOISE_MODELS", "RENDER_MODES", "SynthConfig"]

NOISE_MODELS = ("poisson-gaussian", "variance", "none")
RENDER_MODES = ("auto", "sparse", "volume")


def _pair(name: str, value: Any, low: float, high: float, unit: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {value!r}: must be a pair (low, high) in {unit}") from None
    if not (math.isfinite(a) and math.isfinite(b) and low <= a <= b <= high):
        raise ValueError(f"{name} = {value!r}: need {low} ≤ low ≤ high ≤ {high} {unit}")
    return a, b


@dataclass(frozen=True)
class SynthConfig:
    """fov_mm: (low, high) field of view per sample, mm (diameter of the disc, or side).
    field_shape: ``disk`` or ``square``. depth_um: axial extent (emitter centres within ±depth/2), µm.
    voxel_um: (z, y, x) voxel pitch, µm (None: the cm2-v2 preset's axial step and object pixel). supersample: fine sub-voxels per voxel and axis.
    diameter_um: (low, high) ball diameter, µm. intensity_jitter: (low, high) factor on d².
    density_per_mm2: (low, high) emitters per mm² of the field.
    noise: ``poisson-gaussian`` (peak_photons, offset_mean, offset_sd), ``variance``
    (variance = variance_a·I + variance_b) or ``none``; on images normalised to a peak of 1.
    render: ``sparse`` (the model's emitter renderer, no volume in the loop), ``volume``
    (forward of the rasterised volume) or ``auto`` (sparse when the model has it).
    view_px: side of the nine views cropped at the chief rays (0: no views).
    patch_px: side of the training patches (0: no patches). patches_per_volume: patches per sample.
    store_volume: keep the ground-truth volume in each sample file.
    """

    fov_mm: tuple[float, float] = (6.5, 7.5)
    field_shape: str = "disk"
    depth_um: float = 800.0
    voxel_um: tuple[float, float, float] | None = None
    supersample: int = 5
    diameter_um: tuple[float, float] = (8.0, 20.0)
    intensity_jitter: tuple[float, float] = (0.8, 1.2)
    density_per_mm2: tuple[float, float] = (10.0, 100.0)
    noise: str = "poisson-gaussian"
    peak_photons: float = 500.0
    offset_mean: float = 0.048
    offset_sd: float = 0.017
    variance_a: float = 1.5e-4
    variance_b: float = 5.4e-6
    render: str = "auto"
    view_px: int = 1920
    patch_px: int = 320
    patches_per_volume: int = 36
    store_volume: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "fov_mm", _pair("fov_mm", self.fov_mm, 0.01, 100.0, "mm"))
        object.__setattr__(self, "diameter_um", _pair("diameter_um", self.diameter_um, 0.0, 1000.0, "µm"))
        object.__setattr__(self, "intensity_jitter", _pair("intensity_jitter", self.intensity_jitter, 0.0, 100.0, ""))
        object.__setattr__(self, "density_per_mm2", _pair("density_per_mm2", self.density_per_mm2, 0.0, 1e5, "per mm²"))
        if self.voxel_um is None:
            object.__setattr__(self, "voxel_um", first_order.voxel_um(default_design()))
        try:
            voxel = tuple(float(v) for v in self.voxel_um)
        except (TypeError, ValueError):
            raise ValueError(f"voxel_um = {self.voxel_um!r}: must be three numbers (z, y, x) in µm") from None
        if len(voxel) != 3 or not all(math.isfinite(v) and v > 0 for v in voxel):
            raise ValueError(f"voxel_um = {self.voxel_um!r}: must be three numbers > 0 (z, y, x) in µm")
        object.__setattr__(self, "voxel_um", voxel)
        if self.field_shape not in ("disk", "square"):
            raise ValueError(f"field_shape = {self.field_shape!r}: must be 'disk' or 'square'")
        if not (math.isfinite(self.depth_um) and 0 <= self.depth_um <= 10_000):
            raise ValueError(f"depth_um = {self.depth_um}: must lie within 0–10000 µm")
        if not (isinstance(self.supersample, int) and 1 <= self.supersample <= 16):
            raise ValueError(f"supersample = {self.supersample!r}: must be an integer within 1–16")
        if self.noise not in NOISE_MODELS:
            raise ValueError(f"noise = {self.noise!r}: must be one of {', '.join(NOISE_MODELS)}")
        if self.render not in RENDER_MODES:
            raise ValueError(f"render = {self.render!r}: must be one of {', '.join(RENDER_MODES)}")
        for name in ("peak_photons",):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} = {getattr(self, name)}: must be a finite number > 0")
        for name in ("offset_sd", "variance_a", "variance_b"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} = {getattr(self, name)}: must be a finite number ≥ 0")
        if not math.isfinite(self.offset_mean):
            raise ValueError(f"offset_mean = {self.offset_mean}: must be finite")
        for name in ("view_px", "patch_px", "patches_per_volume"):
            value = getattr(self, name)
            if not (isinstance(value, int) and 0 <= value <= 100_000):
                raise ValueError(f"{name} = {value!r}: must be an integer within 0–100000")
        if self.patch_px and self.view_px and self.patch_px > self.view_px:
            raise ValueError(f"patch_px = {self.patch_px}: must not exceed view_px = {self.view_px}")
        if self.patch_px and self.patches_per_volume and not self.view_px:
            raise ValueError("patches are cut from the views: set view_px > 0 (or patch_px = 0)")
        if self.n_voxels > 2_000_000_000:
            raise ValueError(
                f"the grid {self.grid.shape} has {self.n_voxels / 1e9:.1f} G voxels (> 2 G): coarsen voxel_um or shrink fov_mm"
            )

    # -- derived ----------------------------------------------------------------------------
    @property
    def grid(self) -> VolumeGrid:
        """The volume grid shared by every sample: its side holds the largest field."""
        dz, dy, dx = self.voxel_um
        nz = int(math.floor(self.depth_um / dz + 1e-9)) + 1
        side = self.fov_mm[1] * 1000.0
        ny = int(math.ceil(side / dy - 1e-9))
        nx = int(math.ceil(side / dx - 1e-9))
        return VolumeGrid((nz, ny, nx), (dz, dy, dx))

    @property
    def n_voxels(self) -> int:
        nz, ny, nx = self.grid.shape
        return nz * ny * nx

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SynthConfig:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown synth parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})

    def with_changes(self, **changes: Any) -> SynthConfig:
        return replace(self, **changes)

    # -- presets ----------------------------------------------------------------------------
    @classmethod
    def paper(cls) -> SynthConfig:
        """The paper's full-size recipe."""
        return cls()

    @classmethod
    def scaled(
        cls, factor: float, *, voxel_um: tuple[float, float, float] | None = None, **changes: Any
    ) -> SynthConfig:
        """The paper's recipe with the field, views and patches shrunk by ``factor`` (> 1) — the
        same emitters, densities, sizes and noise on a smaller field. ``voxel_um`` sets the grid
        (e.g. a binned model's native pitch); ``changes`` override any field."""
        if not (math.isfinite(factor) and factor >= 1):
            raise ValueError(f"factor = {factor}: must be ≥ 1")
        base = cls()
        values: dict[str, Any] = {
            "fov_mm": (base.fov_mm[0] / factor, base.fov_mm[1] / factor),
            "view_px": max(int(round(base.view_px / factor / 2)) * 2, 16),
            "patch_px": max(int(round(base.patch_px / factor / 2)) * 2, 8),
        }
        if voxel_um is not None:
            values["voxel_um"] = tuple(voxel_um)
        values.update(changes)
        return replace(base, **values)

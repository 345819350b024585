"""A measurement of a few emitters, by tracing each one: the brute-force reference image.

Emitters come as CSV ``x_um,y_um,z_um,diameter_um,intensity`` (DESIGN.md): object-space
position (µm; x, y from the central lenslet's axis, z from the nominal focal plane, +z towards
the device), bead diameter (µm; a uniform disc in the image) and relative brightness (photons
emitted, in any unit, ≥ 0). Fluorescent emitters are isotropic and emit the fluorophore's
spectrum (``gfp-emission``); each is imaged through every lenslet with the full model of
:mod:`.psf`, and the frames add up (incoherent light).

The measurement is a 16-bit TIFF of raw counts, ``counts = Σ intensity × PSF × scale + dark``
with ``scale`` chosen (unless given) so that the brightest pixel sits at ``fill`` of the
sensor's full scale, and a YAML sidecar (``NAME.yaml``) that records the scale, units, pixel
pitch and orientation. No noise is added: this image is what the 3D-LSV model must reproduce.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
import yaml

import cm2optics
from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, PSFSettings, add_focus
from cm2optics.emission.source import fluorescent_bead
from cm2optics.io import write_atomic, write_text_atomic

__all__ = ["EMITTER_COLUMNS", "Emitters", "read_emitters_csv", "render_emitters", "write_measurement"]

EMITTER_COLUMNS = ("x_um", "y_um", "z_um", "diameter_um", "intensity")


@dataclass(frozen=True, eq=False)
class Emitters:
    """Emitters: ``positions_um`` (N, 3) object-space (x, y, z) in µm, ``diameter_um`` (N,) µm,
    ``intensity`` (N,) relative photons emitted (≥ 0)."""

    positions_um: np.ndarray
    diameter_um: np.ndarray
    intensity: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.positions_um, dtype=float)
        d = np.asarray(self.diameter_um, dtype=float)
        i = np.asarray(self.intensity, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
            raise ValueError(f"positions_um has shape {p.shape}: must be (N, 3) with N ≥ 1")
        if d.shape != (len(p),) or i.shape != (len(p),):
            raise ValueError("diameter_um and intensity need one value per emitter")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(d)) and np.all(np.isfinite(i))):
            raise ValueError("emitters must be finite (no NaN)")
        if np.any(d < 0) or np.any(d > 200):
            raise ValueError(f"diameter_um must lie within 0–200 µm (got {d.min():g}–{d.max():g})")
        if np.any(i < 0):
            raise ValueError("intensity must be ≥ 0")
        object.__setattr__(self, "positions_um", p)
        object.__setattr__(self, "diameter_um", d)
        object.__setattr__(self, "intensity", i)

    def __len__(self) -> int:
        return len(self.intensity)


def read_emitters_csv(path: str | Path) -> Emitters:
    """Read an emitters CSV (columns :data:`EMITTER_COLUMNS`; lines starting ``#`` are comments)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such emitters file")
    with path.open(newline="") as handle:
        reader = csv.DictReader(row for row in handle if not row.lstrip().startswith("#"))
        columns = [c.strip() for c in reader.fieldnames or []]
        missing = [c for c in EMITTER_COLUMNS if c not in columns]
        if missing:
            raise ValueError(f"{path}: needs columns {','.join(EMITTER_COLUMNS)} (missing {', '.join(missing)})")
        rows = []
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            try:
                rows.append([float(row[c]) for c in EMITTER_COLUMNS])
            except ValueError:
                raise ValueError(
                    f"{path} line {line}: {','.join(EMITTER_COLUMNS)} must be numbers (got {row})"
                ) from None
    if not rows:
        raise ValueError(f"{path}: no emitters")
    a = np.asarray(rows)
    try:
        return Emitters(a[:, :3], a[:, 3], a[:, 4])
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def render_emitters(
    design: SystemDesign,
    emitters: Emitters,
    settings: PSFSettings | None = None,
    progress: bool = False,
) -> np.ndarray:
    """The frame of ``emitters`` (float64, (rows, cols) of the binned sensor): Σ intensity × PSF,
    in photons detected per unit of intensity."""
    model = EmissionModel(design, fluorescent_bead(0.0), settings=settings)
    for p in emitters.positions_um:
        model.device_point_mm(p / 1000.0)
    frame = np.zeros(model.grid.shape)
    from rich.progress import Progress

    with Progress(disable=not progress, transient=True) as bar:
        task = bar.add_task("tracing emitters", total=len(emitters))
        for position, diameter, intensity in zip(
            emitters.positions_um, emitters.diameter_um, emitters.intensity, strict=True
        ):
            if intensity > 0:
                for focus in model.foci(position / 1000.0, diameter_um=diameter):
                    add_focus(frame, focus, intensity)
            bar.advance(task)
    return frame


def write_measurement(
    path: str | Path,
    frame: np.ndarray,
    design: SystemDesign,
    binning: int,
    *,
    fill: float = 0.8,
    scale: float | None = None,
    dark_level: float = 0.0,
    extra: dict[str, Any] | None = None,
) -> tuple[Path, Path]:
    """Write ``frame`` (photons detected per unit intensity) as a 16-bit TIFF of counts at the
    sensor's bit depth and its YAML sidecar; returns both paths. ``scale`` (counts per unit of
    frame) defaults to putting the brightest pixel at ``fill`` (0.05–1) of full scale."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"{path}: a measurement is a TIFF (.tif or .tiff)")
    if not (math.isfinite(fill) and 0.05 <= fill <= 1.0):
        raise ValueError(f"fill = {fill!r}: must lie within 0.05–1")
    bits = design.sensor.bit_depth
    full = 2**bits - 1
    if not (math.isfinite(dark_level) and 0 <= dark_level < full):
        raise ValueError(f"dark_level = {dark_level!r}: must lie within 0–{full} counts")
    peak = float(frame.max())
    if scale is None:
        scale = (fill * full - dark_level) / peak if peak > 0 else 1.0
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale = {scale!r}: must be a finite number > 0")
    counts = np.clip(np.rint(frame * scale + dark_level), 0, full).astype(np.uint16)
    write_atomic(path, lambda tmp: tifffile.imwrite(tmp, counts, photometric="minisblack"))
    sidecar = {
        "pixel_um": design.sensor.pixel_um * binning,
        "binning": binning,
        "bit_depth": bits,
        "dark_level": dark_level,
        "counts_per_unit": float(scale),
        "units": "counts = sum(intensity x photons detected per photon emitted) x counts_per_unit + dark_level",
        "image_orientation": "sensor frame: column along +x, row along +y of the device frame, optical axis at the centre",
        "synthetic": True,
        "noise": "none",
        "design": design.name,
        "design_hash": design.parameter_hash(),
        "generator": f"cm2optics {cm2optics.__version__} (cm2optics.emission.image)",
        **(extra or {}),
    }
    yaml_path = path.with_suffix(".yaml")
    write_text_atomic(yaml_path, yaml.safe_dump(sidecar, sort_keys=False, allow_unicode=True))
    return path, yaml_path

"""The PSF calibration scan format, shared by measured and synthetic scans (DESIGN.md).

A scan is a folder:

- ``positions.csv`` with columns ``file,x_mm,y_mm,z_mm,exposure_ms``, one row per image;
  ``file`` names a 16-bit TIFF in the folder, or ``NAME.tif#K`` for page K (0-based) of a
  multi-page TIFF.
- one 16-bit TIFF per row (or multi-page TIFFs as above), all of one shape ``(y, x)``.
- ``scan.yaml`` with at least ``pixel_um`` (pitch of the saved images, after binning, µm),
  ``binning``, ``bit_depth`` and ``dark_level`` (counts); any further keys are kept.

Source positions are in the device's object space: ``x_mm, y_mm`` from the optical axis of
the central lenslet, ``z_mm`` from the nominal focal plane, +z towards the device.
"""

from __future__ import annotations

import csv
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
import yaml

from cm2optics.io import write_text_atomic

COLUMNS = ("file", "x_mm", "y_mm", "z_mm", "exposure_ms")
REQUIRED_META = ("pixel_um", "binning", "bit_depth", "dark_level")


class ScanError(ValueError):
    """A scan folder that does not follow the format; the message says what and where."""


@dataclass(frozen=True)
class ScanMeta:
    """What ``scan.yaml`` says about the images.

    pixel_um: pitch of the saved images (after binning), µm.
    binning: sensor pixels per saved pixel along each axis.
    bit_depth: ADC bits of the raw data (counts run 0 … 2**bit_depth − 1).
    dark_level: mean dark offset of the images, counts.
    extra: any further keys (sensor name, source diameter, …), kept as read.
    """

    pixel_um: float
    binning: int
    bit_depth: int
    dark_level: float
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.pixel_um) and self.pixel_um > 0):
            raise ScanError(f"scan.yaml: pixel_um = {self.pixel_um!r}: must be a finite number > 0 (µm)")
        if not (isinstance(self.binning, int) and self.binning >= 1):
            raise ScanError(f"scan.yaml: binning = {self.binning!r}: must be an integer ≥ 1")
        if self.bit_depth not in (8, 10, 12, 14, 16):
            raise ScanError(f"scan.yaml: bit_depth = {self.bit_depth!r}: must be one of 8, 10, 12, 14, 16")
        if not (math.isfinite(self.dark_level) and 0 <= self.dark_level < 2**self.bit_depth):
            raise ScanError(f"scan.yaml: dark_level = {self.dark_level!r}: must lie within 0 … 2**bit_depth")

    def to_dict(self) -> dict[str, Any]:
        return {"pixel_um": self.pixel_um, "binning": self.binning, "bit_depth": self.bit_depth, "dark_level": self.dark_level, **self.extra}


@dataclass(frozen=True)
class PSFScan:
    """A loaded scan: ``images`` (N, y, x) as stored (uint16 counts), ``positions_mm`` (N, 3)
    as (x, y, z), ``exposure_ms`` (N,), ``files`` (N,) as named in the CSV, and ``meta``."""

    images: np.ndarray
    positions_mm: np.ndarray
    exposure_ms: np.ndarray
    files: tuple[str, ...]
    meta: ScanMeta
    folder: Path | None = None

    def grid_axes_mm(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sorted unique x, y, z (mm) of a scan whose positions form a full grid."""
        return grid_axes_mm(self.positions_mm)

    def normalised(self) -> np.ndarray:
        """Images as float32 with the dark level removed and divided by exposure (counts/ms)."""
        counts = self.images.astype(np.float32) - np.float32(self.meta.dark_level)
        return counts / self.exposure_ms.astype(np.float32)[:, None, None]


def grid_axes_mm(positions_mm: np.ndarray, decimals: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique x, y, z (mm) of ``positions_mm`` (N, 3); raises :class:`ScanError` unless every
    combination occurs exactly once (a full, regular-or-not grid)."""
    rounded = np.round(np.asarray(positions_mm, dtype=float), decimals)
    axes = tuple(np.unique(rounded[:, k]) for k in range(3))
    expected = len(axes[0]) * len(axes[1]) * len(axes[2])
    unique_rows = np.unique(rounded, axis=0)
    if len(unique_rows) != len(rounded):
        raise ScanError(f"positions.csv: {len(rounded) - len(unique_rows)} positions occur more than once")
    if len(rounded) != expected:
        shape = "×".join(str(len(a)) for a in axes)
        raise ScanError(f"positions.csv: {len(rounded)} positions do not form a grid (the unique x, y, z span {shape} = {expected})")
    return axes


def _read_meta(folder: Path) -> ScanMeta:
    path = folder / "scan.yaml"
    if not path.is_file():
        raise ScanError(f"{folder}: no scan.yaml (needs {', '.join(REQUIRED_META)})")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise ScanError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(data, dict):
        raise ScanError(f"{path}: must be a mapping of keys")
    missing = [key for key in REQUIRED_META if key not in data]
    if missing:
        raise ScanError(f"{path}: missing {', '.join(missing)}")
    extra = {k: v for k, v in data.items() if k not in REQUIRED_META}
    try:
        return ScanMeta(float(data["pixel_um"]), int(data["binning"]), int(data["bit_depth"]), float(data["dark_level"]), extra)
    except (TypeError, ValueError) as error:
        if isinstance(error, ScanError):
            raise
        raise ScanError(f"{path}: {error}") from None


def _read_rows(folder: Path) -> list[dict[str, str]]:
    path = folder / "positions.csv"
    if not path.is_file():
        raise ScanError(f"{folder}: no positions.csv (columns {','.join(COLUMNS)})")
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        if reader.fieldnames is None or [c.strip() for c in reader.fieldnames] != list(COLUMNS):
            raise ScanError(f"{path}: columns must be {','.join(COLUMNS)} (found {','.join(reader.fieldnames or [])})")
        rows = [{k.strip(): (v or "").strip() for k, v in row.items()} for row in reader]
    if not rows:
        raise ScanError(f"{path}: no rows")
    return rows


def _number(row: dict[str, str], key: str, line: int) -> float:
    try:
        value = float(row[key])
    except ValueError:
        raise ScanError(f"positions.csv line {line}: {key} = {row[key]!r} is not a number") from None
    if not math.isfinite(value):
        raise ScanError(f"positions.csv line {line}: {key} = {row[key]!r} is not finite")
    return value


def read_scan(folder: str | Path) -> PSFScan:
    """Load and validate a scan folder; every problem raises one :class:`ScanError`."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ScanError(f"{folder}: no such scan folder")
    meta = _read_meta(folder)
    rows = _read_rows(folder)
    positions, exposures, images = [], [], []
    pages: dict[str, np.ndarray] = {}
    for line, row in enumerate(rows, start=2):
        positions.append([_number(row, k, line) for k in ("x_mm", "y_mm", "z_mm")])
        exposure = _number(row, "exposure_ms", line)
        if exposure <= 0:
            raise ScanError(f"positions.csv line {line}: exposure_ms = {exposure} must be > 0")
        exposures.append(exposure)
        name, _, page = row["file"].partition("#")
        path = folder / name
        if name not in pages:
            if not path.is_file():
                raise ScanError(f"positions.csv line {line}: {name} is missing from {folder}")
            try:
                pages[name] = tifffile.imread(path)
            except Exception as error:  # tifffile raises many types for corrupt files
                raise ScanError(f"{path}: not a readable TIFF ({error})") from None
        stack = pages[name]
        if page:
            if stack.ndim != 3 or not page.isdigit() or int(page) >= stack.shape[0]:
                raise ScanError(f"positions.csv line {line}: {row['file']} names no page of {name}")
            image = stack[int(page)]
        else:
            if stack.ndim != 2:
                raise ScanError(f"positions.csv line {line}: {name} has several pages; name one as {name}#K")
            image = stack
        if image.dtype != np.uint16:
            raise ScanError(f"{path}: images must be 16-bit unsigned (found {image.dtype})")
        if images and image.shape != images[0].shape:
            raise ScanError(f"{path}: shape {image.shape} differs from the first image's {images[0].shape}")
        images.append(image)
    listed = {row["file"].partition("#")[0] for row in rows}
    extra = sorted(p.name for p in folder.glob("*.tif*") if p.name not in listed)
    if extra:
        raise ScanError(f"{folder}: TIFFs not listed in positions.csv: {', '.join(extra[:5])}")
    if int(np.max([im.max() for im in images])) >= 2**meta.bit_depth and meta.bit_depth < 16:
        raise ScanError(f"{folder}: counts exceed bit_depth = {meta.bit_depth}")
    positions_mm = np.asarray(positions)
    grid_axes_mm(positions_mm)
    return PSFScan(np.stack(images), positions_mm, np.asarray(exposures), tuple(r["file"] for r in rows), meta, folder)


def write_scan(
    folder: str | Path,
    images: np.ndarray,
    positions_mm: np.ndarray,
    exposure_ms: np.ndarray | float,
    meta: ScanMeta,
    *,
    names: list[str] | None = None,
) -> Path:
    """Write a scan folder (one TIFF per position) atomically: into a staging folder beside
    ``folder``, then renamed into place. ``images`` (N, y, x) must already be uint16 counts."""
    folder = Path(folder)
    images = np.asarray(images)
    positions_mm = np.asarray(positions_mm, dtype=float)
    if images.ndim != 3 or images.dtype != np.uint16:
        raise ScanError(f"images must be uint16 of shape (N, y, x) (got {images.dtype} {images.shape})")
    if positions_mm.shape != (len(images), 3) or not np.all(np.isfinite(positions_mm)):
        raise ScanError(f"positions_mm must be finite with shape ({len(images)}, 3) (got {positions_mm.shape})")
    exposures = np.broadcast_to(np.asarray(exposure_ms, dtype=float), (len(images),))
    names = names or [f"psf_{i:05d}.tif" for i in range(len(images))]
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    try:
        lines = [",".join(COLUMNS)]
        for name, image, (x, y, z), exposure in zip(names, images, positions_mm, exposures, strict=True):
            tifffile.imwrite(staging / name, image, photometric="minisblack")
            lines.append(f"{name},{x:.6f},{y:.6f},{z:.6f},{exposure:g}")
        (staging / "positions.csv").write_text("\n".join(lines) + "\n")
        write_text_atomic(staging / "scan.yaml", yaml.safe_dump(meta.to_dict(), sort_keys=False))
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(staging, folder)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return folder

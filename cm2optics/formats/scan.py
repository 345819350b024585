"""The PSF calibration scan format, shared by measured and synthetic scans (DESIGN.md).

A scan is a folder:

- ``positions.csv`` with columns ``file,x_mm,y_mm,z_mm,exposure_ms``, one row per image;
  ``file`` names a 16-bit TIFF in the folder, or ``NAME.tif#K`` for page K (0-based) of a
  multi-page TIFF. Rows may come in any order: the grid is recovered from the positions.
- one 16-bit TIFF per row (or multi-page TIFFs as above), all of one shape ``(y, x)``.
- ``scan.yaml`` with at least ``pixel_um`` (pitch of the saved images, after binning, µm),
  ``binning``, ``bit_depth`` and ``dark_level`` (counts); any further keys are kept
  (``lenslets: [rows, cols]`` tells the LSV builder how many foci to expect).

Source positions are in the device's object space: ``x_mm, y_mm`` from the optical axis of
the central lenslet, ``z_mm`` from the nominal focal plane, +z towards the device.

What the reader rejects, each with one :class:`ScanError` naming the file and line:
missing or unlisted TIFFs, unreadable TIFFs, images that are not 16-bit unsigned (a float
image with NaNs says so), shapes that differ, counts beyond ``bit_depth``, non-numeric,
NaN or infinite positions, exposures ≤ 0, positions that do not form a full grid, and
**misordered files**, which this format defines as:

1. one image (file, or page of a multi-page TIFF) listed on two rows; or
2. an image whose embedded position disagrees with its row: :func:`write_scan` stores each
   image's position and exposure as JSON in the TIFF ``ImageDescription``
   (``{"cm2optics_psf_scan": 1, "x_mm": …}``), and the reader checks it when present.

A measured scan written by other software has no embedded positions; for those, the LSV
builder (``cm2 lsv build``) checks the image content instead: every image's foci must lie
where the fitted imaging geometry puts the source of its row
(:func:`cm2optics.lsv.preprocess.estimate_geometry`).

:func:`open_scan` validates a folder from the CSV and the TIFF headers and returns a
:class:`ScanIndex` that loads one image at a time (a full-size 9×9×11 scan is ≈ 11 GB of
pixels); :func:`read_scan` loads everything into a :class:`PSFScan`.
"""

from __future__ import annotations

import csv
import json
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

from cm2optics.formats.atomic import write_text_atomic
from cm2optics.formats.errors import FormatError
from cm2optics.formats.outputs import swap_in_folder

COLUMNS = ("file", "x_mm", "y_mm", "z_mm", "exposure_ms")
REQUIRED_META = ("pixel_um", "binning", "bit_depth", "dark_level")
#: Key of the JSON that :func:`write_scan` embeds in every TIFF's ImageDescription.
EMBED_KEY = "cm2optics_psf_scan"
#: Embedded and listed positions that differ by more than this (mm) are misordered files.
POSITION_TOLERANCE_MM = 1e-5
#: ``pixel_um`` may differ from ``binning`` × the sensor's pixel by this share (rounding).
PIXEL_TOLERANCE = 0.01


class ScanError(FormatError):
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

    def check_pixel(self, sensor_pixel_um: float, where: str = "scan.yaml") -> None:
        """Raise :class:`ScanError` unless ``pixel_um`` = ``binning`` × ``sensor_pixel_um`` (µm).

        A contradiction is a misread scan (the magnification comes out wrong by their ratio),
        so it is an error: fix ``scan.yaml``, or name the design whose sensor took the scan.
        """
        expected = self.binning * float(sensor_pixel_um)
        if abs(self.pixel_um - expected) > PIXEL_TOLERANCE * expected:
            raise ScanError(
                f"{where}: pixel_um = {self.pixel_um:g} contradicts binning = {self.binning} × the sensor's "
                f"{float(sensor_pixel_um):g} µm pixel = {expected:g} µm; correct pixel_um or binning "
                "(or use the design of the sensor that took the scan)"
            )

    def to_dict(self) -> dict[str, Any]:
        return {
            "pixel_um": self.pixel_um,
            "binning": self.binning,
            "bit_depth": self.bit_depth,
            "dark_level": self.dark_level,
            **self.extra,
        }


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


@dataclass(frozen=True)
class ScanIndex:
    """A validated scan whose images are read on demand (one at a time).

    positions_mm: (N, 3) source positions as (x, y, z), mm, in CSV row order.
    exposure_ms: (N,) exposures, ms.
    files: (N,) image names as written in the CSV (``NAME.tif`` or ``NAME.tif#K``).
    shape: (y, x) shape shared by all images.
    """

    folder: Path
    meta: ScanMeta
    positions_mm: np.ndarray
    exposure_ms: np.ndarray
    files: tuple[str, ...]
    shape: tuple[int, int]

    def __len__(self) -> int:
        return len(self.files)

    def grid_axes_mm(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return grid_axes_mm(self.positions_mm)

    def grid_index(self) -> np.ndarray:
        """(N, 3) integer indices (ix, iy, iz) of every row in :meth:`grid_axes_mm`."""
        return grid_index(self.positions_mm)

    def image(self, i: int) -> np.ndarray:
        """Image ``i`` as stored (uint16 counts); checks the counts against ``bit_depth``."""
        name, _, page = self.files[i].partition("#")
        path = self.folder / name
        try:
            image = tifffile.imread(path, key=int(page)) if page else tifffile.imread(path)
        except Exception as error:  # tifffile raises many types for corrupt files
            raise ScanError(f"{path}: not a readable TIFF ({error})") from None
        if image.shape != self.shape or image.dtype != np.uint16:
            raise ScanError(f"{path}: changed while reading (now {image.dtype} {image.shape})")
        if self.meta.bit_depth < 16 and int(image.max()) >= 2**self.meta.bit_depth:
            raise ScanError(f"{path}: counts up to {int(image.max())} exceed bit_depth = {self.meta.bit_depth}")
        return image

    def normalised(self, i: int) -> np.ndarray:
        """Image ``i`` as float32 with the dark level removed, divided by exposure (counts/ms)."""
        counts = self.image(i).astype(np.float32) - np.float32(self.meta.dark_level)
        return counts / np.float32(self.exposure_ms[i])

    def load(self) -> PSFScan:
        """Read every image into a :class:`PSFScan`."""
        images = (
            np.stack([self.image(i) for i in range(len(self))]) if len(self) else np.zeros((0, *self.shape), np.uint16)
        )
        return PSFScan(images, self.positions_mm, self.exposure_ms, self.files, self.meta, self.folder)


def grid_axes_mm(positions_mm: np.ndarray, decimals: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique x, y, z (mm) of ``positions_mm`` (N, 3); raises :class:`ScanError` unless every
    combination occurs exactly once (a full, regular-or-not grid)."""
    rounded = np.round(np.asarray(positions_mm, dtype=float), decimals)
    if rounded.ndim != 2 or rounded.shape[1] != 3 or not np.all(np.isfinite(rounded)):
        raise ScanError("positions must be finite (x, y, z) triples")
    axes = tuple(np.unique(rounded[:, k]) for k in range(3))
    expected = len(axes[0]) * len(axes[1]) * len(axes[2])
    unique_rows = np.unique(rounded, axis=0)
    if len(unique_rows) != len(rounded):
        raise ScanError(f"positions.csv: {len(rounded) - len(unique_rows)} positions occur more than once")
    if len(rounded) != expected:
        shape = "×".join(str(len(a)) for a in axes)
        missing = expected - len(rounded)
        raise ScanError(
            f"positions.csv: {len(rounded)} positions do not form a grid (the unique x, y, z span {shape} = {expected}; "
            f"{missing} grid points have no image)"
        )
    return axes


def grid_index(positions_mm: np.ndarray, decimals: int = 6) -> np.ndarray:
    """(N, 3) integer indices (ix, iy, iz) of ``positions_mm`` in :func:`grid_axes_mm`."""
    axes = grid_axes_mm(positions_mm, decimals)
    rounded = np.round(np.asarray(positions_mm, dtype=float), decimals)
    return np.stack([np.searchsorted(axes[k], rounded[:, k]) for k in range(3)], axis=1)


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
        return ScanMeta(
            float(data["pixel_um"]), int(data["binning"]), int(data["bit_depth"]), float(data["dark_level"]), extra
        )
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
        rows = [{k.strip(): (v or "").strip() for k, v in row.items() if k is not None} for row in reader]
    if not rows:
        raise ScanError(f"{path}: no rows")
    return rows


def _number(row: dict[str, str], key: str, line: int) -> float:
    try:
        value = float(row[key])
    except (TypeError, ValueError):
        raise ScanError(f"positions.csv line {line}: {key} = {row.get(key)!r} is not a number") from None
    if not math.isfinite(value):
        raise ScanError(f"positions.csv line {line}: {key} = {row[key]!r} is not finite")
    return value


@dataclass
class _TiffInfo:
    pages: int
    shape: tuple[int, ...]
    dtype: np.dtype
    descriptions: list[str]


def _tiff_info(path: Path) -> _TiffInfo:
    try:
        with tifffile.TiffFile(path) as tif:
            pages = len(tif.pages)
            first = tif.pages[0]
            shape = tuple(first.shape)
            dtype = np.dtype(first.dtype)
            descriptions = []
            for page in tif.pages:
                tag = page.tags.get("ImageDescription")
                descriptions.append(str(tag.value) if tag is not None else "")
                if tuple(page.shape) != shape or np.dtype(page.dtype) != dtype:
                    raise ScanError(f"{path}: pages differ in shape or type")
    except ScanError:
        raise
    except Exception as error:  # tifffile raises many types for corrupt files
        raise ScanError(f"{path}: not a readable TIFF ({error})") from None
    return _TiffInfo(pages, shape, dtype, descriptions)


def _embedded_position(description: str) -> dict[str, float] | None:
    if EMBED_KEY not in description:
        return None
    try:
        data = json.loads(description)
    except ValueError:
        return None
    return data if isinstance(data, dict) and data.get(EMBED_KEY) else None


def _dtype_message(path: Path, dtype: np.dtype) -> str:
    message = f"{path}: images must be 16-bit unsigned (found {dtype})"
    if np.issubdtype(dtype, np.floating):
        try:
            data = tifffile.imread(path)
            bad = int(np.sum(~np.isfinite(data)))
            if bad:
                message += f"; it also holds {bad} NaN or infinite pixels"
        except Exception:  # the dtype message stands on its own
            pass
    return message


def open_scan(folder: str | Path, *, sensor_pixel_um: float | None = None) -> ScanIndex:
    """Validate a scan folder from its CSV, YAML and TIFF headers; images load on demand.

    sensor_pixel_um: the pitch of the sensor that took the scan (µm, before binning); when
    given, ``scan.yaml``'s ``pixel_um`` must equal ``binning`` × it (:meth:`ScanMeta.check_pixel`).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ScanError(f"{folder}: no such scan folder")
    meta = _read_meta(folder)
    if sensor_pixel_um is not None:
        meta.check_pixel(sensor_pixel_um, str(folder / "scan.yaml"))
    rows = _read_rows(folder)
    infos: dict[str, _TiffInfo] = {}
    positions, exposures, seen = [], [], {}
    shape: tuple[int, ...] | None = None
    for line, row in enumerate(rows, start=2):
        position = [_number(row, k, line) for k in ("x_mm", "y_mm", "z_mm")]
        exposure = _number(row, "exposure_ms", line)
        if exposure <= 0:
            raise ScanError(f"positions.csv line {line}: exposure_ms = {exposure} must be > 0")
        entry = row.get("file", "")
        if not entry:
            raise ScanError(f"positions.csv line {line}: no file named")
        name, hash_, page = entry.partition("#")
        key = (name, int(page) if page.isdigit() else page)
        if key in seen:
            raise ScanError(
                f"positions.csv line {line}: {entry} is also listed on line {seen[key]}: misordered files "
                "(one image cannot belong to two positions)"
            )
        seen[key] = line
        path = folder / name
        if name not in infos:
            if not path.is_file():
                raise ScanError(f"positions.csv line {line}: {name} is missing from {folder}")
            infos[name] = _tiff_info(path)
        info = infos[name]
        if hash_:
            if not page.isdigit() or int(page) >= info.pages:
                raise ScanError(f"positions.csv line {line}: {entry} names no page of {name} ({info.pages} pages)")
            description = info.descriptions[int(page)]
        else:
            if info.pages != 1:
                raise ScanError(f"positions.csv line {line}: {name} has {info.pages} pages; name one as {name}#K")
            description = info.descriptions[0]
        if info.dtype != np.uint16:
            raise ScanError(_dtype_message(path, info.dtype))
        if len(info.shape) != 2:
            raise ScanError(f"{path}: each image must be 2-D (y, x), found shape {info.shape}")
        if shape is None:
            shape = info.shape
        elif info.shape != shape:
            raise ScanError(f"{path}: shape {info.shape} differs from the first image's {shape}")
        embedded = _embedded_position(description)
        if embedded is not None:
            recorded = [float(embedded.get(k, math.nan)) for k in ("x_mm", "y_mm", "z_mm")]
            if not np.allclose(recorded, position, atol=POSITION_TOLERANCE_MM, rtol=0):
                raise ScanError(
                    f"positions.csv line {line}: {entry} was recorded at (x, y, z) = "
                    f"({recorded[0]:g}, {recorded[1]:g}, {recorded[2]:g}) mm but is listed at "
                    f"({position[0]:g}, {position[1]:g}, {position[2]:g}) mm: misordered files"
                )
        positions.append(position)
        exposures.append(exposure)
    listed = {row["file"].partition("#")[0] for row in rows}
    extra = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in (".tif", ".tiff") and p.name not in listed)
    if extra:
        raise ScanError(
            f"{folder}: TIFFs not listed in positions.csv: {', '.join(extra[:5])}" + (" …" if len(extra) > 5 else "")
        )
    positions_mm = np.asarray(positions, dtype=float)
    grid_axes_mm(positions_mm)
    return ScanIndex(
        folder, meta, positions_mm, np.asarray(exposures, dtype=float), tuple(r["file"] for r in rows), shape
    )  # type: ignore[arg-type]


def read_scan(folder: str | Path, *, sensor_pixel_um: float | None = None) -> PSFScan:
    """Load and validate a scan folder; every problem raises one :class:`ScanError`."""
    return open_scan(folder, sensor_pixel_um=sensor_pixel_um).load()


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
    ``folder``, then renamed into place. ``images`` (N, y, x) must already be uint16 counts;
    each TIFF carries its position and exposure in its ImageDescription (JSON)."""
    folder = Path(os.path.abspath(folder))
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
            description = json.dumps(
                {
                    EMBED_KEY: 1,
                    "x_mm": round(float(x), 6),
                    "y_mm": round(float(y), 6),
                    "z_mm": round(float(z), 6),
                    "exposure_ms": float(exposure),
                }
            )
            tifffile.imwrite(staging / name, image, photometric="minisblack", description=description, metadata=None)
            lines.append(f"{name},{x:.6f},{y:.6f},{z:.6f},{exposure:.10g}")
        (staging / "positions.csv").write_text("\n".join(lines) + "\n")
        write_text_atomic(staging / "scan.yaml", yaml.safe_dump(meta.to_dict(), sort_keys=False))
        swap_in_folder(staging, folder, "psf simulate")  # never removes files it did not write
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return folder

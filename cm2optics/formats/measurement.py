"""A measurement: a 16-bit TIFF of raw counts with a YAML sidecar (``NAME.yaml``) beside it.

One schema for every writer (traced emitters, the LSV simulator, a lab's own frames): the
sidecar holds at least

- ``pixel_um``: pitch of the saved image (after binning), µm;
- ``bit_depth``: ADC bits of the counts (8, 10, 12, 14 or 16);
- ``dark_level``: mean dark offset, counts;
- ``counts_per_unit``: counts per unit of the generator's image (model units, photons …);
- ``noise``: ``null`` for a noise-free image, or a mapping of the noise settings;
- ``generator``: what wrote it;

and any further keys, kept as written. The image is ``(y, x)``, or ``(J, y, x)`` for the J
crosstalk-free per-lenslet images. Writes are atomic; :func:`read_measurement` reads a TIFF or
``.npy`` frame (a lab's frame may have no sidecar) and :func:`read_sidecar` checks the schema.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
import yaml

from cm2optics.formats.atomic import write_atomic, write_text_atomic
from cm2optics.formats.errors import FormatError

__all__ = ["SIDECAR_KEYS", "MeasurementError", "read_measurement", "read_sidecar", "sidecar_path", "write_measurement"]

#: The keys every sidecar holds, in the order they are written.
SIDECAR_KEYS = ("pixel_um", "bit_depth", "dark_level", "counts_per_unit", "noise", "generator")
BIT_DEPTHS = (8, 10, 12, 14, 16)


class MeasurementError(FormatError):
    """A measurement or sidecar that cannot be used; the message names the file and field."""


def sidecar_path(path: str | Path) -> Path:
    """The sidecar of measurement ``path``: the same name with ``.yaml``."""
    return Path(path).with_suffix(".yaml")


def _check_sidecar(where: str, meta: dict[str, Any]) -> dict[str, Any]:
    missing = [k for k in SIDECAR_KEYS if k not in meta]
    if missing:
        raise MeasurementError(f"{where}: sidecar misses {', '.join(missing)}")
    pixel, bits, dark, scale = (meta[k] for k in SIDECAR_KEYS[:4])
    if not (isinstance(pixel, (int, float)) and math.isfinite(pixel) and pixel > 0):
        raise MeasurementError(f"{where}: pixel_um = {pixel!r}: must be a finite number > 0 (µm)")
    if bits not in BIT_DEPTHS:
        raise MeasurementError(f"{where}: bit_depth = {bits!r}: must be one of {', '.join(map(str, BIT_DEPTHS))}")
    if not (isinstance(dark, (int, float)) and 0 <= dark < 2**bits):
        raise MeasurementError(f"{where}: dark_level = {dark!r}: must lie within 0 … 2**bit_depth counts")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise MeasurementError(f"{where}: counts_per_unit = {scale!r}: must be a finite number > 0")
    if meta["noise"] is not None and not isinstance(meta["noise"], dict):
        raise MeasurementError(f"{where}: noise = {meta['noise']!r}: must be null or a mapping of settings")
    return meta


def write_measurement(path: str | Path, counts: np.ndarray, meta: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``counts`` (uint16, (y, x) or (J, y, x)) as a TIFF and ``meta`` as its sidecar
    (the keys :data:`SIDECAR_KEYS` first, then the rest); returns both paths."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise MeasurementError(f"{path}: a measurement is a TIFF (.tif or .tiff)")
    counts = np.asarray(counts)
    if counts.dtype != np.uint16 or counts.ndim not in (2, 3):
        raise MeasurementError(f"{path}: counts must be uint16 (y, x) or (J, y, x) (got {counts.dtype} {counts.shape})")
    meta = _check_sidecar(str(path), dict(meta))
    if int(counts.max(initial=0)) >= 2 ** meta["bit_depth"]:
        raise MeasurementError(f"{path}: counts up to {int(counts.max())} exceed bit_depth = {meta['bit_depth']}")
    ordered = {k: meta[k] for k in SIDECAR_KEYS} | {k: v for k, v in meta.items() if k not in SIDECAR_KEYS}
    write_atomic(path, lambda tmp: tifffile.imwrite(tmp, counts, photometric="minisblack"))
    yaml_path = write_text_atomic(sidecar_path(path), yaml.safe_dump(ordered, sort_keys=False, allow_unicode=True))
    return path, yaml_path


def read_sidecar(path: str | Path) -> dict[str, Any] | None:
    """The sidecar of measurement ``path`` as a checked mapping, or None when there is none."""
    yaml_path = sidecar_path(path)
    if not yaml_path.is_file():
        return None
    try:
        meta = yaml.safe_load(yaml_path.read_text())
    except yaml.YAMLError as error:
        raise MeasurementError(f"{yaml_path}: not valid YAML ({error})") from None
    if not isinstance(meta, dict):
        raise MeasurementError(f"{yaml_path}: must be a mapping of keys")
    return _check_sidecar(str(yaml_path), meta)


def read_measurement(path: str | Path, dark_level: float = 0.0) -> np.ndarray:
    """A measurement image (TIFF or .npy) as float32 (y, x), less ``dark_level`` (counts)."""
    path = Path(path)
    if path.is_dir():
        raise MeasurementError(f"{path}: is a folder; give a measurement file (.tif or .npy)")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such measurement file")
    try:
        if path.suffix.lower() == ".npy":
            data = np.load(path, allow_pickle=False)
        elif path.suffix.lower() in (".tif", ".tiff"):
            data = tifffile.imread(path)
        else:
            raise MeasurementError(f"{path}: unknown measurement format {path.suffix!r} (use .tif or .npy)")
    except ValueError:
        raise
    except Exception as error:  # tifffile/numpy raise many types for corrupt files
        raise MeasurementError(f"{path}: not a readable image ({type(error).__name__}: {error})") from None
    data = np.squeeze(np.asarray(data))
    if data.ndim != 2:
        raise MeasurementError(f"{path}: a measurement is one image (y, x), found shape {data.shape}")
    if not np.issubdtype(data.dtype, np.number) or np.iscomplexobj(data):
        raise MeasurementError(f"{path}: pixel values must be real numbers (found {data.dtype})")
    data = data.astype(np.float32) - np.float32(dark_level)
    if not np.all(np.isfinite(data)):
        raise MeasurementError(f"{path}: contains {int(np.sum(~np.isfinite(data)))} NaN or infinite pixels")
    return data

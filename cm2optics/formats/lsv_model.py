"""The 3D-LSV model file: one HDF5 (``.h5``) or NPZ (``.npz``) file.

Layout (``format = "cm2optics-lsv"``, ``version = 1``): ``basis`` (K, J, h, w),
``coefficients`` (K, nz, ny, nx), ``grid/x_mm|y_mm|z_mm``, ``geometry/r0_poly|A_poly|o_poly|layout``,
``svd/singular_values|nmse|nmse_per_psf``, attributes ``sensor_shape``, ``pixel_um``, ``scale``,
``oversample``, ``default_grid`` (JSON) and ``provenance`` (JSON: scan, its fingerprint, build
options, geometry fit, package version, time). Version 2 adds each lenslet's best-focus surface,
``focal_surface/coefficients`` (J, 4) and ``focal_surface/rms_mm`` (J,), and the attribute
``refine`` (:mod:`cm2optics.lsv.focal_surface`); a model without a surface is written as
version 1, and a version-1 file reads without one (plain interpolation), as before. Version 3
adds the attribute ``rotate_aberrations`` (true: each lateral neighbour's PSF is turned to the
source's azimuth about the lenslet's axis before the blend, :mod:`cm2optics.lsv.rotation`); a
model without it is written as version 1 or 2, and an older file reads with it false; such a model
also keeps its turned coefficients, ``interpolation/turned_coefficients`` (J, K, nz, ny', nx'),
which take minutes to compute at full size. Version 4 adds the attribute ``warp_shapes`` (true:
neighbouring PSFs are blended by displacement interpolation, :mod:`cm2optics.lsv.warp`; its
coefficients are kept in the same array); an older file reads with it false. An NPZ file holds the same arrays under the same names
(``grid/x_mm`` …) and the attributes as one JSON string ``attrs``.

This module reads and writes the fields as plain arrays (:func:`read_lsv_model`,
:func:`write_lsv_model`); :class:`cm2optics.lsv.model.LSVModel` is built from them.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from cm2optics.formats.atomic import write_atomic
from cm2optics.formats.errors import FormatError
from cm2optics.formats.volume import VolumeGrid

__all__ = ["FORMAT", "VERSION", "ModelError", "read_lsv_model", "write_lsv_model"]

FORMAT = "cm2optics-lsv"
VERSION = 4
#: The focal surface's arrays and their paths in the file (version 2).
_SURFACE = {"coefficients": "focal_surface/coefficients", "rms_mm": "focal_surface/rms_mm"}
#: The turned coefficients' path (version 3, with ``rotate_aberrations``).
_TURNED = "interpolation/turned_coefficients"
#: Array fields and their paths in the file.
_ARRAYS = {
    "basis": "basis",
    "coefficients": "coefficients",
    "grid_x_mm": "grid/x_mm",
    "grid_y_mm": "grid/y_mm",
    "grid_z_mm": "grid/z_mm",
    "singular_values": "svd/singular_values",
    "nmse": "svd/nmse",
    "nmse_per_psf": "svd/nmse_per_psf",
}


class ModelError(FormatError):
    """A model file that cannot be used, or a request the model cannot serve."""


def json_default(value: Any) -> Any:
    """JSON for numpy scalars and arrays and paths (provenance records)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _attrs(fields: dict[str, Any]) -> dict[str, Any]:
    surface = fields.get("focal_surface") is not None
    rotate = bool(fields.get("rotate_aberrations", False))
    warp = bool(fields.get("warp_shapes", False))
    return {
        "format": FORMAT,
        "version": 4 if warp else 3 if rotate else 2 if surface else 1,
        "refine": int(fields.get("refine", 1)),
        "rotate_aberrations": rotate,
        "warp_shapes": warp,
        "sensor_shape": [int(v) for v in fields["sensor_shape"]],
        "pixel_um": float(fields["pixel_um"]),
        "scale": float(fields.get("scale", 1.0)),
        "oversample": int(fields.get("oversample", 1)),
        "default_grid": json.dumps(fields["default_grid"].to_dict()),
        "provenance": json.dumps(fields.get("provenance", {}), ensure_ascii=False, default=json_default),
    }


def write_lsv_model(path: str | Path, fields: dict[str, Any]) -> Path:
    """Write a model's fields (those of :class:`~cm2optics.lsv.model.LSVModel`, ``geometry`` as
    a mapping of arrays) atomically; ``.npz`` writes NPZ, anything else HDF5."""
    path = Path(path)
    attrs = _attrs(fields)
    arrays = {where: np.asarray(fields.get(name, np.zeros(0))) for name, where in _ARRAYS.items()}
    arrays |= {f"geometry/{k}": np.asarray(v) for k, v in fields["geometry"].items()}
    if fields.get("focal_surface") is not None:
        arrays |= {where: np.asarray(fields["focal_surface"][name]) for name, where in _SURFACE.items()}
    if (attrs["rotate_aberrations"] or attrs["warp_shapes"]) and fields.get("turned_coefficients") is not None:
        arrays[_TURNED] = np.asarray(fields["turned_coefficients"], np.float32)

    def write_h5(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            for key, value in attrs.items():
                f.attrs[key] = np.array(value) if isinstance(value, list) else value
            for where, value in arrays.items():
                options = {"compression": "gzip", "compression_opts": 4, "shuffle": True} if where == "basis" else {}
                f.create_dataset(where, data=value, **options)

    def write_npz(tmp: Path) -> None:
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, attrs=np.array(json.dumps(attrs)), **arrays)

    return write_atomic(path, write_npz if path.suffix.lower() == ".npz" else write_h5)


def _read_raw(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
        return json.loads(str(arrays.pop("attrs"))), arrays
    with h5py.File(path, "r") as f:
        attrs = dict(f.attrs)
        if attrs.get("format") != FORMAT:
            return attrs, {}
        arrays = {}
        f.visititems(lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None)
    return attrs, arrays


def read_lsv_model(path: str | Path) -> dict[str, Any]:
    """The fields of a model file (``geometry`` as a mapping of arrays); a missing, foreign,
    newer or unreadable file raises :class:`ModelError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such model file")
    try:
        attrs, arrays = _read_raw(path)
        if attrs.get("format") != FORMAT:
            raise ModelError(f"{path}: not a cm2optics LSV model (format = {attrs.get('format')!r})")
        if int(attrs.get("version", 0)) > VERSION:
            raise ModelError(
                f"{path}: model version {int(attrs['version'])} is newer than this cm2optics reads ({VERSION})"
            )
        fields: dict[str, Any] = {name: arrays[where] for name, where in _ARRAYS.items()}
        fields["geometry"] = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("geometry/")}
        fields["sensor_shape"] = tuple(int(v) for v in attrs["sensor_shape"])
        fields["pixel_um"] = float(attrs["pixel_um"])
        fields["scale"] = float(attrs.get("scale", 1.0))
        fields["oversample"] = int(attrs.get("oversample", 1))
        fields["refine"] = int(attrs.get("refine", 1))
        fields["rotate_aberrations"] = bool(attrs.get("rotate_aberrations", False))
        fields["warp_shapes"] = bool(attrs.get("warp_shapes", False))
        fields["turned_coefficients"] = arrays.get(_TURNED)
        have = [where in arrays for where in _SURFACE.values()]
        if any(have) and not all(have):
            raise ModelError(f"{path}: an incomplete focal surface ({', '.join(_SURFACE.values())})")
        fields["focal_surface"] = {name: arrays[where] for name, where in _SURFACE.items()} if all(have) else None
        fields["default_grid"] = VolumeGrid.from_dict(json.loads(attrs["default_grid"]))
        fields["provenance"] = json.loads(attrs.get("provenance", "{}"))
        return fields
    except ModelError:
        raise
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as error:
        raise ModelError(f"{path}: not a readable LSV model ({error})") from None

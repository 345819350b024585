"""The PSF stack file of a depth-wise shift-invariant (LSI) model: one HDF5 file.

Layout (``format = "cm2optics-psf-stack"``, ``version = 1``): ``patches`` (J, nz, h, w) the PSF
patch of each lenslet at each depth, ``origins`` (J, nz, 2) their integer sensor (row, col),
``centre_rays`` (J, 2); attributes ``grid`` (JSON of a :class:`VolumeGrid`), ``sensor_shape``,
``flip`` (rows, cols) and ``meta`` (JSON). :class:`cm2optics.lsv.lsi.DepthwiseConvOperator`
is built from the fields.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from cm2optics.formats.atomic import write_atomic
from cm2optics.formats.errors import FormatError
from cm2optics.formats.volume import VolumeGrid

__all__ = ["PSF_STACK_FORMAT", "PSFStackError", "read_psf_stack", "write_psf_stack"]

PSF_STACK_FORMAT = "cm2optics-psf-stack"


class PSFStackError(FormatError):
    """A PSF stack file that cannot be used."""


def write_psf_stack(
    path: str | Path,
    patches: np.ndarray,
    origins: np.ndarray,
    grid: VolumeGrid,
    sensor_shape: tuple[int, int],
    flip: tuple[bool, bool],
    centre_rays: np.ndarray,
    meta: dict[str, Any],
) -> Path:
    """Write a PSF stack atomically."""

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = PSF_STACK_FORMAT
            f.attrs["version"] = 1
            f.attrs["grid"] = json.dumps(grid.to_dict())
            f.attrs["sensor_shape"] = np.array(sensor_shape)
            f.attrs["flip"] = np.array(flip)
            f.attrs["meta"] = json.dumps(meta)
            f.create_dataset("patches", data=patches, compression="gzip", shuffle=True, track_times=False)
            f.create_dataset("origins", data=origins, track_times=False)
            f.create_dataset("centre_rays", data=centre_rays, track_times=False)

    return write_atomic(Path(path), write)


def read_psf_stack(path: str | Path) -> dict[str, Any]:
    """The fields of a PSF stack (the arguments of :func:`write_psf_stack`, less ``path``)."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != PSF_STACK_FORMAT:
                raise PSFStackError(f"{path}: not a cm2optics PSF stack (format = {f.attrs.get('format')!r})")
            return {
                "patches": f["patches"][()],
                "origins": f["origins"][()],
                "grid": VolumeGrid.from_dict(json.loads(f.attrs["grid"])),
                "sensor_shape": tuple(int(v) for v in f.attrs["sensor_shape"]),
                "flip": tuple(bool(v) for v in f.attrs["flip"]),
                "centre_rays": f["centre_rays"][()],
                "meta": json.loads(f.attrs.get("meta", "{}")),
            }
    except (OSError, KeyError) as error:
        raise PSFStackError(f"{path}: not a readable PSF stack ({error})") from None

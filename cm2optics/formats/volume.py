"""Volumes on disk, shared by every stage (no torch here).

- A volume is a ``(z, y, x)`` array in a TIFF with ImageJ spacing metadata (opens in Fiji and
  napari) or a ``.npy`` file. Voxel ``(iz, iy, ix)`` sits at ``x = (ix − (nx−1)/2)·dx`` (same for
  y) and ``z = (iz − (nz−1)/2)·dz``: centred on the optical axis and the nominal focal plane,
  ``iz`` increasing towards the device (+z). A ``.npy`` file carries no spacing: the caller
  supplies it (or takes a model's default grid).

Every write is atomic (:func:`cm2optics.formats.atomic.write_atomic`); every reader raises
:class:`VolumeError` (a ``ValueError``) with one clear message for bad input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from cm2optics.formats.atomic import write_atomic
from cm2optics.formats.errors import FormatError

__all__ = ["VolumeError", "VolumeGrid", "read_volume", "write_volume"]


class VolumeError(FormatError):
    """A volume or emitter file that cannot be used; the message says what and where."""


@dataclass(frozen=True)
class VolumeGrid:
    """A regular voxel grid centred on the optical axis and the nominal focal plane.

    shape: voxels along (z, y, x).
    voxel_um: voxel pitch along (z, y, x), µm.
    """

    shape: tuple[int, int, int]
    voxel_um: tuple[float, float, float]

    def __post_init__(self) -> None:
        shape = tuple(int(n) for n in self.shape)
        voxel = tuple(float(v) for v in self.voxel_um)
        if len(shape) != 3 or any(n < 1 for n in shape):
            raise VolumeError(f"grid shape = {self.shape!r}: must be three integers ≥ 1 (z, y, x)")
        if len(voxel) != 3 or not all(math.isfinite(v) and v > 0 for v in voxel):
            raise VolumeError(f"voxel_um = {self.voxel_um!r}: must be three finite numbers > 0 (z, y, x), µm")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "voxel_um", voxel)

    def axis_um(self, axis: int) -> np.ndarray:
        """Physical coordinates (µm) of the voxel centres along ``axis`` (0: z, 1: y, 2: x)."""
        n = self.shape[axis]
        return (np.arange(n) - (n - 1) / 2.0) * self.voxel_um[axis]

    def axis_mm(self, axis: int) -> np.ndarray:
        return self.axis_um(axis) / 1000.0

    @property
    def extent_um(self) -> tuple[float, float, float]:
        """Distance between the outermost voxel centres along (z, y, x), µm."""
        return tuple((n - 1) * v for n, v in zip(self.shape, self.voxel_um, strict=True))  # type: ignore[return-value]

    def to_dict(self) -> dict:
        return {"shape": list(self.shape), "voxel_um": list(self.voxel_um)}

    @classmethod
    def from_dict(cls, data: dict) -> VolumeGrid:
        return cls(tuple(data["shape"]), tuple(data["voxel_um"]))  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- volumes


def read_volume(
    path: str | Path, voxel_um: tuple[float, float, float] | None = None, *, require_3d: bool = False
) -> tuple[np.ndarray, VolumeGrid]:
    """Read a ``(z, y, x)`` volume (TIFF or ``.npy``) as float32 with its grid.

    ``voxel_um`` (z, y, x in µm) overrides the file's spacing; a ``.npy`` file (no spacing) or a
    TIFF without ImageJ spacing needs it. A 2-D image is read as one plane, unless
    ``require_3d`` (a reconstruction is always 3-D: a 2-D file is likely a raw measurement). Raises :class:`VolumeError` for a missing or unreadable
    file, a wrong number of dimensions, NaN/inf or negative values.
    """
    path = Path(path)
    if not path.is_file():
        raise VolumeError(f"{path}: no such volume file")
    spacing: tuple[float, float, float] | None = None
    if path.suffix.lower() == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except Exception as error:  # numpy raises several types for corrupt files
            raise VolumeError(f"{path}: not a readable .npy file ({error})") from None
    elif path.suffix.lower() in (".tif", ".tiff"):
        try:
            with tifffile.TiffFile(path) as tif:
                data = tif.asarray()
                spacing = _tiff_spacing(tif)
        except VolumeError:
            raise
        except Exception as error:  # tifffile raises many types for corrupt files
            raise VolumeError(f"{path}: not a readable TIFF ({error})") from None
    else:
        raise VolumeError(f"{path}: unknown volume format {path.suffix!r} (use .tif or .npy)")
    if data.ndim == 2 and require_3d and spacing is None:  # a one-plane volume keeps its ImageJ spacing
        raise VolumeError(
            f"{path}: a 2-D image of shape {data.shape}, not a 3-D volume (z, y, x): a reconstruction must be a volume "
            "(is this the raw measurement?)"
        )
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3:
        raise VolumeError(f"{path}: a volume must have 3 dimensions (z, y, x), found shape {data.shape}")
    if not np.issubdtype(data.dtype, np.number) or np.iscomplexobj(data):
        raise VolumeError(f"{path}: voxel values must be real numbers (found {data.dtype})")
    data = np.ascontiguousarray(data, dtype=np.float32)
    if not np.all(np.isfinite(data)):
        raise VolumeError(f"{path}: contains {int(np.sum(~np.isfinite(data)))} NaN or infinite voxels")
    if data.size and float(data.min()) < 0:
        raise VolumeError(
            f"{path}: contains negative values (min {float(data.min()):.4g}); a fluorescence volume is ≥ 0"
        )
    if voxel_um is not None:
        spacing = tuple(float(v) for v in voxel_um)  # type: ignore[assignment]
    if spacing is None:
        raise VolumeError(
            f"{path}: no voxel spacing in the file; give it (z, y, x in µm), e.g. --voxel-um 10,4.15,4.15"
        )
    return data, VolumeGrid(data.shape, spacing)  # type: ignore[arg-type]


def _tiff_spacing(tif: tifffile.TiffFile) -> tuple[float, float, float] | None:
    meta = tif.imagej_metadata or {}
    page = tif.pages[0]
    try:
        xres = page.tags["XResolution"].value
        yres = page.tags["YResolution"].value
    except KeyError:
        return None
    if "spacing" not in meta:
        return None
    unit = str(meta.get("unit", "micron")).lower()
    scale = {"micron": 1.0, "um": 1.0, "µm": 1.0, "\\u00b5m": 1.0, "mm": 1000.0, "nm": 1e-3}.get(unit)
    if scale is None:
        raise VolumeError(f"{tif.filehandle.path}: unknown spacing unit {unit!r} (use micron)")
    dx = xres[1] / xres[0] if xres[0] else 0.0
    dy = yres[1] / yres[0] if yres[0] else 0.0
    dz = float(meta["spacing"])
    return (dz * scale, dy * scale, dx * scale)


def write_volume(path: str | Path, volume: np.ndarray, voxel_um: tuple[float, float, float]) -> Path:
    """Write a ``(z, y, x)`` volume as an ImageJ TIFF (float32, spacing in µm) or ``.npy``."""
    path = Path(path)
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise VolumeError(f"a volume must have 3 dimensions (z, y, x), got shape {volume.shape}")
    grid = VolumeGrid(volume.shape, voxel_um)  # validates the spacing
    dz, dy, dx = grid.voxel_um
    if path.suffix.lower() == ".npy":
        return write_atomic(path, lambda tmp: _save_npy(tmp, volume.astype(np.float32)))
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise VolumeError(f"{path}: unknown volume format {path.suffix!r} (use .tif or .npy)")
    data = np.ascontiguousarray(volume, dtype=np.float32)
    return write_atomic(
        path,
        lambda tmp: tifffile.imwrite(
            tmp,
            data,
            imagej=True,
            resolution=(1.0 / dx, 1.0 / dy),
            metadata={"spacing": dz, "unit": "micron", "axes": "ZYX"},
        ),
    )


def _save_npy(tmp: Path, array: np.ndarray) -> None:
    with open(tmp, "wb") as handle:
        np.save(handle, array, allow_pickle=False)

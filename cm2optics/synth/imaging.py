"""What the synthesiser needs from a forward model, for an LSV model and for any operator.

:class:`Imaging` wraps either an :class:`~cm2optics.lsv.model.LSVModel` (images of emitters
straight from the model with ``forward_sparse``, or of the rasterised volume through its
operator) or an operator of :class:`~cm2optics.formats.operator.VolumeOperator` with
``forward(volume, per_lenslet=True)`` and ``chief_rays_px()`` (the depth-wise LSI operator, a
test's analytic operator). It gives the per-lenslet (crosstalk-free) images — their sum is the
measurement — the chief rays of the nine views, and the in-focus mapping of voxels onto pixels.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.models import load_forward_model
from cm2optics.formats.volume import VolumeGrid

__all__ = ["Imaging", "load_imaging"]


class Imaging:
    """source: an LSV model or an operator; grid: the volume grid; render: auto | sparse | volume."""

    def __init__(self, source: Any, grid: VolumeGrid, render: str = "auto"):
        self.source = source
        self.grid = grid
        self.is_model = hasattr(source, "forward_sparse") and hasattr(source, "geometry")
        if render == "auto":
            render = "sparse" if self.is_model else "volume"
        if render == "sparse" and not self.is_model:
            raise ValueError("render = 'sparse' needs an LSV model (an operator images volumes only)")
        self.render = render
        if not self.is_model:
            if tuple(source.grid.shape) != tuple(grid.shape) or not np.allclose(source.grid.voxel_um, grid.voxel_um):
                raise ValueError(
                    f"the operator is defined on a {source.grid.shape} grid of {source.grid.voxel_um} µm voxels; "
                    f"the synthetic volumes need {grid.shape} of {grid.voxel_um} µm"
                )
        self._operator = None

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return tuple(int(v) for v in self.source.sensor_shape)  # type: ignore[return-value]

    @property
    def n_lenslets(self) -> int:
        return int(self.source.n_lenslets)

    @property
    def needs_volume(self) -> bool:
        return self.render == "volume"

    def operator(self) -> Any:
        if self._operator is None:
            self._operator = self.source.operator(self.grid) if self.is_model else self.source
        return self._operator

    def per_lenslet(self, emitters: Emitters, volume: np.ndarray | None) -> np.ndarray:
        """(J, H, W) float32 crosstalk-free images of the sample (model units)."""
        return self.image(emitters, volume, per_lenslet=True)

    def image(self, emitters: Emitters, volume: np.ndarray | None, *, per_lenslet: bool = False) -> np.ndarray:
        """The sample's image (H, W), or its J crosstalk-free images (J, H, W), float32, model units."""
        if self.render == "sparse":
            return np.asarray(self.source.forward_sparse(emitters, per_lenslet=per_lenslet), dtype=np.float32)
        if volume is None:
            raise ValueError("render = 'volume' needs the rasterised volume")
        out = self.operator().forward(volume, per_lenslet=per_lenslet)
        return np.asarray(out.numpy() if hasattr(out, "numpy") else out, dtype=np.float32)

    def chief_rays_px(self) -> np.ndarray:
        """(J, 2) sensor (row, col) of each lenslet's image of the centre of the focal plane."""
        if self.is_model:
            return np.asarray(self.source.geometry.focus(0.0, 0.0, 0.0), float).reshape(-1, 2)
        return np.asarray(self.source.chief_rays_px(), float).reshape(-1, 2)

    def pixels_per_voxel(self) -> np.ndarray | None:
        """(rows per iy, cols per ix) at the focal plane, signed (negative: inverted), or None when
        the mapping rotates (then no volume patches can be aligned with the views)."""
        if self.is_model:
            A0 = np.asarray(self.source.geometry.A(0.0), float)  # rows (row, col), columns (x, y), px/mm
            dy, dx = self.grid.voxel_um[1] / 1000.0, self.grid.voxel_um[2] / 1000.0
            main = np.array([A0[0, 1] * dy, A0[1, 0] * dx])
            cross = abs(A0[0, 0] * dx) + abs(A0[1, 1] * dy)
            return main if cross < 0.02 * float(np.abs(main).min()) else None
        flip = getattr(self.source, "flip", (True, True))
        return np.array([-1.0 if flip[0] else 1.0, -1.0 if flip[1] else 1.0])


@functools.lru_cache(maxsize=2)
def _load_cached(path: str, mtime: float, grid_key: tuple, render: str) -> Imaging:
    grid = VolumeGrid(grid_key[0], grid_key[1])
    return Imaging(load_forward_model(path), grid, render)


def load_imaging(path: str | Path, grid: VolumeGrid, render: str = "auto") -> Imaging:
    """The :class:`Imaging` of a model file (cached per process: Dask workers load it once)."""
    path = str(Path(path).resolve())
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such model file")
    return _load_cached(path, os.path.getmtime(path), (grid.shape, grid.voxel_um), render)

"""Shared fixtures of the LSV tests."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.lsv.build import model_from_crops


@pytest.fixture(scope="session")
def grid_toy():
    """Factory: ``make(psf, axes, geometry, oversample)`` → (model, crops, grid_index), a full-rank
    one-lenslet model of the fine PSFs ``psf(x, y, z)`` → (1, h·S, w·S) at every node of ``axes``
    (x, y, z mm) on a 400 × 420 sensor of 5-µm pixels."""

    def make(psf, axes, geometry, oversample):
        xs, ys, zs = axes
        positions = [(x, y, z) for z in zs for y in ys for x in xs]
        grid_index = np.array([[ix, iy, iz] for iz in range(len(zs)) for iy in range(len(ys)) for ix in range(len(xs))])
        crops = np.stack([psf(*p) for p in positions])
        model, _ = model_from_crops(
            crops,
            grid_index,
            axes,
            geometry,
            rank=len(crops),
            sensor_shape=(400, 420),
            pixel_um=5.0,
            axial_um=100.0,
            trim=None,
            oversample=oversample,
        )
        return model, crops, grid_index

    return make

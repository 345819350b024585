"""Tilted parts: the one convention for the as-built tilts of the lenslet array and the sensor.

A part tilted by (θx, θy) degrees is turned right-handedly about the x axis by θx, then about the
y axis by θy, about its pivot: ``R = R_y(θy)·R_x(θx)``. Its own axes are R's columns; a point
at (x, y) of a tilted plane through the pivot sits ``z ≈ y·sin θx − x·sin θy`` above it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["rotate", "tilt_matrix"]


def tilt_matrix(tilt_x_deg: float, tilt_y_deg: float) -> np.ndarray:
    """3 × 3 rotation ``R_y(θy)·R_x(θx)``: columns are the tilted part's x, y and normal axes."""
    ax, ay = math.radians(tilt_x_deg), math.radians(tilt_y_deg)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(ax), -math.sin(ax)], [0.0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0.0, math.sin(ay)], [0.0, 1.0, 0.0], [-math.sin(ay), 0.0, math.cos(ay)]])
    return ry @ rx


def rotate(
    rotation: tuple[tuple[float, float, float], ...] | np.ndarray,
    x: Any,
    y: Any,
    z: Any,
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0),
    inverse: bool = False,
) -> tuple[Any, Any, Any]:
    """(x, y, z) (NumPy or Dr.Jit arrays, or floats) turned by ``rotation`` (R; its transpose
    with ``inverse``) about ``pivot`` (mm): a tilted part's own frame to the device frame, or
    back (directions: pivot 0)."""
    r = [[float(v) for v in row] for row in rotation]
    if inverse:
        r = [list(col) for col in zip(*r, strict=True)]
    a, b, c = x - pivot[0], y - pivot[1], z - pivot[2]
    return tuple(r[i][0] * a + r[i][1] * b + r[i][2] * c + pivot[i] for i in range(3))

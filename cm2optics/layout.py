"""Where things sit in the device frame: poses of the LED units and of the imaging stack.

Pure NumPy so that CAD, ray tracing and analysis share one placement. Device frame:
origin on the sensor surface, +z towards the sample (see :mod:`cm2optics.design`).

LED frame (one per unit): origin at the centre of the LED's emitting surface, +z along the
unit's axis (the direction the light leaves in), +x tangential (counter-clockwise seen from
the sample side), +y = z × x. The LED package lies at z ≤ 0, the collimator and filter at z > 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.design import SystemDesign


@dataclass(frozen=True)
class Pose:
    """A rigid placement: ``matrix`` (4×4) maps local homogeneous points to the device frame."""

    matrix: np.ndarray

    @property
    def origin_mm(self) -> np.ndarray:
        return self.matrix[:3, 3].copy()

    @property
    def axis(self) -> np.ndarray:
        """The local +z axis in the device frame (unit vector)."""
        return self.matrix[:3, 2].copy()

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        """Map local points (…, 3) in mm to the device frame."""
        points = np.asarray(points_mm, dtype=float)
        return points @ self.matrix[:3, :3].T + self.matrix[:3, 3]


def led_poses(design: SystemDesign) -> list[Pose]:
    """Pose of every LED unit, aimed at the centre of the nominal focal plane."""
    arr = design.led_array
    target = np.array([0.0, 0.0, design.object_plane_z_mm])
    poses = []
    for i in range(arr.count):
        phi = math.radians(arr.azimuth_deg) + 2.0 * math.pi * i / arr.count
        origin = np.array([arr.offset_mm * math.cos(phi), arr.offset_mm * math.sin(phi), design.led_height_mm])
        z_axis = target - origin
        z_axis /= np.linalg.norm(z_axis)
        x_axis = np.array([-math.sin(phi), math.cos(phi), 0.0])
        y_axis = np.cross(z_axis, x_axis)
        matrix = np.eye(4)
        matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x_axis, y_axis, z_axis, origin
        poses.append(Pose(matrix))
    return poses

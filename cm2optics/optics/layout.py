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
from cm2optics.optics import first_order


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
    """Pose of every LED unit, its axis aimed at the centre of the nominal focal plane and its
    aperture (excitation filter's lower face) ``led_array.offset_mm`` off the optical axis."""
    arr = design.led_array
    tilt = math.radians(arr.tilt_deg)
    aperture_z = first_order.object_plane_z_mm(design) - (arr.offset_mm / math.tan(tilt) if tilt > 0 else 10.0)
    poses = []
    for i in range(arr.count):
        phi = math.radians(arr.azimuth_deg) + 2.0 * math.pi * i / arr.count
        radial = np.array([math.cos(phi), math.sin(phi), 0.0])
        z_axis = -math.sin(tilt) * radial + np.array([0.0, 0.0, math.cos(tilt)])
        origin = arr.offset_mm * radial + np.array([0.0, 0.0, aperture_z]) - arr.excitation_gap_mm * z_axis
        x_axis = np.array([-math.sin(phi), math.cos(phi), 0.0])
        y_axis = np.cross(z_axis, x_axis)
        matrix = np.eye(4)
        matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x_axis, y_axis, z_axis, origin
        poses.append(Pose(matrix))
    return poses


@dataclass(frozen=True)
class HousingEnvelope:
    """Outer envelope of the MLA housing in the device frame (mm): a square base flange that
    stands on the sensor board (a skirt around the sensor package and standoffs at the screw
    holes below a plate just above the sensor surface) and a square tower around the optics,
    open at the top. Other parts may rest on the flange's top face."""

    flange_side_mm: float
    flange_bottom_z_mm: float
    flange_top_z_mm: float
    tower_side_mm: float
    tower_top_z_mm: float
    tower_chamfer_mm: float


def mla_housing_envelope(design: SystemDesign) -> HousingEnvelope:
    """Envelope that every other printed part must keep clear of."""
    return HousingEnvelope(
        flange_side_mm=design.sensor_board.size_mm,
        flange_bottom_z_mm=-design.sensor.package_height_mm,
        flange_top_z_mm=design.mechanics.clearance_mm + design.mla_housing.flange_mm,
        tower_side_mm=design.mla_housing.outer_mm,
        tower_top_z_mm=design.emission_filter_z_mm + design.emission_filter.thickness_mm,
        tower_chamfer_mm=design.mla_housing.chamfer_mm,
    )

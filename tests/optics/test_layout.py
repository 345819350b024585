"""The LED units' poses: the aperture ``offset_mm`` off the axis, the axis tilted by ``tilt_deg``
and meeting the focal plane at the aim point."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.optics import first_order
from cm2optics.optics.layout import led_poses


@pytest.mark.parametrize("aim_mm", [0.0, 2.0, -1.5])
def test_each_axis_meets_the_focal_plane_at_its_aim_point(v2, aim_mm):
    design = v2.with_changes({"led_array.aim_mm": aim_mm, "led_array.tilt_deg": 40.0, "led_array.azimuth_deg": 10.0})
    z_plane = first_order.object_plane_z_mm(design)
    gap = design.led_array.excitation_gap_mm
    for i, pose in enumerate(led_poses(design)):
        phi = math.radians(10.0 + 90.0 * i)
        radial = np.array([math.cos(phi), math.sin(phi), 0.0])
        aperture = pose.apply(np.array([0.0, 0.0, gap]))
        assert np.hypot(*aperture[:2]) == pytest.approx(design.led_array.offset_mm)
        assert math.degrees(math.acos(pose.axis[2])) == pytest.approx(40.0)
        hit = aperture + (z_plane - aperture[2]) / pose.axis[2] * pose.axis
        assert hit[:2] == pytest.approx(aim_mm * radial[:2], abs=1e-9)
        assert np.allclose(pose.matrix[:3, :3].T @ pose.matrix[:3, :3], np.eye(3))


def test_aiming_past_the_centre_raises_the_units(v2):
    """The same tilt and offset with the aim point moved past the centre: a longer run to the
    plane, so the aperture sits lower (further from the sample) by Δaim / tan(tilt)."""
    base = led_poses(v2)[0].origin_mm[2]
    aimed = led_poses(v2.with_changes({"led_array.aim_mm": -1.0}))[0].origin_mm[2]
    shift = v2.led_array.aim_mm + 1.0
    assert base - aimed == pytest.approx(shift / math.tan(math.radians(v2.led_array.tilt_deg)))


def _cube(centre_x: float, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A unit cube at (centre_x, 0, 0) turned by angle_deg about z: corners and axes (rows)."""
    from cm2optics.optics.layout import Pose, _box_corners

    a = math.radians(angle_deg)
    m = np.eye(4)
    m[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    m[0, 3] = centre_x
    return _box_corners(Pose(m), 0.5, -0.5, 0.5), m[:3, :3].T


@pytest.mark.parametrize(
    ("x", "angle", "overlap"),
    [(0.9, 0.0, True), (1.1, 0.0, False), (1.1, 45.0, True), (1.3, 45.0, False)],  # 45°: reaches 0.5 + √2/2
)
def test_separating_axis_test_on_cubes(x, angle, overlap):
    from cm2optics.optics.layout import _convex_overlap

    a, a_axes = _cube(0.0, 0.0)
    b, b_axes = _cube(x, angle)
    assert _convex_overlap(a, a_axes, b, b_axes) is overlap


def test_unit_clashes_pass_the_preset_and_catch_units_in_the_tower(v2, v2_collimating):
    from cm2optics.optics.layout import unit_clashes

    assert unit_clashes(v2) == [] and unit_clashes(v2_collimating) == []
    # At 45° / 6.7 mm, aimed past the centre: lower, into the tower.
    low = v2_collimating.with_changes({"led_array.aim_mm": -2.0})
    assert any("enters the imaging tower" in line for line in unit_clashes(low))
    crowded = v2_collimating.with_changes({"led_array.offset_mm": 5.5, "led_array.tilt_deg": 55.0})
    assert any("overlap" in line for line in unit_clashes(crowded))


def test_dome_rim_lies_on_the_inner_face_under_each_unit(v2):
    """The height where the dome meets the tower: the point on the tower's side (plus clearance)
    at that height lies on the plane of the dome's inner face, parallel to the unit's inner side
    and half the socket's width + clearance + 1.5 × the plate's thickness from the LED's axis."""
    from cm2optics.optics.layout import dome_rim_z_mm, mla_housing_envelope, unit_clashes

    meets, top = dome_rim_z_mm(v2)
    c, t = v2.mechanics.clearance_mm, v2.base_plate.thickness_mm
    pose = led_poses(v2)[0]
    radial = pose.origin_mm[:2] / np.linalg.norm(pose.origin_mm[:2])
    hole = mla_housing_envelope(v2).tower_side_mm / 2 + c
    point = np.array([*(hole * radial), meets])
    assert (point - pose.origin_mm) @ pose.matrix[:3, 1] == pytest.approx(v2.led_housing.outer_mm / 2 + c + 1.5 * t)
    tilt = math.radians(v2.led_array.tilt_deg)
    assert top - meets == pytest.approx(t / (math.cos(tilt) + math.sin(tilt)))
    far = v2.with_changes({"led_array.offset_mm": 10.3, "led_array.aim_mm": 2.3, "led_array.tilt_deg": 50.8})
    assert any("dome" in line for line in unit_clashes(far))

"""Conversions between :class:`cm2optics.optics.layout.Pose` and CadQuery placements."""

from __future__ import annotations

import cadquery as cq
from OCP.gp import gp_Trsf

from cm2optics.optics.layout import Pose


def location_from_pose(pose: Pose) -> cq.Location:
    """CadQuery location that maps a part's local frame to the device frame."""
    trsf = gp_Trsf()
    m = pose.matrix
    trsf.SetValues(*m[0, :4], *m[1, :4], *m[2, :4])
    return cq.Location(trsf)


def place(part: cq.Workplane, pose: Pose) -> cq.Workplane:
    """``part`` (one solid in its local frame) moved to ``pose`` in the device frame."""
    return cq.Workplane().add(part.val().moved(location_from_pose(pose)))

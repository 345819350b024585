"""The printed base plate: a dome over the MLA housing that holds the LED units.

Device frame (origin on the sensor surface, +z towards the sample). The plate is built where
it sits; it has three features:

* **dome** — a shell ``base_plate.thickness_mm`` thick, a pyramid with one face per LED unit
  (a hip roof for the four units of CM²): each face is parallel to its unit's inner side
  (the housing's ``+y`` face, tilted by ``led_array.tilt_deg``) and lies under it, so the
  units stand on the dome. It rests on the MLA housing's flange and rises to meet the tower's
  sides, which it surrounds with ``mechanics.clearance_mm`` along a vertical land; its top
  and bottom rims are cut square (a vertical land and a horizontal face of equal width,
  ``thickness / (cos tilt + sin tilt)``), so the shell has no knife edges. Between the units
  it closes the space around the tower against side light;
* **sockets** — one per :func:`cm2optics.optics.layout.led_poses` entry, in that unit's LED frame:
  a cup ``base_plate.socket_depth_mm`` deep around the housing's back (clearance on every
  side; walls and a floor ``mechanics.wall_mm`` thick, the floor with a hole for the LED's
  leads) whose outer back edge is chamfered to keep the plate compact;
* **rails** — each socket carries the rail of :class:`cm2optics.cad.led_housing.LEDHousingLayout`,
  extended through the socket's ``+x`` wall and into its floor: it enters the housing's
  loading window as the housing slides into the socket and locates the LED, the collimator
  flange and the excitation filter on their ``+x`` sides.

The space each housing sweeps as it slides in along its axis is cut out, so nothing of the
plate stands in front of a unit. The dome lies below the tower's top; sockets and rails end
behind each unit's lip and outside the light from the units' apertures to the field and from
the field down to the emission filter.
"""

from __future__ import annotations

import math

import cadquery as cq

from cm2optics.cad.fits import Fit
from cm2optics.cad.led_housing import THROUGH_MM, Box, LEDHousingLayout, bore_solid, led_housing_layout
from cm2optics.cad.placement import place
from cm2optics.design import DesignError, SystemDesign
from cm2optics.optics.layout import dome_rim_z_mm, led_poses, mla_housing_envelope

#: How far the space swept by a housing sliding into its socket is cut out in front of it, mm.
SWEEP_MM = 30.0


def _polygon_prism(design: SystemDesign, apothems: list[float], heights: list[float]) -> cq.Workplane:
    """Ruled solid through regular polygons (one side facing each LED unit) of the given
    ``apothems`` (mm) at the given ``heights`` (mm)."""
    arr = design.led_array
    n = arr.count
    angles = [math.radians(arr.azimuth_deg) + (2 * i + 1) * math.pi / n for i in range(n)]
    wires = [
        cq.Wire.makePolygon(
            [
                cq.Vector(a / math.cos(math.pi / n) * math.cos(t), a / math.cos(math.pi / n) * math.sin(t), z)
                for t in angles
            ],
            close=True,
        )
        for a, z in zip(apothems, heights, strict=True)
    ]
    return cq.Workplane().add(cq.Solid.makeLoft(wires, ruled=True))


def _dome(design: SystemDesign, layout: LEDHousingLayout) -> cq.Workplane:
    """The pyramidal shell: its faces ``thickness_mm`` thick under the units, its bottom on
    the flange, its top rim around the tower (see the module docstring)."""
    arr, t, c = design.led_array, design.base_plate.thickness_mm, design.mechanics.clearance_mm
    if arr.count < 3:
        raise DesignError(
            "led_array.count", arr.count, "the base plate's dome has one face per LED unit: needs ≥ 3 units"
        )
    env = mla_housing_envelope(design)
    cos_t, sin_t = math.cos(math.radians(arr.tilt_deg)), math.sin(math.radians(arr.tilt_deg))
    pose = led_poses(design)[0]
    # Plane y_local = k of unit 0's LED frame: radial · cos + z · sin = reach − k (all units alike).
    reach = float(-pose.origin_mm @ pose.matrix[:3, 1])
    socket = layout.half_mm + c
    k_outer, k_inner = socket + t / 2, socket + 3 * t / 2

    def apothem(z: float, k: float) -> float:
        return (reach - k - z * sin_t) / cos_t

    land = t / (cos_t + sin_t)
    hole = env.tower_side_mm / 2 + c
    bottom = env.flange_top_z_mm
    meets_tower, top = dome_rim_z_mm(design)
    if not (bottom < meets_tower and top < env.tower_top_z_mm):
        raise DesignError(
            "led_array.tilt_deg",
            arr.tilt_deg,
            f"the dome under the units must meet the tower's side between the flange ({bottom:g} mm) and the "
            f"tower's top ({env.tower_top_z_mm:g} mm); it would meet it at {meets_tower:.3f}–{top:.3f} mm",
        )
    outer = _polygon_prism(design, [apothem(bottom, k_outer), apothem(top, k_outer)], [bottom, top])
    below, above = bottom - THROUGH_MM, top + THROUGH_MM
    inner = _polygon_prism(design, [apothem(below, k_inner), apothem(above, k_inner)], [below, above])
    foot = apothem(bottom, k_inner) + land
    feet = _polygon_prism(design, [foot, foot], [below, above])
    tower = Box(-hole, hole, -hole, hole, below, above)
    return outer.intersect(feet).cut(inner).cut(tower.solid())


def _socket(design: SystemDesign, layout: LEDHousingLayout) -> cq.Workplane:
    """One socket block in the LED frame, before the housing's room is cut out of it: a box
    ``mechanics.wall_mm`` wider than the socket on every side and behind it, its outer back
    edge chamfered by as much."""
    t, c = design.mechanics.wall_mm, design.mechanics.clearance_mm
    side = layout.half_mm + c + t
    z0, z1 = layout.back_z_mm - c - t, layout.back_z_mm + design.base_plate.socket_depth_mm
    # On "YZ", local (x, y) is global (y, z) and the extrusion runs along +x.
    profile = [(-side + t, z0), (side, z0), (side, z1), (-side, z1), (-side, z0 + t)]
    return cq.Workplane("YZ").polyline(profile).close().extrude(2 * side).translate((-side, 0, 0))


def _rail(design: SystemDesign, layout: LEDHousingLayout) -> cq.Workplane:
    """The rail in the LED frame: its steps run out through the socket's +x wall and back
    into the floor; the collimator's bore is cut out of it."""
    t, c = design.mechanics.wall_mm, design.mechanics.clearance_mm
    rail = None
    for step in layout.rails:
        box = Box(step.x0, layout.half_mm + c + t, step.y0, step.y1, layout.back_z_mm - c - t / 2, step.z1).solid()
        rail = box if rail is None else rail.union(box)
    if layout.bore_radius_mm is not None:
        rail = rail.cut(bore_solid(layout, THROUGH_MM))
    return rail


def build_base_plate(design: SystemDesign) -> cq.Workplane:
    """The base plate of ``design`` as one solid in the device frame."""
    layout = led_housing_layout(design)
    t, c = design.mechanics.wall_mm, design.mechanics.clearance_mm
    poses = led_poses(design)
    socket, rail = _socket(design, layout), _rail(design, layout)
    half = layout.half_mm + c
    back = layout.back_z_mm - c
    swept = Box(-half, half, -half, half, back, back + SWEEP_MM).solid()
    slot = layout.lead_slot
    leads = Box(slot.x0, slot.x1, slot.y0, slot.y1, back - t - THROUGH_MM, back + THROUGH_MM).solid()
    plate = _dome(design, layout)
    for pose in poses:
        plate = plate.union(place(socket, pose))
    for pose in poses:
        plate = plate.cut(place(swept, pose)).cut(place(leads, pose))
    for pose in poses:
        plate = plate.union(place(rail, pose))
    solids = plate.solids().vals()
    if len(solids) != 1 or not solids[0].isValid():
        raise RuntimeError(f"the base plate did not build as one valid solid ({len(solids)} solids)")
    return cq.Workplane().add(solids[0])


def base_plate_fits(design: SystemDesign) -> list[Fit]:
    """Clearance per side (mm): each LED housing in its socket, each unit's parts against its
    rail (the smallest of the LED's, flange's and filter's ``+x`` sides, the rail's sides in
    the window and its front end under the lip), and the plate around the MLA housing's tower."""
    layout = led_housing_layout(design)
    c = design.mechanics.clearance_mm
    led, filt, col = design.led, design.excitation_filter, design.collimator
    lower, upper = layout.rails
    window = layout.windows[0]
    above = [filt.width_mm / 2] + ([col.footprint_mm / 2] if col is not None else [])
    rail = min(
        lower.x0 - led.package_width_mm / 2,
        upper.x0 - max(above),
        window.y1 - lower.y1,
        lower.x0 - window.x0,
        layout.filter_seat.z1 - upper.z1,
    )
    socket = (layout.half_mm + c) - design.led_housing.outer_mm / 2
    fits = []
    for i in range(1, design.led_array.count + 1):
        fits += [
            Fit(f"LED housing {i}", f"base-plate socket {i}", socket),
            Fit(f"LED unit {i} parts (+x sides)", f"rail {i}", rail),
        ]
    tower = mla_housing_envelope(design).tower_side_mm / 2
    fits.append(Fit("MLA housing tower", "base-plate opening", (tower + c) - tower))
    return fits

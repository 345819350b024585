"""The printed MLA housing: holds the imaging optics over the sensor and screws to its board.

Device frame (origin on the sensor surface, +z towards the sample). From the board up:
a skirt around the sensor package and four standoffs at the screw holes stand on the PCB;
a plate (the flange, ``mla_housing.flange_mm`` thick) just above the sensor covers the skirt
and reaches the standoffs with four diagonal arms (a full board-sized plate would triple the
part's weight);
a square tower rises from it around a stepped bore:

=====================  ===========================================================
sensor cone            lofted from the sensor's active area to the film seat
film seat              absorption film, pressed in from the sensor side (glue dots)
spacer                 between film and MLA, ``lip_mm`` narrower than the film (its ledge):
                       wide enough for every ray of the 8-mm field (the film is sized for it)
MLA seat               the diced MLA, pushed in from the sensor side, flat face down, up against
                       four corner tabs that reach ``lip_mm`` over its corners; a drop of black
                       glue in the seat's corners holds it (and darkens its diced sides)
mask seat              the aperture mask on the ledge above the MLA seat (and the tabs)
filter seat            the emission filter, flush with the top of the tower
=====================  ===========================================================

Every seat is its part plus ``mechanics.clearance_mm`` per side; the tower's top outer
edges are chamfered at 45° to clear the tilted LED units.

Nothing lies under the array's flat face: there each lenslet's beam converges to a fraction of
its aperture and a support would shade much of it (corner pads under the array cost the corner
lenslets 30 % of their light on axis and whole foci off axis), whereas above the lenses each beam
fills its aperture and the tabs shade ≤ 5 % of a corner lenslet (the bore and tabs are
:mod:`cm2optics.optics.housing`, which the emission tracer uses too).
"""

from __future__ import annotations

import cadquery as cq

from cm2optics.cad.fits import Fit
from cm2optics.design import SystemDesign
from cm2optics.optics.housing import BoreStep, bore_steps, mla_tab_geometry
from cm2optics.optics.layout import mla_housing_envelope


def _box(width: float, length: float, z0: float, z1: float) -> cq.Workplane:
    return cq.Workplane().box(width, length, z1 - z0, centered=(True, True, False)).translate((0, 0, z0))


def _mla_tabs(design: SystemDesign, seat: BoreStep) -> cq.Workplane:
    """The corner tabs (:func:`mla_tab_geometry`) as triangular prisms in the corners of ``seat``."""
    geometry = mla_tab_geometry(design)
    hx, hy, d = seat.width_mm / 2, seat.length_mm / 2, geometry.diagonal_mm
    tabs = None
    for sx in (-1, 1):
        for sy in (-1, 1):
            tri = [(sx * hx, sy * hy), (sx * (d - hy), sy * hy), (sx * hx, sy * (d - hx))]
            tab = (
                cq.Workplane()
                .polyline(tri)
                .close()
                .extrude(geometry.z1_mm - geometry.z0_mm)
                .translate((0, 0, geometry.z0_mm))
            )
            tabs = tab if tabs is None else tabs.union(tab)
    return tabs


def build_mla_housing(design: SystemDesign) -> cq.Workplane:
    """The MLA housing of ``design`` as one solid in the device frame."""
    env = mla_housing_envelope(design)
    c, wall = design.mechanics.clearance_mm, design.mechanics.wall_mm
    sensor, board = design.sensor, design.sensor_board
    plate_z0 = c
    # Plate with arms, skirt and standoffs.
    pocket_w, pocket_l = sensor.package_width_mm + 2 * c, sensor.package_length_mm + 2 * c
    body = _box(pocket_w + 2 * wall, pocket_l + 2 * wall, plate_z0, env.flange_top_z_mm)
    arm_width = board.hole_diameter_mm + 2 * wall
    arm_length = board.hole_spacing_mm * 2**0.5
    for angle in (45, -45):
        arm = _box(arm_length, arm_width, plate_z0, env.flange_top_z_mm).rotate((0, 0, 0), (0, 0, 1), angle)
        body = body.union(arm)
    skirt = _box(pocket_w + 2 * wall, pocket_l + 2 * wall, env.flange_bottom_z_mm, plate_z0).cut(
        _box(pocket_w, pocket_l, env.flange_bottom_z_mm, plate_z0)
    )
    half = board.hole_spacing_mm / 2
    holes = [(sx * half, sy * half) for sx in (-1, 1) for sy in (-1, 1)]
    standoffs = (
        cq.Workplane()
        .pushPoints(holes)
        .circle(board.hole_diameter_mm / 2 + wall)
        .extrude(plate_z0 - env.flange_bottom_z_mm)
        .translate((0, 0, env.flange_bottom_z_mm))
    )
    tower = _box(env.tower_side_mm, env.tower_side_mm, env.flange_top_z_mm, env.tower_top_z_mm)
    if env.tower_chamfer_mm > 0:
        tower = tower.edges(">Z").chamfer(env.tower_chamfer_mm)
    body = body.union(skirt).union(standoffs).union(tower)
    # Screw holes and the bore.
    body = body.cut(
        cq.Workplane()
        .pushPoints(holes)
        .circle(board.hole_diameter_mm / 2)
        .extrude(env.flange_top_z_mm - env.flange_bottom_z_mm)
        .translate((0, 0, env.flange_bottom_z_mm))
    )
    steps = bore_steps(design)
    margin = 2 * c
    cone = (
        cq.Workplane()
        .workplane(offset=plate_z0)
        .rect(sensor.active_width_mm + 2 * margin, sensor.active_length_mm + 2 * margin)
        .workplane(offset=steps[0].z0_mm - plate_z0)
        .rect(steps[0].width_mm, steps[0].length_mm)
        .loft()
    )
    body = body.cut(cone)
    for step in steps:
        body = body.cut(_box(step.width_mm, step.length_mm, step.z0_mm, step.z1_mm))
    body = body.union(_mla_tabs(design, next(s for s in steps if s.name == "MLA seat")))
    solids = body.solids().vals()
    if len(solids) != 1 or not solids[0].isValid():
        raise RuntimeError(f"the MLA housing did not build as one valid solid ({len(solids)} solids)")
    return cq.Workplane().add(solids[0])


def mla_housing_fits(design: SystemDesign) -> list[Fit]:
    """Clearance of every part seated in the MLA housing, from the builder's own numbers."""
    c = design.mechanics.clearance_mm
    steps = {s.name: s for s in bore_steps(design)}
    fits = [
        Fit("sensor package", "skirt", c),
        Fit("MLA", "MLA seat", (steps["MLA seat"].width_mm - design.mla.width_mm) / 2),
        Fit("aperture mask", "mask seat", (steps["mask seat"].width_mm - design.aperture_mask.outer_mm) / 2),
        Fit("emission filter", "filter seat", (steps["filter seat"].width_mm - design.emission_filter.width_mm) / 2),
    ]
    if design.absorption_filter is not None:
        fits.append(
            Fit("absorption film", "film seat", (steps["film seat"].width_mm - design.absorption_filter.width_mm) / 2)
        )
    return fits

"""The printed LED housing of one illumination unit: LED, collimator and excitation filter.

Local frame: the LED frame of :mod:`cm2optics.optics.layout` — origin at the centre of the LED's
emitting surface, ``+z`` the direction the light leaves in, the package at ``z ≤ 0``; the
assembly places one housing per :func:`cm2optics.optics.layout.led_poses` entry.

A square tube (``led_housing.outer_mm``) with these sections, from the back:

=================  ==========================================================================
back wall          ``led_housing.back_mm`` thick, with a slot under the LED for its two leads
LED pocket         the package (``led.package_width_mm`` along x, ``package_length_mm`` along y)
bore               with a collimator: round, for its body, under the flange seat
light tube         without one (V1): a square tube the size of the clear aperture
seat               the collimator's flange with the excitation filter resting on its exit face
                   (``led_array.excitation_gap_mm`` must equal the exit face's height), or the
                   filter alone on the light tube
front lip          ``mechanics.min_wall_mm`` thick, overlapping the filter's edges by
                   ``led_housing.lip_mm``; its opening is the unit's clear aperture
=================  ==========================================================================

Every seat is its part plus ``mechanics.clearance_mm`` on each side, along the axis too.

Loading. A one-piece tube closed by a back wall and a front lip cannot take parts through
either end: in both presets the filter and the flange (4 mm square) do not pass the LED
pocket (3.4 mm wide), the LED (4.5 mm long) does not pass their seats (4.2 mm), and nothing
passes the lip. So the tube's ``+x`` face has a loading window from the back face to the lip,
and the parts slide in sideways, along ``−x``:

1. the LED, emitter up, leads out through the back-wall slot;
2. the collimator (V2), exit face up: body through the bore's channel, flange into the seat;
3. the excitation filter, onto the flange (V2) or the light tube's ledge (V1), under the lip;
4. the loaded housing slides, back first, along its axis into its socket on the base plate
   (:mod:`cm2optics.cad.base_plate`). The socket carries a *rail* that enters the window
   through its notch in the back wall and closes it: it locates the three parts' ``+x`` faces
   with the same clearance as every other seat and stops light leaking sideways.

The rail is stepped: behind the flange it reaches in to the LED's ``+x`` face (less the
collimator's bore), so the flange also rests on it; from there to the lip it stands off the
flange and the filter. Rails slide in from the back, so a step may only narrow towards the
back; :class:`LEDHousingLayout` holds the numbers both parts are built from.
"""

from __future__ import annotations

from dataclasses import dataclass

import cadquery as cq

from cm2optics.cad.fits import Fit
from cm2optics.design import SystemDesign
from cm2optics.optics.layout import led_unit_block

#: How far a cutter reaches past the faces it opens, mm (no coplanar faces in the booleans).
THROUGH_MM = 1.0


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in a part's local frame, mm."""

    x0: float
    x1: float
    y0: float
    y1: float
    z0: float
    z1: float

    def solid(self) -> cq.Workplane:
        """The box as one solid."""
        return (
            cq.Workplane()
            .box(self.x1 - self.x0, self.y1 - self.y0, self.z1 - self.z0, centered=False)
            .translate((self.x0, self.y0, self.z0))
        )


@dataclass(frozen=True)
class LEDHousingLayout:
    """Every dimension of the LED housing and of the rail that closes it (LED frame, mm).

    outer: the housing's outer block, from its back face to the front of the lip.
    led_pocket, lead_slot: the LED's pocket (open through the +x face) and the slot for its
        leads through the back wall.
    bore_radius_mm, bore_z_mm: the collimator body's bore and its z range (``None`` without a
        collimator); channel: the bore's way out to the loading window.
    tube: the light tube between LED and filter (``None`` with a collimator).
    flange_seat: the collimator flange's seat (``None`` without a collimator).
    filter_seat: the excitation filter's seat.
    aperture: the lip's opening (the unit's clear aperture); its z range spans the lip.
    windows: the loading window in the +x face, stepped like the rails, plus clearance.
    rails: the rail's steps as they sit in the window; the base plate extends them outwards
        through its socket wall and backwards into the socket floor, and cuts the bore out.
    """

    outer: Box
    led_pocket: Box
    lead_slot: Box
    bore_radius_mm: float | None
    bore_z_mm: tuple[float, float] | None
    channel: Box | None
    tube: Box | None
    flange_seat: Box | None
    filter_seat: Box
    aperture: Box
    windows: tuple[Box, ...]
    rails: tuple[Box, ...]

    @property
    def half_mm(self) -> float:
        """Half the housing's side, mm."""
        return self.outer.x1

    @property
    def back_z_mm(self) -> float:
        """The housing's back face, mm."""
        return self.outer.z0

    @property
    def front_z_mm(self) -> float:
        """The front face of the lip, where light leaves the unit, mm."""
        return self.outer.z1


def led_housing_layout(design: SystemDesign) -> LEDHousingLayout:
    """The LED housing's dimensions from the design (see the module docstring)."""
    c, w = design.mechanics.clearance_mm, design.mechanics.min_wall_mm
    led, filt, col = design.led, design.excitation_filter, design.collimator
    block = led_unit_block(design)
    half, back, front = block.half_mm, block.back_z_mm, block.front_z_mm
    out = half + THROUGH_MM
    lip = design.led_housing.lip_mm
    gap = design.led_array.excitation_gap_mm
    filter_top = gap + filt.thickness_mm

    led_pocket = Box(
        -(led.package_width_mm / 2 + c),
        out,
        -(led.package_length_mm / 2 + c),
        led.package_length_mm / 2 + c,
        -led.package_height_mm - c,
        c,
    )
    slot_x, slot_y = led.package_width_mm / 4, led.package_length_mm / 2 - w
    lead_slot = Box(-slot_x, slot_x, -slot_y, slot_y, back - THROUGH_MM, led_pocket.z0 + c / 2)
    fw, fl = filt.width_mm / 2 + c, filt.length_mm / 2 + c
    filter_seat = Box(-fw, out, -fl, fl, gap - c, filter_top + c)
    ax, ay = filt.width_mm / 2 - lip, filt.length_mm / 2 - lip  # the lip overlaps the filter by lip_mm
    aperture = Box(-ax, ax, -ay, ay, filter_top + c, front + THROUGH_MM)

    widths = [led.package_length_mm, filt.width_mm, filt.length_mm]
    inner_faces = [filt.width_mm / 2 + c, led.package_width_mm / 2 + c]
    if col is not None:
        exit_z = col.led_gap_mm + col.height_mm
        flange_z0 = exit_z - col.flange_mm
        r = col.footprint_mm / 2 + c
        bore_z = (c, flange_z0 - c)
        channel = Box(0.0, out, -r, r, *bore_z)
        flange_seat = Box(-r, out, -r, r, flange_z0 - c, exit_z + c)
        tube = None
        ledge_z = flange_seat.z0
        widths.append(col.footprint_mm)
        inner_faces.append(r)
    else:
        r = bore_z = channel = flange_seat = None
        tube = Box(aperture.x0, aperture.x1, aperture.y0, aperture.y1, c, filter_seat.z0)
        ledge_z = filter_seat.z0
    # Rails: the lower step reaches the LED's +x face up to the seat, the upper one stands off
    # every part it passes on its way in; both as wide as the narrowest part they pass.
    h = min(widths) / 2
    lower = Box(led.package_width_mm / 2 + c, half + c, -h, h, back - c, ledge_z)
    upper = Box(max(inner_faces), half + c, -h, h, back - c, filter_top)
    rails = (lower, upper)
    windows = tuple(Box(rail.x0 - c, out, -h - c, h + c, back - THROUGH_MM, rail.z1 + c) for rail in rails)
    return LEDHousingLayout(
        outer=Box(-half, half, -half, half, back, front),
        led_pocket=led_pocket,
        lead_slot=lead_slot,
        bore_radius_mm=r,
        bore_z_mm=bore_z,
        channel=channel,
        tube=tube,
        flange_seat=flange_seat,
        filter_seat=filter_seat,
        aperture=aperture,
        windows=windows,
        rails=rails,
    )


def bore_solid(layout: LEDHousingLayout, extra_mm: float = 0.0) -> cq.Workplane:
    """The collimator body's bore as a cylinder (requires a collimator), reaching ``extra_mm``
    (mm) further up than the bore itself."""
    z0, z1 = layout.bore_z_mm
    return cq.Workplane().circle(layout.bore_radius_mm).extrude(z1 + extra_mm - z0).translate((0, 0, z0))


def build_led_housing(design: SystemDesign) -> cq.Workplane:
    """One LED housing of ``design`` as one solid in the LED frame."""
    layout = led_housing_layout(design)
    body = layout.outer.solid()
    cavities = [layout.led_pocket, layout.lead_slot, layout.filter_seat, layout.aperture, *layout.windows]
    if layout.bore_radius_mm is not None:
        body = body.cut(bore_solid(layout))
        cavities += [layout.channel, layout.flange_seat]
    else:
        cavities.append(layout.tube)
    for box in cavities:
        body = body.cut(box.solid())
    solids = body.solids().vals()
    if len(solids) != 1 or not solids[0].isValid():
        raise RuntimeError(f"the LED housing did not build as one valid solid ({len(solids)} solids)")
    return cq.Workplane().add(solids[0])


def led_unit_parts(design: SystemDesign) -> dict[str, cq.Workplane]:
    """The bought-in parts of one unit in the LED frame: ``led`` (the package as a block, its
    top face the emitting surface: the dome and pads of a real package are not modelled) and
    ``excitation_filter`` (a plate, lower face at ``led_array.excitation_gap_mm``)."""
    led, filt = design.led, design.excitation_filter
    gap = design.led_array.excitation_gap_mm
    pw, pl = led.package_width_mm / 2, led.package_length_mm / 2
    fw, fl = filt.width_mm / 2, filt.length_mm / 2
    return {
        "led": Box(-pw, pw, -pl, pl, -led.package_height_mm, 0.0).solid(),
        "excitation_filter": Box(-fw, fw, -fl, fl, gap, gap + filt.thickness_mm).solid(),
    }


def led_housing_fits(design: SystemDesign) -> list[Fit]:
    """Clearance per side (mm) of each part in its housing seat: the smallest over its ``−x``
    and ``±y`` sides and its free axial sides (the filter rests on the collimator's flange, so
    with a collimator only its lip side counts). The ``+x`` side is the base plate's rail
    (:func:`cm2optics.cad.base_plate.base_plate_fits`)."""
    layout = led_housing_layout(design)
    led, filt, col = design.led, design.excitation_filter, design.collimator
    gap = design.led_array.excitation_gap_mm

    def lateral(seat: Box, width: float, length: float) -> float:
        return min(-seat.x0 - width / 2, seat.y1 - length / 2, -seat.y0 - length / 2)

    pocket, seat = layout.led_pocket, layout.filter_seat
    led_axial = min(pocket.z1, -led.package_height_mm - pocket.z0)
    filter_axial = seat.z1 - (gap + filt.thickness_mm)
    if col is None:
        filter_axial = min(filter_axial, gap - seat.z0)
    fits = [
        Fit("LED package", "LED pocket", min(lateral(pocket, led.package_width_mm, led.package_length_mm), led_axial)),
        Fit("excitation filter", "filter seat", min(lateral(seat, filt.width_mm, filt.length_mm), filter_axial)),
    ]
    if col is not None:
        flange = layout.flange_seat
        flange_axial = (col.led_gap_mm + col.height_mm - col.flange_mm) - flange.z0
        fits.insert(
            1,
            Fit(
                "collimator flange",
                "flange seat",
                min(lateral(flange, col.footprint_mm, col.footprint_mm), flange_axial),
            ),
        )
    return fits

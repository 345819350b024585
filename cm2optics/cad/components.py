"""Bought-in and cut parts of the imaging module: filters, film, aperture mask, sensor, board.

Each builder returns one solid in its local frame: centred on the optical axis, lower face
at z = 0 (the assembly lifts it to its height in the device frame).
"""

from __future__ import annotations

import cadquery as cq

from cm2optics.design import SystemDesign


def _plate(width_mm: float, length_mm: float, thickness_mm: float) -> cq.Workplane:
    return cq.Workplane().box(width_mm, length_mm, thickness_mm, centered=(True, True, False))


def build_emission_filter(design: SystemDesign) -> cq.Workplane:
    """Interference emission filter plate."""
    f = design.emission_filter
    return _plate(f.width_mm, f.length_mm, f.thickness_mm)


def build_absorption_filter(design: SystemDesign) -> cq.Workplane:
    """Absorbing long-pass film (requires ``design.absorption_filter``)."""
    f = design.absorption_filter
    if f is None:
        raise ValueError("absorption_filter is null in this design: there is no film to build")
    return _plate(f.width_mm, f.length_mm, f.thickness_mm)


def build_aperture_mask(design: SystemDesign) -> cq.Workplane:
    """Opaque aperture plate (laser-cut shim or black film) with its square opening."""
    m = design.aperture_mask
    return (
        _plate(m.outer_mm, m.outer_mm, m.thickness_mm)
        .faces(">Z")
        .workplane()
        .rect(m.opening_mm, m.opening_mm)
        .cutThruAll()
    )


def build_sensor_package(design: SystemDesign) -> cq.Workplane:
    """Sensor package as a block; its top face is the photosensitive surface."""
    s = design.sensor
    return _plate(s.package_width_mm, s.package_length_mm, s.package_height_mm)


def build_sensor_board(design: SystemDesign) -> cq.Workplane:
    """Camera PCB with its four mounting holes; top face at z = 0 locally."""
    b = design.sensor_board
    half = b.hole_spacing_mm / 2
    holes = [(sx * half, sy * half) for sx in (-1, 1) for sy in (-1, 1)]
    board = (
        cq.Workplane()
        .box(b.size_mm, b.size_mm, b.thickness_mm, centered=(True, True, False))
        .translate((0, 0, -b.thickness_mm))
    )
    return board.faces(">Z").workplane().pushPoints(holes).hole(b.hole_diameter_mm)

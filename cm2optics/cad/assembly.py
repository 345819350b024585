"""The device assembled: every part built once in its local frame and placed in the device
frame, the fits of every seated part, and a pairwise interference check.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cadquery as cq
import numpy as np
import trimesh

from cm2optics.cad import base_plate, collimator, components, led_housing, mla, mla_housing
from cm2optics.cad.fits import Fit
from cm2optics.cad.placement import location_from_pose
from cm2optics.design import SystemDesign
from cm2optics.optics.layout import led_poses

#: Intersections smaller than this (mm³) are contacts (a part resting on its ledge), not clashes.
INTERFERENCE_TOLERANCE_MM3 = 1e-4


@dataclass(frozen=True)
class PartSpec:
    """A distinct part: how to build it and what it is made of.

    name: file stem and identifier.
    build: design → one solid in the part's local frame.
    printed: whether the project prints it (printability rules apply) or buys/cuts it.
    material: what it is made of.
    description: one line for people.
    fidelity: optional (design, mesh) → figures of how true the mesh is to the design.
    """

    name: str
    build: Callable[[SystemDesign], cq.Workplane]
    printed: bool
    material: str
    description: str
    fidelity: Callable[[SystemDesign, trimesh.Trimesh], dict[str, float]] | None = None


@dataclass(frozen=True)
class PlacedPart:
    """One instance of a part in the device frame."""

    instance: str
    part: str
    solid: cq.Solid
    matrix: np.ndarray  # 4×4, local → device frame


def _led_unit_part(key: str) -> Callable[[SystemDesign], cq.Workplane]:
    def build(design: SystemDesign) -> cq.Workplane:
        return led_housing.led_unit_parts(design)[key]

    return build


def part_specs(design: SystemDesign) -> list[PartSpec]:
    """The distinct parts of ``design`` (a V1 design has no film and no collimator)."""
    specs = [
        PartSpec("sensor_board", components.build_sensor_board, False, "FR-4", "camera PCB with its mounting holes"),
        PartSpec("sensor_package", components.build_sensor_package, False, "ceramic", f"{design.sensor.name} package"),
        PartSpec(
            "mla_housing", mla_housing.build_mla_housing, True, "black resin", "holds the imaging optics on the board"
        ),
        PartSpec(
            "mla",
            mla.build_mla,
            False,
            design.mla.material.value,
            f"{design.mla.rows}×{design.mla.cols} microlens array",
            mla.lens_rms_deviation_um,
        ),
        PartSpec(
            "aperture_mask", components.build_aperture_mask, False, "black shim", "square aperture over the lenslets"
        ),
        PartSpec(
            "emission_filter",
            components.build_emission_filter,
            False,
            design.emission_filter.material.value,
            "interference emission filter",
        ),
        PartSpec("base_plate", base_plate.build_base_plate, True, "black resin", "dome that holds the LED units"),
        PartSpec("led_housing", led_housing.build_led_housing, True, "black resin", "one LED unit's housing"),
        PartSpec("led", _led_unit_part("led"), False, "LED", "surface-mount LED package"),
        PartSpec(
            "excitation_filter",
            _led_unit_part("excitation_filter"),
            False,
            design.excitation_filter.material.value,
            "interference excitation filter",
        ),
    ]
    specs[3:3] = _if_present(
        design.absorption_filter,
        "absorption_filter",
        components.build_absorption_filter,
        False,
        "absorbing long-pass film",
    )
    specs += _if_present(
        design.collimator, "collimator", collimator.build_collimator, True, "freeform TIR LED collimator"
    )
    return specs


def _if_present(
    part: object | None, name: str, build: Callable[[SystemDesign], cq.Workplane], printed: bool, description: str
) -> list[PartSpec]:
    """The spec of an optional part (made of ``part.material``) in a list; empty when the design has none."""
    return [] if part is None else [PartSpec(name, build, printed, part.material.value, description)]


def _imaging_heights(design: SystemDesign) -> dict[str, float]:
    """Device-frame height of each imaging part's local origin, mm."""
    return {
        "sensor_board": -design.sensor.package_height_mm,
        "sensor_package": -design.sensor.package_height_mm,
        "mla_housing": 0.0,
        "absorption_filter": design.imaging.film_to_sensor_mm,
        "mla": design.imaging.mla_to_sensor_mm,
        "aperture_mask": design.mask_z_mm,
        "emission_filter": design.emission_filter_z_mm,
        "base_plate": 0.0,
    }


LED_UNIT_PARTS = ("led_housing", "led", "excitation_filter", "collimator")


def place_parts(design: SystemDesign, built: dict[str, cq.Workplane]) -> list[PlacedPart]:
    """Instances of the ``built`` parts (name → local solid) placed in the device frame."""
    heights = _imaging_heights(design)
    placed = []
    for name, part in built.items():
        solid = part.val()
        if name in heights:
            matrix = np.eye(4)
            matrix[2, 3] = heights[name]
            placed.append(PlacedPart(name, name, solid.translate(cq.Vector(0, 0, heights[name])), matrix))
        elif name in LED_UNIT_PARTS:
            for i, pose in enumerate(led_poses(design), start=1):
                placed.append(PlacedPart(f"{name}_{i}", name, solid.moved(location_from_pose(pose)), pose.matrix))
        else:
            raise KeyError(f"no placement known for part {name!r}")
    return placed


def interferences(
    placed: list[PlacedPart], tolerance_mm3: float = INTERFERENCE_TOLERANCE_MM3
) -> list[dict[str, object]]:
    """Pairs of placed parts whose solids overlap by more than ``tolerance_mm3`` (mm³)."""
    boxes = [p.solid.BoundingBox() for p in placed]
    clashes = []
    for i in range(len(placed)):
        for j in range(i + 1, len(placed)):
            a, b = boxes[i], boxes[j]
            if (
                a.xmax < b.xmin
                or b.xmax < a.xmin
                or a.ymax < b.ymin
                or b.ymax < a.ymin
                or a.zmax < b.zmin
                or b.zmax < a.zmin
            ):
                continue
            volume = placed[i].solid.intersect(placed[j].solid).Volume()
            if volume > tolerance_mm3:
                clashes.append({"a": placed[i].instance, "b": placed[j].instance, "volume_mm3": round(volume, 6)})
    return clashes


def fits(design: SystemDesign) -> list[Fit]:
    """Every seated part's clearance in the assembly."""
    return (
        mla_housing.mla_housing_fits(design) + led_housing.led_housing_fits(design) + base_plate.base_plate_fits(design)
    )


#: The parts whose placement follows the LED units' aim, and what they may collide with.
AIM_CHECK_PARTS = ("mla_housing", "base_plate", "led_housing", "led", "excitation_filter", "collimator")


def aim_interferences(design: SystemDesign) -> list[dict[str, object]]:
    """The assembly's interference check (:func:`interferences`) over the parts that the LED
    units' placement moves and the MLA housing they must clear. A base plate that cannot be
    built around the units (its dome would not meet the tower) is reported as a clash of its own
    (``volume_mm3`` None, with the reason)."""
    specs = {spec.name: spec for spec in part_specs(design) if spec.name in AIM_CHECK_PARTS}
    built = {}
    for name, spec in specs.items():
        try:
            built[name] = spec.build(design)
        except (ValueError, RuntimeError) as error:  # DesignError is a ValueError
            return [{"a": name, "b": "design", "volume_mm3": None, "reason": str(error).splitlines()[0]}]
    return interferences(place_parts(design, built))

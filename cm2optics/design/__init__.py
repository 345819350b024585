"""The CM² system design, the leaf of the package: frozen, validated dataclasses, YAML in/out, presets.

Every number that shapes a part, a ray or a pixel lives here, once. Lengths are in mm, pixel
pitches in µm, wavelengths in nm, angles in degrees (``_deg``) in files and radians (``_rad``) in
code. Construct parts directly (``MicrolensArray(...)``) or load a YAML preset
(:func:`load_preset`, :func:`load_design`); either way a bad value raises :class:`DesignError`
naming the field, the value and what is allowed.

One idea per module: :mod:`~.validation` (errors), :mod:`~.sensor`, :mod:`~.mla`, :mod:`~.filters`,
:mod:`~.imaging`, :mod:`~.illumination`, :mod:`~.mechanics` (the parts), :mod:`~.as_built` and
:mod:`~.as_built_illumination` (how the assembled device departs from them), :mod:`~.system` (the
device and its cross-part checks), :mod:`~.coerce` and :mod:`~.io` (YAML), :mod:`~.materials`
(refractive indices) and :mod:`~.paraxial` (ABCD matrices). Derived optics (best focus,
magnification, object pixel, NA) are functions in :mod:`cm2optics.optics.first_order`; this
package imports no other part of cm2optics.
"""

from cm2optics.design.as_built import AsBuilt
from cm2optics.design.as_built_illumination import IlluminationAsBuilt
from cm2optics.design.filters import AbsorptionFilter, InterferenceFilter
from cm2optics.design.illumination import LED, Collimator, LEDArray
from cm2optics.design.imaging import ImagedVolume, ImagingLayout
from cm2optics.design.io import (
    DEFAULT_PRESET,
    available_presets,
    default_design,
    design_from_dict,
    load_design,
    load_preset,
)
from cm2optics.design.materials import Material, refractive_index
from cm2optics.design.mechanics import BasePlate, LEDHousing, Mechanics, MLAHousing
from cm2optics.design.mla import ApertureMask, MicrolensArray, Side
from cm2optics.design.sensor import Sensor, SensorBoard
from cm2optics.design.system import SystemDesign
from cm2optics.design.validation import DesignError

__all__ = [
    "DEFAULT_PRESET",
    "LED",
    "AbsorptionFilter",
    "AsBuilt",
    "ApertureMask",
    "BasePlate",
    "Collimator",
    "DesignError",
    "IlluminationAsBuilt",
    "ImagedVolume",
    "ImagingLayout",
    "InterferenceFilter",
    "LEDArray",
    "LEDHousing",
    "MLAHousing",
    "Material",
    "Mechanics",
    "MicrolensArray",
    "Sensor",
    "SensorBoard",
    "Side",
    "SystemDesign",
    "available_presets",
    "default_design",
    "design_from_dict",
    "load_design",
    "load_preset",
    "refractive_index",
]

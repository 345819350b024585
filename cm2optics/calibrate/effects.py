"""The effect library: physical effects a model may lack, each a named parameter set with units,
ranges and defaults (the value at which the effect is absent).

Adding an effect to the model means the model gains its parameters and their fitted values.
Geometric and optical effects change where and how the foci form and need the simulator;
the sensor-side effects (stray light, leakage, pixel crosstalk) act on the images themselves and
are applied here, by :func:`apply_image_effects`, to any simulator's output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cm2optics.optics.sensor_effects import crosstalk, halo


@dataclass(frozen=True)
class Parameter:
    """One fitted quantity.

    name: key in the effect's ``parameters`` (unit in the name where it has one).
    default: the value at which the effect is absent.
    low, high: the physically sensible range.
    step: finite-difference step for derivatives (in the parameter's unit).
    """

    name: str
    default: float
    low: float
    high: float
    step: float


@dataclass(frozen=True)
class Effect:
    """A physical effect: its vocabulary name, parameters and what it does."""

    name: str
    parameters: tuple[Parameter, ...]
    description: str
    lenslet: int | None = None  # for per-lenslet effects: which lenslet (row-major index)
    side: str | None = None  # for per-side effects: which side of the array ("+x", "-x", "+y", "-y")

    @property
    def key(self) -> str:
        index = self.lenslet if self.lenslet is not None else self.side
        return self.name if index is None else f"{self.name}[{index}]"

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.parameters}


def _p(name: str, default: float, low: float, high: float, step: float) -> Parameter:
    return Parameter(name, default, low, high, step)


GLOBAL_EFFECTS: tuple[Effect, ...] = (
    Effect(
        "mla_decenter",
        (_p("dx_mm", 0, -0.2, 0.2, 0.002), _p("dy_mm", 0, -0.2, 0.2, 0.002)),
        "the lenslet array displaced across the sensor",
    ),
    Effect("mla_rotation", (_p("angle_deg", 0, -3, 3, 0.05),), "the lenslet array rotated about the optical axis"),
    Effect(
        "mla_tilt",
        (_p("tilt_x_deg", 0, -5, 5, 0.1), _p("tilt_y_deg", 0, -5, 5, 0.1)),
        "the lenslet array tilted about x and y (right-handed, about the centre of its vertex plane): each "
        "lenslet's distance from the sensor, its focus and its magnification change across the array",
    ),
    Effect(
        "sensor_tilt",
        (_p("tilt_x_deg", 0, -5, 5, 0.1), _p("tilt_y_deg", 0, -5, 5, 0.1)),
        "the sensor tilted about x and y (right-handed, about its centre): a focus at (x, y) on it is "
        "defocused by y·sin θx − x·sin θy and moves along its chief ray",
    ),
    Effect(
        "mla_spacing",
        (_p("delta_mm", 0, -0.3, 0.3, 0.005),),
        "the lenslet array's distance from the sensor differs from the design",
    ),
    Effect("lenslet_pitch", (_p("delta_mm", 0, -0.05, 0.05, 0.0005),), "the lenslet pitch differs from the design"),
    Effect(
        "source_profile",
        (_p("falloff_per_rad2", 0, 0, 150, 0.5),),
        "the calibration source emits into a cone rather than isotropically: its intensity falls as "
        "exp(−2·falloff·θ²), a Gaussian of half-angle 1/√falloff at 1/e²",
    ),
    Effect(
        "stray_light",
        (_p("fraction", 0, 0, 0.5, 0.01), _p("width_um", 200, 20, 2000, 20.0)),
        "a fraction of each focus's light spread into a wide halo (scatter in the housing and filters)",
    ),
    Effect(
        "leakage_background",
        (_p("counts_per_ms", 0, 0, 1e4, 0.05),),
        "uniform light reaching the sensor in proportion to the exposure (excitation leaking through the filters)",
    ),
    Effect(
        "pixel_crosstalk",
        (_p("fraction", 0, 0, 0.5, 0.02),),
        "a fraction of each pixel's signal shared with its four neighbours",
    ),
    Effect(
        "vignetting",
        (_p("radius_delta_mm", 0, -1, 1, 0.05),),
        "the clear aperture that cuts off the foci of sources far off a lenslet's axis differs from the design",
    ),
)


def per_lenslet_effects(lenslets: int) -> tuple[Effect, ...]:
    """Effects of one lenslet each: its transmission and its decentre."""
    out = []
    for j in range(lenslets):
        out.append(
            Effect(
                "lenslet_transmission",
                (_p("transmission", 1, 0, 1.5, 0.02),),
                "one lenslet passes less (or more) light than the others: dust, a defect",
                j,
            )
        )
        out.append(
            Effect(
                "lenslet_decenter",
                (_p("dx_mm", 0, -0.1, 0.1, 0.002), _p("dy_mm", 0, -0.1, 0.1, 0.002)),
                "one lenslet displaced within the array",
                j,
            )
        )
    return tuple(out)


#: The sides of the array, as the design's ``mla.partial_sides`` names them.
SIDES = ("+x", "-x", "+y", "-y")


def partial_lenslet_effects(pitch_mm: float) -> tuple[Effect, ...]:
    """Partial lenslets left by dicing on one side each: a row or column of lens segments
    ``border_mm`` wide (0 to just under the pitch, ``pitch_mm``) beside the array, each adding a
    weak extra view of the source (the paper's false positives)."""
    border = _p("border_mm", 0, 0, 0.95 * pitch_mm, 0.01)
    return tuple(
        Effect(
            "partial_lenslets",
            (border,),
            f"partial lenslets on the array's {side} side add extra, weaker views (design: mla.partial_sides, "
            "mla.partial_border_mm)",
            side=side,
        )
        for side in SIDES
    )


#: The largest calibration source the library fits, µm (:class:`~cm2optics.emission.source.PointSource`'s range).
MAX_SOURCE_DIAMETER_UM = 200.0


def source_size_effect(declared_um: float = 0.0) -> Effect | None:
    """The calibration source larger than the ``declared_um`` (µm) the scan says it used: a
    pinhole or bead of diameter ``diameter_um`` (µm, object space; default: the declared size, at
    which the effect is absent; range: the declared size to :data:`MAX_SOURCE_DIAMETER_UM`).

    A source of diameter d is a disc: every focus is the point source's convolved with the disc's
    image, d × the lenslet's lateral magnification at the source's depth across. Its second
    moment, (d·m)²/16 per axis, adds to the focus's: the same widening, relative to the image of
    the disc, in every lenslet and field position, growing with the magnification over depth
    (m ∝ 1/(D − z)). Pixel crosstalk widens the foci by a fixed amount in sensor pixels whatever
    the depth and magnification; stray light moves a fraction of the energy into a wide halo.
    None when the declared source is already at the largest size."""
    if not 0.0 <= declared_um < MAX_SOURCE_DIAMETER_UM:
        return None
    return Effect(
        "source_size",
        (_p("diameter_um", declared_um, declared_um, MAX_SOURCE_DIAMETER_UM, 2.0),),
        f"the calibration source is a disc larger than declared ({declared_um:g} µm): every focus is blurred by "
        "its image, the diameter × the magnification at the source's depth",
    )


def library(lenslets: int, pitch_mm: float = 1.0, source_diameter_um: float = 0.0) -> tuple[Effect, ...]:
    """Every candidate effect for an array of ``lenslets`` lenslets at a pitch of ``pitch_mm``,
    imaged with a calibration source declared ``source_diameter_um`` (µm) across."""
    size = source_size_effect(source_diameter_um)
    return (
        GLOBAL_EFFECTS + ((size,) if size else ()) + per_lenslet_effects(lenslets) + partial_lenslet_effects(pitch_mm)
    )


def split_key(key: str) -> tuple[str, int | str | None]:
    """An effect key's name and index: ``"lenslet_decenter[4]"`` → ("lenslet_decenter", 4),
    ``"partial_lenslets[+x]"`` → ("partial_lenslets", "+x"), ``"mla_rotation"`` → (…, None)."""
    name, _, index = key.partition("[")
    if not index:
        return name, None
    index = index[:-1]
    return name, index if index in SIDES else int(index)


# ----------------------------------------------------------------------------- image-side effects


def apply_image_effects(images: np.ndarray, values: dict[str, dict[str, float]], pixel_um: float) -> np.ndarray:
    """The sensor-side effects in ``values`` (effect name → parameters) applied to images
    (N, y, x) in counts per ms of a unit source; effects not named are absent. The same
    functions as a design's ``as_built`` section (:mod:`cm2optics.optics.sensor_effects`)."""
    out = np.asarray(images, np.float32)
    if "stray_light" in values:
        p = values["stray_light"]
        out = halo(out, p["fraction"], p["width_um"] / pixel_um)
    if "pixel_crosstalk" in values:
        out = crosstalk(out, values["pixel_crosstalk"]["fraction"])
    return out


def leakage_counts(values: dict[str, dict[str, float]], exposure_ms: np.ndarray) -> np.ndarray:
    """(N,) uniform leakage counts added to each frame."""
    rate = values.get("leakage_background", {}).get("counts_per_ms", 0.0)
    return rate * np.asarray(exposure_ms, float)

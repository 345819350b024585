"""The paper's own measurements as residuals of the model (issue 14, item 7): part (a), the
excitation power; the paper's numbers for all three parts (:data:`PAPER`; parts (b) and (c) are
:mod:`.paper_sbr` and :mod:`.paper_field`).

The paper (Xue et al., Optica 2022; LaTeX source in the repository's ``shared/paper``) measured
"up-to 75 mW (at maximum driving current of 350 mA)" over the 8-mm region with a Thorlabs
PM121D power meter (supplement, illumination module), while ``cm2 illum run --preset cm2-v2``
traces the design with the preset's 640 mW per LED. :func:`excitation_power_chain` traces the
design, then multiplies the prediction by a chain of physical factors, each with its value, 1σ
relative uncertainty, source and whether the code computed it (from the trace or the spectra)
or took it as a stated assumption; what the chain leaves between the prediction and the
measurement is the unexplained ratio, with the factors' uncertainties combined in quadrature
(relative, i.e. on a log scale).

Every number the paper gives is an input here (:data:`PAPER`, with where it is written), never
a result.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign

__all__ = ["PAPER", "Factor", "excitation_power_chain"]

#: The paper's numbers used here, each with where it is written (shared/paper/000_3c80ff3f351ba806.txt).
PAPER: dict[str, dict[str, Any]] = {
    "measured_power_mw": {
        "value": 75.0,
        "source": "supplement, illumination module: 'up-to 75 mW (at maximum driving current of 350 mA), "
        "measured by a power meter (Thorlabs no.PM121D)' (also main text, Fig. 2 section)",
    },
    "drive_current_ma": {
        "value": 350.0,
        "source": "supplement: LED driver 'LED-dynamics Inc., 3021-D-E-350, 350 mA'",
    },
    "led": {"value": "Lumileds LXML-PB01-0040", "source": "main text and supplement, illumination module"},
    "field_mm": {"value": 8.0, "source": "main text: 'confined uniform illumination ... across an 8-mm diameter FOV'"},
    "sbr_gain": {
        "value": 5.0,
        "source": "main text, Fig. 2e caption and imaging module: the hybrid filter 'improves the SBR by >5× on a "
        "phantom consisting of 10-µm fluorescence beads' ('10-µm fluorescent beads in clear resin'); supplement, "
        "spectral properties: 'reduced the background haziness by ~5 times' (a lower bound)",
    },
    "bead_diameter_um": {
        "value": 10.0,
        "source": "main text, Fig. 2e caption: '10-µm fluorescent beads in clear resin'",
    },
    "bead_density_per_mm2": {
        "value": 15.0,
        "range": [10.0, 20.0],
        "source": "main text, experiments: 'The phantom is estimated to have 10-20 emitters / mm²'",
    },
    "phantom_thickness_mm": {
        "value": 0.5,
        "source": "main text, Fig. 7 caption: 'cylindrical volume with ~6.7-mm diameter and ~0.5-mm depth' (the Fig. 2e "
        "phantom's size is not given; the same protocol, supplement 'Preparation of phantom objects')",
    },
    "phantom_diameter_mm": {"value": 6.7, "source": "main text, Fig. 7 caption (as phantom_thickness_mm)"},
    "source_diameter_um": {
        "value": 5.0,
        "source": "supplement, sparse PSF calibration: 'A 5-µm mounted pinhole (Thorlabs, P5D)'",
    },
    "object_pixel_um": {
        "value": 4.15,
        "source": "supplement, imaging module: 'a calibrated de-magnification of ~1.7× which results in an effective "
        "pixel size of 4.15 µm' (also main text: 'IMX178 ... gives a 4.15-µm effective pixel size')",
    },
    "demagnification": {"value": 1.7, "source": "supplement, imaging module (as object_pixel_um)"},
    "edge_drop": {
        "value": 0.85,
        "uncertainty": 0.05,
        "source": "main text, CM²Net in simulation: 'rapid intensity fall-off (~85% drop at the 7-mm FOV edge) of the "
        "imperfect point source'; supplement, ablation study: the intensity 'under the central microlens' drops 'as "
        "much as ~85% near the edge' (± 5 %: the paper's '~')",
    },
    "edge_radius_mm": {"value": 3.5, "source": "main text: 'at the 7-mm FOV edge' (radius 3.5 mm)"},
}

#: The preset's photometric conversion (cm2-v2.yaml: "≥ 40 lm at 350 mA with V(470 nm) = 0.091").
PRESET_V = 0.091
#: PM121D's input aperture, mm (assumed: Thorlabs' S12xC photodiode heads have a Ø9.5-mm aperture).
METER_APERTURE_MM = 9.5
#: Refractive index of the meter's window/photodiode cover glass (assumed), for its Fresnel loss.
METER_WINDOW_N = 1.5
#: Thermal droop of a blue InGaN LED run at 350 mA in a closed printed housing (assumed: ≈ 5–15 %
#: between 25 °C and an ≈ 85 °C junction for such LEDs; no datasheet curve in the repository).
THERMAL_DROOP = (0.90, 0.05)
#: Printed-surface RMS error of the collimator, µm (the robustness study's default for a Form 2).
SURFACE_RMS_UM = 2.0


@dataclass(frozen=True)
class Factor:
    """One link of the chain: measured = predicted × Π value (× what remains).

    name: short id. value: the multiplicative factor. uncertainty: its 1σ, relative.
    computed: True when the code computed it from the trace or the spectra; False: an assumption.
    source: where the value (or its inputs) comes from.
    """

    name: str
    value: float
    uncertainty: float
    computed: bool
    source: str


def _photometric_factor(design: SystemDesign) -> Factor:
    """Radiant flux of the same 40 lm with the LED spectrum's own luminous efficacy rather than
    V at the peak: V_eff = ∫ V S dλ / ∫ S dλ (CIE 1924 photopic V, the spectra library's LED model)."""
    import colour

    from cm2optics.illumination.source import led_source

    spectrum = led_source(design).spectrum
    v = colour.colorimetry.SDS_LEFS_PHOTOPIC["CIE 1924 Photopic Standard Observer"]
    v_at = np.interp(spectrum.wavelength_nm, v.wavelengths, v.values, left=0.0, right=0.0)
    v_eff = spectrum.weighted_mean(v_at)
    return Factor(
        "led_photometric_conversion",
        PRESET_V / v_eff,
        0.10,
        True,
        f"spectrum-weighted V = {v_eff:.4f} (CIE 1924 photopic, LED model peak {design.led.peak_nm:g} nm) against "
        f"the preset's V(470) = {PRESET_V}; ±10 %: the flux bin '0040' gives a minimum of 40 lm, its spread is not "
        "in the repository",
    )


def _window_transmittance(cos_i: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel transmittance from air into the meter's window (n = METER_WINDOW_N)."""
    from cm2optics.optics.interfaces import fresnel_transmittance

    cos_t = np.sqrt(1.0 - (1.0 - cos_i**2) / METER_WINDOW_N**2)
    return np.asarray(fresnel_transmittance(cos_i, cos_t, 1.0, METER_WINDOW_N))


def _meter_factors(design: SystemDesign, record: Any, scene: Any) -> list[Factor]:
    """The meter's aperture (power inside Ø9.5 mm against inside the 8-mm field) and its
    angular response (unpolarised Fresnel transmission into its window at every delivered ray's
    incidence, against normal incidence, where such meters are calibrated)."""
    from cm2optics.illumination.tracer import Status

    on = record.status == int(Status.SAMPLE)
    r = np.hypot(record.hit_mm[on, 0], record.hit_mm[on, 1])
    field = design.volume.field_mm / 2
    inside = np.count_nonzero(r <= field)
    aperture = np.count_nonzero(r <= METER_APERTURE_MM / 2)
    half_mm = 0.5 / 2  # ±0.5 mm on the aperture's diameter
    spread = (
        np.count_nonzero(r <= METER_APERTURE_MM / 2 + half_mm) - np.count_nonzero(r <= METER_APERTURE_MM / 2 - half_mm)
    ) / (2 * max(aperture, 1))
    # Incidence on the sample plane: the direction of the last segment (the exit direction is
    # the direction through the filter's portal; after it the ray travels straight to the plane).
    d = record.exit_direction[on][r <= field]
    cos_i = np.clip(np.abs(d[:, 2]) / np.linalg.norm(d, axis=1), 0.0, 1.0)
    t = _window_transmittance(cos_i)
    t0 = float(_window_transmittance(np.ones(1))[0])
    angle = np.degrees(np.arccos(cos_i))
    return [
        Factor(
            "meter_aperture",
            aperture / max(inside, 1),
            float(spread),
            True,
            f"traced power inside Ø{METER_APERTURE_MM} mm (assumed PM121D aperture, ±0.5 mm) against inside the "
            f"{2 * field:g}-mm field",
        ),
        Factor(
            "meter_angular_response",
            float(t.mean() / t0),
            0.02,
            True,
            f"Fresnel transmission of an n = {METER_WINDOW_N} window at the delivered rays' incidence (median "
            f"{np.median(angle):.1f}°, 90 % below {np.quantile(angle, 0.9):.1f}°) against normal incidence; "
            "±2 %: the window's index and coating are assumptions",
        ),
    ]


def _surface_factor(scene: Any, setup: Any, nominal_fraction: float, samples: int) -> Factor:
    """Delivered fraction with a printed surface error of ``SURFACE_RMS_UM`` against the nominal
    (the robustness study's random smooth surface, mean and spread over ``samples`` draws)."""
    from cm2optics.illumination.robustness import Tolerances, draw_errors, perturbed_scene
    from cm2optics.illumination.tracer import Status, trace

    rng = np.random.default_rng(1)
    tolerances = Tolerances(led_placement_mm=0.0, unit_tilt_deg=0.0, surface_rms_um=SURFACE_RMS_UM)
    ratios = []
    for _ in range(samples):
        moved = perturbed_scene(scene, draw_errors(scene.collimator, scene.units, tolerances, rng))
        record = trace(moved, setup.source, setup.rays, transmission=setup.transmission, seed=setup.seed)
        r = np.hypot(record.hit_mm[:, 0], record.hit_mm[:, 1])
        delivered = (record.status == int(Status.SAMPLE)) & (r <= scene.field_radius_mm)
        ratios.append(delivered.mean() / nominal_fraction)
    ratios = np.asarray(ratios)
    return Factor(
        "printed_surface_error",
        float(ratios.mean()),
        float(max(ratios.std(ddof=1) if samples > 1 else 0.0, 0.01)),
        True,
        f"{samples} traces with a {SURFACE_RMS_UM:g}-µm RMS smooth random surface on every collimator "
        "(cm2 illum robustness's model; the same rays)",
    )


def trace_design(design: SystemDesign, *, rays: int = 400_000, seed: int = 0) -> tuple[Any, Any, Any]:
    """The design's as-built illumination traced with its own LED and filter models: (scene, setup,
    record). ``design`` must have a collimator."""
    from cm2optics.illumination.as_built import as_built_scene
    from cm2optics.illumination.compare import setup_from_options
    from cm2optics.illumination.geometry import build_scene, collimator_from_design
    from cm2optics.illumination.tracer import trace

    setup = setup_from_options(design, rays=rays, seed=seed)
    scene = as_built_scene(build_scene(design, collimator_from_design(design)))
    return scene, setup, trace(scene, setup.source, rays, transmission=setup.transmission, seed=seed)


def excitation_power_chain(
    design: SystemDesign,
    *,
    rays: int = 400_000,
    seed: int = 0,
    surface_samples: int = 3,
    traced: tuple[Any, Any, Any] | None = None,
) -> dict[str, Any]:
    """Part (a): the traced excitation power, the chain of factors towards the paper's 75 mW and
    what remains unexplained (see the module docstring). ``design`` must have a collimator;
    ``traced``: its :func:`trace_design` (traced here with ``rays`` and ``seed`` when None)."""
    from cm2optics.illumination.metrics import figures_of_merit

    scene, setup, record = trace_design(design, rays=rays, seed=seed) if traced is None else traced
    figures = figures_of_merit(record, scene)
    predicted = figures.power_mw
    factors = [
        _photometric_factor(design),
        Factor(
            "drive_current",
            1.0,
            0.0,
            False,
            f"the preset's flux is already at the paper's {PAPER['drive_current_ma']['value']:g} mA "
            "(the LED's 1000-mA rating plays no part)",
        ),
        Factor(
            "led_thermal_droop",
            THERMAL_DROOP[0],
            THERMAL_DROOP[1] / THERMAL_DROOP[0],
            False,
            "assumed: blue InGaN flux at an ≈ 85 °C junction against 25 °C (no heat sink; the paper ran 1 h at "
            "300 mA without overheating)",
        ),
        *_meter_factors(design, record, scene),
        Factor(
            "excitation_filter",
            1.0,
            0.05,
            False,
            "already in the trace (the design's 470/40 model with its angle shift); ±5 %: the real coating's "
            "in-band transmission against the model",
        ),
        _surface_factor(scene, setup, figures.delivered_fraction.value, surface_samples),
    ]
    product = math.prod(f.value for f in factors)
    relative = math.sqrt(sum(f.uncertainty**2 for f in factors) + (predicted.stderr / predicted.value) ** 2)
    explained = predicted.value * product
    measured = PAPER["measured_power_mw"]["value"]
    remaining = measured / explained
    return {
        "measured_mw": measured,
        "measured_source": PAPER["measured_power_mw"]["source"],
        "predicted_mw": round(predicted.value, 2),
        "predicted_stderr_mw": round(predicted.stderr, 2),
        "predicted_ratio": round(predicted.value / measured, 3),
        "factors": [asdict(f) | {"value": round(f.value, 4), "uncertainty": round(f.uncertainty, 4)} for f in factors],
        "explained_mw": round(explained, 2),
        "explained_relative_uncertainty": round(relative, 4),
        "remaining_ratio": round(remaining, 3),
        "remaining_sigma_log": round(abs(math.log(remaining)) / relative, 2),
        "description": (
            f"the chain explains {predicted.value / explained:.2f}× of the {predicted.value / measured:.2f}× gap; "
            f"a factor {1 / remaining:.2f} (±{100 * relative:.0f} %) remains between {explained:.0f} mW and the "
            f"measured {measured:g} mW, {abs(math.log(remaining)) / relative:.1f}σ on a log scale: no factor "
            "of the chain accounts for it"
        ),
        "setup": {"design": design.name, "rays": rays, "seed": seed, "surface_samples": surface_samples},
    }

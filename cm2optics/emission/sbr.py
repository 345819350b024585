"""Signal and background at the sensor, and their ratio (SBR), for the two emission chains.

Both per photon the LEDs emit (:class:`~cm2optics.emission.filter_angles.Excitation`: where
each excitation ray lands on the sample plane, its direction and its share of those photons),
in photoelectrons summed over the sensor:

* signal: the fluorescence of the imaged field (``volume.field_mm``), excited by the light that
  lands in it, where it lands: each landing ray's power enters the sample (Fresnel
  transmittance at its angle, index ``surface_index``) and the fluorophore absorbs
  ``absorbed_fraction`` × (its relative excitation spectrum averaged over the excitation light)
  and re-emits with ``quantum_yield``, isotropically. Each fluorescence ray carries its share to
  the sensor through the interference filter at its angle, the film at its own angle, and the
  sensor's quantum efficiency. Light that lands outside the field excites nothing that is
  imaged, but it adds to the background.
* background: the excitation light itself, along two paths, from every ray that lands.
  (1) Scattered back by the sample (``diffuse_reflectance``) as a Lambertian glow where it lands
  (:func:`~cm2optics.emission.filter_angles.glow_from_hits`: tilted beams of finite width and
  spread reach beyond the imaged field). (2) Reflected specularly by the sample's flat surface
  (Fresnel, :func:`~cm2optics.emission.filter_angles.mirror_on_sample`): the shallow side of
  each tilted beam bounces back across the axis into the mask opening. Both meet the filter far
  more obliquely than the fluorescence (up to ≈ 45° against ≈ 27°), where its passband has slid
  onto the excitation band: that is the leakage the hybrid filter exists to stop.

Signal and background share one photon budget, so a beam that spends light outside the field
pays for it in SBR (counting the signal per *landed* photon instead would rank a bare LED, whose
wide beam lands mostly beyond the sensor's reach, above a collimated one). The excitation is
the design's model beams (:func:`~cm2optics.emission.filter_angles.model_excitation`: uniform
hard-edged cones of the étendue half-angle, no losses) unless a traced one is given
(:func:`cm2optics.illumination.traced_sbr.traced_sbr`): the model is for the spectra report;
a design decision takes the traced beam, whose tails and aim the model does not see.

Both are computed from one ray trace per source distribution
(:func:`~cm2optics.emission.filter_angles.trace_emission_rays`), binned by angle of incidence at
the filter and at the film, with spectra on 380–780 nm (photon units: power × λ).

The absolute SBR depends on the sample (absorption, yield, scattering); the gain of the
hybrid over the interference-only chain does not — the sample's numbers cancel in it.
Backgrounds that no filter removes (fluorescence from outside the field or out of focus,
autofluorescence of the sample or the printed housing) are not modelled; they cap the gain a
measurement can show.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.emission.filter_angles import (
    EmissionRays,
    Emitter,
    Excitation,
    binned_sources,
    glow_from_hits,
    mirror_on_sample,
    model_excitation,
    trace_from_sources,
    trace_rays,
)
from cm2optics.optics import first_order
from cm2optics.spectra.absorption import fresnel_transmittance
from cm2optics.spectra.chain import EmissionChain, emission_chain, excitation_spectrum
from cm2optics.spectra.library import load_spectrum
from cm2optics.spectra.spectrum import DEFAULT_WAVELENGTH_NM

__all__ = ["CHAINS", "SBRResult", "Sample", "signal_and_background"]

#: The two emission chains compared, by key.
CHAINS = ("interference_only", "hybrid")

_FINE_FILTER_DEG = 0.5  # integration bins of the angle at the interference filter
_FINE_FILM_DEG = 1.0  # and at the film


@dataclass(frozen=True)
class Sample:
    """What the sample does with the excitation light (per excitation photon).

    absorbed_fraction: fraction absorbed by the fluorophore at its excitation peak (0–1);
        default 1 %: a sparse bead phantom or weakly labelled tissue.
    quantum_yield: fluorescence photons per absorbed photon (0–1); default 0.9 (fluorescein beads;
        EGFP 0.6).
    diffuse_reflectance: fraction scattered back towards the device as a Lambertian glow (0–1);
        default 5 %: clear resin with beads (tissue: 20–40 %).
    surface_index: refractive index of the sample's flat top surface, for its specular (Fresnel)
        reflection (1–2.5); default 1.5: a resin block or a glass window (water 1.33; 1 turns the
        reflection off, for a rough surface).
    """

    absorbed_fraction: float = 0.01
    quantum_yield: float = 0.9
    diffuse_reflectance: float = 0.05
    surface_index: float = 1.5

    def __post_init__(self) -> None:
        for name in ("absorbed_fraction", "quantum_yield", "diffuse_reflectance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value <= 1):
                raise ValueError(f"{name} = {value!r}: must lie within 0–1 (> 0)")
        if not (math.isfinite(self.surface_index) and 1.0 <= self.surface_index <= 2.5):
            raise ValueError(f"surface_index = {self.surface_index!r}: must lie within 1–2.5")


@dataclass(frozen=True, eq=False)
class SBRResult:
    """Signal and background per angle-of-incidence bin at the interference filter.

    aoi_bin_edges_deg: bin edges, degrees.
    signal: per chain key (:data:`CHAINS`), photoelectrons per photon the LEDs emit in each bin.
    background_by_path: per path (``diffuse``, ``specular``), then per chain key, the same.
    field_radius_mm: radius of the fluorescent field, mm.
    glow_radius_mm: radius holding 95 % of the scattered excitation glow (within the sensor's reach), mm.
    excitation_landed: share of the LEDs' photons that land on the sample plane.
    excitation_in_field: share that enters the sample inside the field (after the surface's Fresnel loss).
    sample: the sample model. film_from_design: whether the hybrid film is the design's own
        (False: the library's default film was added to a design that has none).
    excitation_overlap: the fluorophore's relative excitation averaged over the excitation light.
    """

    aoi_bin_edges_deg: np.ndarray
    signal: dict[str, np.ndarray]
    background_by_path: dict[str, dict[str, np.ndarray]]
    field_radius_mm: float
    glow_radius_mm: float
    excitation_landed: float
    excitation_in_field: float
    sample: Sample
    film_from_design: bool
    excitation_overlap: float

    @property
    def background(self) -> dict[str, np.ndarray]:
        """Per chain key, the background of both paths in each bin."""
        return {chain: sum(path[chain] for path in self.background_by_path.values()) for chain in CHAINS}

    def sbr(self, chain: str) -> float:
        """Total signal / total background for ``chain`` (a key of :data:`CHAINS`)."""
        return float(self.signal[chain].sum() / self.background[chain].sum())

    def sbr_vs_angle(self, chain: str) -> np.ndarray:
        """Signal / background within each angle bin (NaN where a bin has no background)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.background[chain] > 0, self.signal[chain] / self.background[chain], np.nan)

    @property
    def sbr_interference_only(self) -> float:
        return self.sbr("interference_only")

    @property
    def sbr_hybrid(self) -> float:
        return self.sbr("hybrid")

    @property
    def sbr_gain(self) -> float:
        """SBR of the hybrid chain over that of the interference-only chain."""
        return self.sbr_hybrid / self.sbr_interference_only

    def to_dict(self) -> dict[str, Any]:
        """JSON-able figures: totals, gain, and per-angle signal, background and SBR."""

        def sig(x: float) -> float:
            return float(f"{x:.4g}")

        centres = 0.5 * (self.aoi_bin_edges_deg[1:] + self.aoi_bin_edges_deg[:-1])
        used = (self.signal["interference_only"] > 0) | (self.background["interference_only"] > 0)
        return {
            "sbr_interference_only": sig(self.sbr_interference_only),
            "sbr_hybrid": sig(self.sbr_hybrid),
            "sbr_gain": sig(self.sbr_gain),
            "signal_per_excitation_photon": {k: sig(v.sum()) for k, v in self.signal.items()},
            "background_per_excitation_photon": {k: sig(v.sum()) for k, v in self.background.items()},
            "background_by_path_per_excitation_photon": {
                path: {k: sig(v.sum()) for k, v in chains.items()} for path, chains in self.background_by_path.items()
            },
            "signal_transmission_hybrid_over_interference_only": sig(
                self.signal["hybrid"].sum() / self.signal["interference_only"].sum()
            ),
            "background_rejection_hybrid_over_interference_only": sig(
                self.background["interference_only"].sum() / self.background["hybrid"].sum()
            ),
            "field_radius_mm": round(self.field_radius_mm, 3),
            "glow_radius_mm": round(self.glow_radius_mm, 3),
            "excitation_landed": sig(self.excitation_landed),
            "excitation_in_field": sig(self.excitation_in_field),
            "film_from_design": self.film_from_design,
            "excitation_overlap": round(self.excitation_overlap, 4),
            "sample": {
                "absorbed_fraction": self.sample.absorbed_fraction,
                "quantum_yield": self.sample.quantum_yield,
                "diffuse_reflectance": self.sample.diffuse_reflectance,
                "surface_index": self.sample.surface_index,
            },
            "vs_angle": {
                "aoi_deg": [round(float(c), 2) for c in centres[used]],
                **{
                    f"{name}_{chain}": [sig(v) if math.isfinite(v) else None for v in values[used]]
                    for chain in CHAINS
                    for name, values in (
                        ("signal", self.signal[chain]),
                        ("background", self.background[chain]),
                        ("sbr", self.sbr_vs_angle(chain)),
                    )
                },
            },
        }


def _binned(rays: EmissionRays, filter_edges: np.ndarray, film_edges: np.ndarray) -> np.ndarray:
    weights, _, _ = np.histogram2d(
        np.degrees(rays.aoi_filter_rad),
        np.degrees(rays.aoi_film_rad),
        bins=(filter_edges, film_edges),
        weights=rays.power,
    )
    return weights


def _detected(
    weights: np.ndarray,
    chain: EmissionChain,
    photons: np.ndarray,
    qe: np.ndarray,
    filter_deg: np.ndarray,
    film_deg: np.ndarray,
) -> np.ndarray:
    """Photoelectrons per emitted photon in each filter-angle bin: Σ_film-bins W · ∫ n T_filter T_film QE dλ."""
    wavelength = DEFAULT_WAVELENGTH_NM
    step = np.gradient(wavelength)
    t_filter = chain.interference.transmittance(wavelength, np.radians(filter_deg)[:, None])
    if chain.film is None:
        t_film = np.ones((film_deg.size, wavelength.size))
    else:
        t_film = chain.film.transmittance(wavelength, np.radians(film_deg)[:, None])
    integral = (t_filter * (photons * qe * step)) @ t_film.T  # (filter bins, film bins)
    return np.sum(weights * integral, axis=1)


def signal_and_background(
    design: SystemDesign,
    sample: Sample = Sample(),
    excitation: Excitation | None = None,
    field_step_mm: float = 0.4,
    pupil_samples: int = 24,
    beam_samples: int = 16,
    glow_step_mm: float = 0.5,
    max_specular_rays: int = 200_000,
    seed: int = 0,
    bin_deg: float = 2.5,
) -> SBRResult:
    """Signal and background at the sensor for the interference-only and hybrid chains, per photon
    the LEDs emit.

    excitation: the light landing on the sample plane (default: the model beams,
        :func:`model_excitation` with ``beam_samples``; a trace's:
        :func:`cm2optics.illumination.traced_sbr.traced_excitation`).
    field_step_mm: grid of the fluorescent field's irradiance, mm; pupil_samples: directions per
        source along each side of the mask opening (see :func:`trace_from_sources`);
        glow_step_mm: grid of the scattered glow, mm; max_specular_rays: landed rays mirrored by
        the surface at most (drawn with ``seed``, their power scaled to the landed total).
    bin_deg: width of the reported angle-of-incidence bins, degrees (0.5–10).
    Raises ValueError when no excitation enters the field (no signal).
    """
    if not (math.isfinite(bin_deg) and 0.5 <= bin_deg <= 10):
        raise ValueError(f"bin_deg = {bin_deg!r}: must lie within 0.5–10°")
    if not (math.isfinite(field_step_mm) and 0.01 <= field_step_mm <= 2.0):
        raise ValueError(f"field_step_mm = {field_step_mm!r}: must lie within 0.01–2 mm")
    if not (isinstance(max_specular_rays, int) and max_specular_rays >= 1):
        raise ValueError(f"max_specular_rays = {max_specular_rays!r}: must be an integer ≥ 1")
    excitation = model_excitation(design, beam_samples) if excitation is None else excitation
    hits, directions, power = excitation.hits_mm, excitation.directions, excitation.power
    entering = power * fresnel_transmittance(np.arccos(np.clip(np.abs(directions[:, 2]), 0, 1)), sample.surface_index)
    inside = np.hypot(hits[:, 0], hits[:, 1]) <= design.volume.field_mm / 2
    in_field = float(entering[inside].sum())
    if not in_field > 0:
        raise ValueError("no excitation light lands in the imaged field: no signal to compute an SBR from")
    glow, glow_power = glow_from_hits(design, hits, power, glow_step_mm)
    heading = np.flatnonzero(directions[:, 2] > 0)  # directions known at landing
    pick = heading[np.random.default_rng(seed).permutation(heading.size)[:max_specular_rays]]
    origins = np.column_stack([hits[pick], np.full(pick.size, first_order.object_plane_z_mm(design))])
    scale = power[heading].sum() / power[pick].sum() if pick.size else 0.0
    mirrored = mirror_on_sample(origins, directions[pick], power[pick] * scale, sample.surface_index)

    signal_rays = trace_from_sources(
        design, binned_sources(hits[inside], entering[inside], field_step_mm), Emitter.ISOTROPIC, pupil_samples
    )
    background_rays = {
        "diffuse": trace_from_sources(design, glow, Emitter.LAMBERTIAN, pupil_samples),
        "specular": trace_rays(design, *mirrored),
    }
    background_scale = {"diffuse": sample.diffuse_reflectance * glow_power, "specular": 1.0}

    wavelength = DEFAULT_WAVELENGTH_NM
    excitation_photons = excitation_spectrum(design).values * wavelength
    excitation_photons = excitation_photons / np.trapezoid(excitation_photons, wavelength)
    overlap = float(np.trapezoid(excitation_photons * load_spectrum("gfp-excitation")(wavelength), wavelength))
    emission_photons = load_spectrum("gfp-emission")(wavelength) * wavelength
    emission_photons = emission_photons / np.trapezoid(emission_photons, wavelength)
    qe = load_spectrum("imx178-qe")(wavelength)
    fluorescence_per_photon = in_field * sample.absorbed_fraction * overlap * sample.quantum_yield

    top = 90.0
    filter_edges = np.arange(0.0, top + _FINE_FILTER_DEG / 2, _FINE_FILTER_DEG)
    film_edges = np.arange(0.0, top + _FINE_FILM_DEG / 2, _FINE_FILM_DEG)
    filter_deg = 0.5 * (filter_edges[1:] + filter_edges[:-1])
    film_deg = 0.5 * (film_edges[1:] + film_edges[:-1])
    w_signal = _binned(signal_rays, filter_edges, film_edges)
    w_background = {path: _binned(rays, filter_edges, film_edges) for path, rays in background_rays.items()}

    coarse_edges = np.arange(0.0, top + bin_deg / 2, bin_deg)
    coarse_index = np.clip(np.digitize(filter_deg, coarse_edges) - 1, 0, coarse_edges.size - 2)

    def coarse(values: np.ndarray) -> np.ndarray:
        return np.bincount(coarse_index, weights=values, minlength=coarse_edges.size - 1)

    hybrid = emission_chain(design)
    chains = {"interference_only": hybrid.without_film(), "hybrid": hybrid}
    signal = {
        key: coarse(_detected(w_signal, chain, emission_photons, qe, filter_deg, film_deg) * fluorescence_per_photon)
        for key, chain in chains.items()
    }
    background = {
        path: {
            key: coarse(
                _detected(weights, chain, excitation_photons, qe, filter_deg, film_deg) * background_scale[path]
            )
            for key, chain in chains.items()
        }
        for path, weights in w_background.items()
    }
    return SBRResult(
        aoi_bin_edges_deg=coarse_edges,
        signal=signal,
        background_by_path=background,
        field_radius_mm=design.volume.field_mm / 2,
        glow_radius_mm=glow.radius_mm(0.95),
        excitation_landed=float(power.sum()),
        excitation_in_field=in_field,
        sample=sample,
        film_from_design=design.absorption_filter is not None,
        excitation_overlap=overlap,
    )

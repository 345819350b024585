"""Signal and background at the sensor, and their ratio (SBR), for the two emission chains.

Per excitation photon delivered to the sample, in photoelectrons summed over the sensor:

* signal: the fluorophore absorbs ``absorbed_fraction`` × (its relative excitation spectrum
  averaged over the excitation light) and re-emits with ``quantum_yield``, isotropically,
  from points spread evenly over the imaged field (``volume.field_mm``). Each ray carries
  its share to the sensor through the interference filter at its angle, the film at its own
  angle, and the sensor's quantum efficiency.
* background: the excitation light itself, along two paths. (1) Scattered back by the sample
  (``diffuse_reflectance``) as a Lambertian glow wherever the LED beams land
  (:func:`~cm2optics.emission.filter_angles.excitation_footprint`: four tilted beams of finite width
  and étendue-limited spread reach beyond the imaged field). (2) Reflected specularly by the
  sample's flat surface (Fresnel, index ``surface_index``;
  :func:`~cm2optics.emission.filter_angles.specular_rays`): the shallow edge of each 45° beam
  bounces back across the axis into the mask opening. Both meet the filter far more
  obliquely than the fluorescence (up to ≈ 45° against ≈ 27°), where its passband has slid
  onto the excitation band: that is the leakage the hybrid filter exists to stop.

Both are computed from one ray trace per source distribution
(:func:`~cm2optics.emission.filter_angles.trace_emission_rays`), binned by angle of incidence at
the filter and at the film, with spectra on 380–780 nm (photon units: power × λ).

The absolute SBR depends on the sample (absorption, yield, scattering); the gain of the
hybrid over the interference-only chain does not — the sample's numbers cancel in it.
Backgrounds that no filter removes (out-of-focus fluorescence, autofluorescence of the
sample or the printed housing) are not modelled; they cap the gain a measurement can show.
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
    Sources,
    excitation_footprint,
    field_sources,
    specular_rays,
    trace_from_sources,
    trace_rays,
)
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
    signal: per chain key (:data:`CHAINS`), photoelectrons per excitation photon in each bin.
    background_by_path: per path (``diffuse``, ``specular``), then per chain key, the same.
    field_radius_mm: radius of the fluorescent field, mm.
    glow_radius_mm: radius holding 95 % of the scattered excitation glow, mm.
    sample: the sample model. film_from_design: whether the hybrid film is the design's own
        (False: the library's default film was added to a design that has none).
    excitation_overlap: the fluorophore's relative excitation averaged over the excitation light.
    """

    aoi_bin_edges_deg: np.ndarray
    signal: dict[str, np.ndarray]
    background_by_path: dict[str, dict[str, np.ndarray]]
    field_radius_mm: float
    glow_radius_mm: float
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
    glow: Sources | None = None,
    specular: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    field_step_mm: float = 0.4,
    pupil_samples: int = 24,
    beam_samples: int = 16,
    bin_deg: float = 2.5,
) -> SBRResult:
    """Signal and background at the sensor for the interference-only and hybrid chains.

    glow: where the diffusely scattered excitation light comes from (default:
        :func:`excitation_footprint`).
    specular: the excitation mirrored by the sample's surface, (origins_mm, directions, power)
        as :func:`specular_rays` gives them (default: the model beams' own, ``beam_samples``;
        a traced illumination's: :func:`cm2optics.illumination.traced_sbr.traced_background`).
    field_step_mm: spacing of the fluorescent source points, mm; pupil_samples: directions per
        source along each side of the mask opening (see :func:`trace_from_sources`);
        beam_samples: sampling of each LED beam for the specular reflection (:func:`specular_rays`).
    bin_deg: width of the reported angle-of-incidence bins, degrees (0.5–10).
    """
    if not (math.isfinite(bin_deg) and 0.5 <= bin_deg <= 10):
        raise ValueError(f"bin_deg = {bin_deg!r}: must lie within 0.5–10°")
    glow = excitation_footprint(design) if glow is None else glow
    signal_rays = trace_from_sources(design, field_sources(design, field_step_mm), Emitter.ISOTROPIC, pupil_samples)
    background_rays = {
        "diffuse": trace_from_sources(design, glow, Emitter.LAMBERTIAN, pupil_samples),
        "specular": trace_rays(
            design, *(specular if specular is not None else specular_rays(design, sample.surface_index, beam_samples))
        ),
    }
    background_scale = {"diffuse": sample.diffuse_reflectance, "specular": 1.0}

    wavelength = DEFAULT_WAVELENGTH_NM
    excitation = excitation_spectrum(design)
    excitation_photons = excitation.values * wavelength
    excitation_photons = excitation_photons / np.trapezoid(excitation_photons, wavelength)
    overlap = float(np.trapezoid(excitation_photons * load_spectrum("gfp-excitation")(wavelength), wavelength))
    emission_photons = load_spectrum("gfp-emission")(wavelength) * wavelength
    emission_photons = emission_photons / np.trapezoid(emission_photons, wavelength)
    qe = load_spectrum("imx178-qe")(wavelength)
    fluorescence_per_photon = sample.absorbed_fraction * overlap * sample.quantum_yield

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
        sample=sample,
        film_from_design=design.absorption_filter is not None,
        excitation_overlap=overlap,
    )

"""Collimate through the excitation filter, spread after it: the ceiling of that architecture (issue 16).

Three measured factors bound what a unit can deliver when a clear spreader after the filter
shapes the beam (the authors' LED profile, spectrum and excitation coating table throughout):

* the filter's share of the LED's power for each angle of incidence
  (:func:`~cm2optics.illumination.bounds.filter_throughput`), and its mean over a uniform-radiance
  cone of the étendue-limited half-angle (the tightest any optic can make the 1 × 1-mm die's
  beam through the 4-mm flange or the 3.4-mm clear aperture); also with the Fresnel loss of the
  filter's bare back face (N-BK7 into air), which the tracer leaves out (it applies the coating's
  T once);
* the beam each part actually sends to the filter (traced without the filter: the share that
  leaves the unit, its angles p50 / p90, the filter's mean share over it, ⟨T⟩, and their
  product L⟨T⟩ — what passes the filter); collimating variants of the enclosed-die part in
  wider units (the designed collimating wall needs a ≥ 5.1-mm footprint) are traced too, with
  the tower clash of their housings stated;
* the spreader's two bare faces (clear resin, normal incidence; one face when it is printed on,
  or cemented to, the filter) and the circle share at CV ≤ 10 % of a revolved or freeform beam
  with the finite LED (:func:`~cm2optics.illumination.bounds.uniform_beam_bound`, at each
  design's placement).

    .venv/bin/python benchmarks/illum_filter_lever.py --rays 200000 --out lever.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from illum_ray_families import reference_inputs

from cm2optics.design import load_preset
from cm2optics.design.materials import Material, refractive_index
from cm2optics.formats.outputs import OutputError, check_output
from cm2optics.illumination.bounds import etendue_blur_rad, filter_throughput, uniform_beam_bound
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.tracer import trace
from cm2optics.optics.layout import unit_clashes
from cm2optics.spectra.absorption import fresnel_transmittance

ROOT = Path(__file__).resolve().parents[1]
ENCLOSED = str(ROOT / "benchmarks/designs/cm2-v2-enclosed-spread.yaml")
ANGLES_DEG = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 50.0, 60.0)
DESIGN_WAVELENGTH_NM = 470.0


def collimating_unit(design, side_mm: float, height_mm: float):
    """The enclosed-die part with both sub-beams collimated (no spread), in a unit whose filter,
    part and housing are ``side_mm`` wide (housing 1.5 mm wider), the filter on its exit face."""
    return design.with_changes(
        {
            "collimator.lens_spread_deg": 0.0,
            "collimator.tir_spread_deg": 0.0,
            "collimator.tir_crossing": False,
            "collimator.footprint_mm": side_mm,
            "collimator.height_mm": height_mm,
            "led_array.excitation_gap_mm": design.collimator.led_gap_mm + height_mm,
            "excitation_filter.width_mm": side_mm,
            "excitation_filter.length_mm": side_mm,
            "led_housing.outer_mm": side_mm + 1.5,
        }
    )


def back_face(aoi_rad: np.ndarray) -> np.ndarray:
    """Transmittance of the filter's bare N-BK7 back face for a ray that met the coating at
    ``aoi_rad`` in air (the same angle in air on the way out), at the design wavelength."""
    return fresnel_transmittance(aoi_rad, float(refractive_index(Material.N_BK7, DESIGN_WAVELENGTH_NM)))


def cone_mean(values: np.ndarray, angles_rad: np.ndarray, half_angle_rad: float) -> float:
    """Mean of ``values`` (sampled on ``angles_rad``) over a cone of uniform radiance: weight
    sin θ cos θ up to ``half_angle_rad``."""
    weight = np.sin(angles_rad) * np.cos(angles_rad) * (angles_rad <= half_angle_rad)
    return float(np.sum(weight * values) / np.sum(weight))


def beam_at_filter(design, collimator, setup, rays: int, seed: int) -> dict:
    """Trace ``design`` without its filter: the share leaving the unit, its angles to the unit's
    axis and the filter's mean share over it."""
    scene = build_scene(design, collimator, excitation_filter=False)
    record = trace(scene, setup.source, rays, seed=seed)
    out = record.passed
    cos_axis = np.einsum("ij,ij->i", record.exit_direction[out], scene.unit_axes[record.unit[out]])
    angle = np.arccos(np.clip(cos_axis, -1.0, 1.0))
    passed = setup.transmission(record.wavelength_nm[out], angle)
    leaves = float(out.mean())
    mean_t = float(passed.mean())
    return {
        "leaves_unit": round(leaves, 4),
        "p50_deg": round(float(np.degrees(np.percentile(angle, 50))), 2),
        "p90_deg": round(float(np.degrees(np.percentile(angle, 90))), 2),
        "filter_mean_T": round(mean_t, 4),
        "filter_mean_T_with_back_face": round(float((passed * back_face(angle)).mean()), 4),
        "passes_filter": round(leaves * mean_t, 4),
        "passes_filter_stderr": round(float(np.sqrt(leaves * mean_t * (1 - leaves * mean_t) / record.rays)), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=200_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=None, help="JSON file for the tables")
    args = parser.parse_args()
    if args.out:
        try:
            check_output(args.out, command="illum_filter_lever", inputs=[str(ENCLOSED)], overwrite=True)
        except OutputError as error:
            parser.error(str(error))
    enclosed = load_preset(ENCLOSED)
    setup, authors = reference_inputs(enclosed)
    report: dict = {"inputs": "authors' LED profile, spectrum and excitation coating table", "rays": args.rays}

    grid = np.radians(np.linspace(0.0, 60.0, 241))
    share = filter_throughput(enclosed, grid, setup.transmission, setup.source.spectrum)
    with_back = share * back_face(grid)
    report["filter_by_angle"] = [
        {
            "aoi_deg": a,
            "T": round(float(np.interp(math.radians(a), grid, share)), 4),
            "T_with_back_face": round(float(np.interp(math.radians(a), grid, with_back)), 4),
        }
        for a in ANGLES_DEG
    ]
    flange = math.asin(enclosed.led.emitter_mm / enclosed.collimator.footprint_mm)
    cones = {"etendue_4mm_flange": flange, "etendue_clear_aperture": etendue_blur_rad(enclosed)}
    cones |= {f"uniform_{a:g}deg": math.radians(a) for a in (10, 20, 25, 30)}
    report["filter_over_cones"] = {
        name: {
            "half_angle_deg": round(math.degrees(alpha), 2),
            "T": round(cone_mean(share, grid, alpha), 4),
            "T_with_back_face": round(cone_mean(with_back, grid, alpha), 4),
        }
        for name, alpha in cones.items()
    }
    n_resin = float(refractive_index(enclosed.collimator.material, DESIGN_WAVELENGTH_NM))
    face = float(fresnel_transmittance(0.0, n_resin))
    report["spreader_faces"] = {
        "resin_index": round(n_resin, 4),
        "two_faces": round(face**2, 4),
        "one_face": round(face, 4),
    }

    designs = {
        "cm2-v2 (default, ff4 close aim)": load_preset("cm2-v2"),
        "enclosed, spreading wall": enclosed,
        "collimating, 5.1-mm unit": collimating_unit(enclosed, 5.1, 2.8),
        "collimating, 6.0-mm unit": collimating_unit(enclosed, 6.0, 3.5),
    }
    beams = {}
    for label, design in designs.items():
        beams[label] = beam_at_filter(design, collimator_from_design(design), setup, args.rays, args.seed)
        clashes = unit_clashes(design)
        beams[label]["housing_clash"] = clashes[0] if clashes else None
        for freeform in (False, True):
            bound = uniform_beam_bound(
                design,
                finite_source=True,
                freeform=freeform,
                **({"cells": 24, "rays_per_ring": 4000} if freeform else {}),
            )
            beams[label]["circle_share_freeform" if freeform else "circle_share_revolved"] = bound["output_bound"]
        print(label, json.dumps(beams[label]), flush=True)
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import PAPER_COLLIMATOR  # a 2.0-mm excitation gap: the authors' 2.0-mm part under its filter

    paper = load_preset("cm2-v2").with_changes(PAPER_COLLIMATOR)
    beams["authors' part (STL)"] = beam_at_filter(paper, authors, setup, args.rays, args.seed)
    print("authors' part (STL)", json.dumps(beams["authors' part (STL)"]), flush=True)
    report["beams"] = beams
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    sys.exit(main())

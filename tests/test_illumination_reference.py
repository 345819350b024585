"""The authors' printed collimator traced beside V1 and the cm2-v2 CAD part, in one setup.

Uses the original device's reference data (LED angular profile and spectrum, the excitation
coating's angle table, the authors' STL) from ``../shared/reference/cm2-v2``; skipped when it
is absent. The numbers asserted are this tracer's (200 000 rays, tolerances ≫ the Monte Carlo
error); the comments say how they relate to the paper's.
"""

from __future__ import annotations

import pytest

from cm2optics.illumination.compare import V1_LABEL, compare_designs, configurations, setup_from_options, stl_collimator


@pytest.fixture(scope="module")
def authors_stl(reference_dir, v2):
    return stl_collimator(v2, reference_dir / "CM2_V2_freeform_illuminator.stl", [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])


@pytest.fixture(scope="module")
def reference_setup(reference_dir, v2):
    def make(**kwargs):
        return setup_from_options(
            v2,
            led_profile=reference_dir / "led_angular_profile.csv",
            led_spectrum=reference_dir / "led_spectrum.csv",
            filter_table=reference_dir / "coating_real_ex.csv",
            rays=200_000,
            **kwargs,
        )

    return make


def test_bare_trace_of_the_authors_part(v2, authors_stl, reference_setup):
    """No filter, no housing: the unit 45° and 6.7 mm off-axis, its exit face ≈ 9.5 mm from the
    field centre. Measured: ≈ 85 % of the LED's power leaves forwards, ≈ 75 % within 30° of the
    axis, ≈ 60 % lands inside the 8-mm circle. (The issue's quick trace said ≈ 90/50/25 %; this
    tracer agrees ray for ray with the independent NumPy tracer and with the closed-form tests,
    and the point-source exit angles — lens rays within 3°, TIR rays at 13–18°, only the 26–35°
    band uncollimated — explain a ≈ 17° median beam.)"""
    setup = reference_setup(excitation_filter=False, housing=False)
    (bare,) = compare_designs(v2, setup, [("authors' part, bare", authors_stl)])
    assert bare.throughput.value == pytest.approx(0.85, abs=0.03)
    assert bare.fraction_within_30deg.value == pytest.approx(0.75, abs=0.04)
    assert bare.delivered_fraction.value == pytest.approx(0.60, abs=0.04)


def test_three_designs_side_by_side(v2, authors_stl, reference_setup):
    setup = reference_setup()
    v1, cad, authors = compare_designs(v2, setup, configurations(v2, authors_stl))
    assert v1.label == V1_LABEL
    # Power through the filter / LED power: V1 ≈ 27 %, the paper's "≈ 24 % (V1)".
    assert v1.throughput.value == pytest.approx(0.27, abs=0.03)
    # The authors' part passes ≈ 63 % (the paper's Zemax said ≈ 80 %: the filter alone passes
    # only 86 % of this LED's spectrum even at normal incidence, and the light it reflects is
    # lost on the LED board here).
    assert authors.throughput.value == pytest.approx(0.63, abs=0.03)
    # Into the 8-mm circle: V1 ≈ 8 %, the authors' part ≈ 51 % — but as a central spot (CV ≈ 57 %).
    assert v1.delivered_fraction.value == pytest.approx(0.08, abs=0.02)
    assert authors.delivered_fraction.value == pytest.approx(0.51, abs=0.03)
    assert authors.uniformity_cv.value > 0.4
    # The cm2-v2 CAD part sits in between.
    assert v1.delivered_fraction.value < cad.delivered_fraction.value < authors.delivered_fraction.value
    for figures in (v1, cad, authors):
        ledger = figures.ledger
        assert ledger["delivered"].value + ledger["absorbed"].value + ledger["escaped"].value == pytest.approx(
            1.0, abs=1e-9
        )

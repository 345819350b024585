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
def authors_stl(reference_dir, v2_collimating):
    """The authors' part at the paper's placement (45° / 6.7 mm, aimed at the field centre)."""
    return stl_collimator(
        v2_collimating, reference_dir / "CM2_V2_freeform_illuminator.stl", [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]
    )


@pytest.fixture(scope="module")
def reference_setup(reference_dir):
    def make(design, **kwargs):
        return setup_from_options(
            design,
            led_profile=reference_dir / "led_angular_profile.csv",
            led_spectrum=reference_dir / "led_spectrum.csv",
            filter_table=reference_dir / "coating_real_ex.csv",
            rays=200_000,
            **kwargs,
        )

    return make


def test_bare_trace_of_the_authors_part(v2_collimating, authors_stl, reference_setup):
    """No filter, no housing: the unit 45° and 6.7 mm off-axis, its exit face ≈ 9.5 mm from the
    field centre. Measured: ≈ 85 % of the LED's power leaves forwards, ≈ 75 % within 30° of the
    axis, ≈ 60 % lands inside the 8-mm circle. (The issue's quick trace said ≈ 90/50/25 %; this
    tracer agrees ray for ray with the independent NumPy tracer and with the closed-form tests,
    and the point-source exit angles — lens rays within 3°, TIR rays at 13–18°, only the 26–35°
    band uncollimated — explain a ≈ 17° median beam.)"""
    setup = reference_setup(v2_collimating, excitation_filter=False, housing=False)
    (bare,) = compare_designs(v2_collimating, setup, [("authors' part, bare", authors_stl)])
    assert bare.throughput.value == pytest.approx(0.85, abs=0.03)
    assert bare.fraction_within_30deg.value == pytest.approx(0.75, abs=0.04)
    assert bare.delivered_fraction.value == pytest.approx(0.60, abs=0.04)


def test_three_designs_side_by_side(v2_collimating, authors_stl, reference_setup):
    """At the paper's placement, with the paper's collimating architecture for the CAD part."""
    setup = reference_setup(v2_collimating)
    v1, cad, authors = compare_designs(v2_collimating, setup, configurations(v2_collimating, authors_stl))
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
    # The collimating CAD part sits in between.
    assert v1.delivered_fraction.value < cad.delivered_fraction.value < authors.delivered_fraction.value
    for figures in (v1, cad, authors):
        ledger = figures.ledger
        assert ledger["delivered"].value + ledger["absorbed"].value + ledger["escaped"].value == pytest.approx(
            1.0, abs=1e-9
        )


def test_the_default_design_is_uniform_and_delivers_what_was_measured(v2, reference_setup):
    """cm2-v2 as shipped (the uniform design of issue 16): at 10⁶ rays it delivers 0.3149 ± 0.0005
    of the LEDs' power at CV 9.50 % (noise floor 2.5 %, noise-free 9.2 %; BENCHMARKS.md). Here at
    2 × 10⁵ rays: the delivered fraction within ≈ 5 of its standard errors, and the noise-free CV
    (√(CV² − floor²)) within 10 % — the paper's architecture at its placement gives ≈ 35 %."""
    import math

    setup = reference_setup(v2)
    _, cad = compare_designs(v2, setup, configurations(v2, None))
    assert cad.delivered_fraction.value == pytest.approx(0.3149, abs=0.005)
    noise_free_cv = math.sqrt(max(cad.uniformity_cv.value**2 - cad.uniformity_cv_noise**2, 0.0))
    assert 0.06 < noise_free_cv <= 0.10


def _independent_bare_trace(stl_path, profile_csv, emitter_z_mm: float, rays: int = 60_000, seed: int = 1):
    """A second, independent tracer for the bare authors' part: trimesh's ray casting, its own
    LED sampling and its own unit placement (nothing shared with ``cm2optics.illumination``).

    LED: 1 × 1 mm square at z = ``emitter_z_mm`` in the STL's frame, emitting towards −z with
    the tabulated I(θ). Faceted surfaces, unpolarised Fresnel, TIR, n = 1.5. The unit is
    tilted 45° with its exit face 9.5 mm from the field centre. Returns (forward fraction,
    fraction within 30° of the axis, fraction landing in the 8-mm circle)."""
    import numpy as np
    import trimesh

    rng = np.random.default_rng(seed)
    mesh = trimesh.load_mesh(stl_path)
    table = np.loadtxt(profile_csv, delimiter=",", skiprows=1)
    theta = np.linspace(0.0, np.pi / 2, 2001)
    cdf = np.cumsum(np.interp(np.degrees(theta), table[:, 0], table[:, 1]) * np.sin(theta))
    t = np.interp(rng.random(rays), cdf / cdf[-1], theta)
    phi = rng.uniform(0.0, 2 * np.pi, rays)
    d = np.column_stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), -np.cos(t)])
    o = np.column_stack(
        [rng.uniform(-0.5, 0.5, rays), rng.uniform(-0.5, 0.5, rays), np.full(rays, emitter_z_mm + 1e-4)]
    )
    alive = np.ones(rays, bool)
    for _ in range(40):
        idx = np.flatnonzero(alive)
        points, ray_of, tri = mesh.ray.intersects_location(o[idx], d[idx], multiple_hits=False)
        hit = idx[ray_of]
        alive[np.setdiff1d(idx, hit)] = False  # left the part for good
        normal = mesh.face_normals[tri]
        cos_i = -np.einsum("ij,ij->i", d[hit], normal)
        entering = cos_i > 0
        n1, n2 = np.where(entering, 1.0, 1.5), np.where(entering, 1.5, 1.0)
        normal = np.where(entering[:, None], normal, -normal)
        cos_i = np.abs(cos_i)
        eta = n1 / n2
        k = 1 - eta**2 * (1 - cos_i**2)
        cos_t = np.sqrt(np.clip(k, 0, None))
        rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
        rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
        reflect = rng.random(hit.size) < np.where(k < 0, 1.0, (rs + rp) / 2)
        new = np.where(
            reflect[:, None],
            d[hit] + 2 * cos_i[:, None] * normal,
            eta[:, None] * d[hit] + (eta * cos_i - cos_t)[:, None] * normal,
        )
        d[hit] = new / np.linalg.norm(new, axis=1, keepdims=True)
        o[hit] = points + 1e-5 * d[hit]
        if not alive.any():
            break
    forward = d[:, 2] < 0
    within_30 = -d[:, 2] > np.cos(np.radians(30.0))
    # Unit frame → device frame: the unit axis (−z of the STL) points at the field centre.
    tilt = np.radians(45.0)
    axis = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    rotation = np.column_stack([[np.cos(tilt), 0.0, np.sin(tilt)], [0.0, 1.0, 0.0], -axis])
    start = (o - [0.0, 0.0, -1.0]) @ rotation.T - 9.5 * axis
    direction = d @ rotation.T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -start[:, 2] / direction[:, 2]
    landing = start[:, :2] + s[:, None] * direction[:, :2]
    in_circle = forward & (s > 0) & (np.hypot(landing[:, 0], landing[:, 1]) < 4.0)
    return forward.mean(), within_30.mean(), in_circle.mean()


def test_an_independent_tracer_agrees_on_the_authors_part(reference_dir):
    """Our figures for the bare authors' part come back from a tracer that shares no code with
    ours: ≈ 87 / 75 / 56 % (forward / within 30° / in the circle) on the faceted mesh, where ours
    gives 85 / 74 / 56 % with ``--flat-normals --no-housing`` (60 % in the circle with smooth
    normals). The issue's ≈ 90 / 50 / 25 % is what this tracer gives with the emitter 0.5 mm down
    inside the cavity (≈ 86 / 47 / 30 %), not at its mouth."""
    stl, profile = reference_dir / "CM2_V2_freeform_illuminator.stl", reference_dir / "led_angular_profile.csv"
    forward, within_30, in_circle = _independent_bare_trace(stl, profile, emitter_z_mm=1.0)
    assert forward == pytest.approx(0.87, abs=0.03)
    assert within_30 == pytest.approx(0.75, abs=0.03)
    assert in_circle == pytest.approx(0.56, abs=0.04)
    forward, within_30, in_circle = _independent_bare_trace(stl, profile, emitter_z_mm=0.5)
    assert within_30 == pytest.approx(0.47, abs=0.04)
    assert in_circle == pytest.approx(0.30, abs=0.04)

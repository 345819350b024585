"""Gradients of the illumination objective through Dr.Jit: the Zernike slopes, the rim-holding
piston, the gradient against finite differences of the same objective, and the CLI's gradient search."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.design import load_preset
from cm2optics.optics.freeform import lens_sag_mm, rim_piston_um, zernike, zernike_with_gradient

TERMS = (3, 4, 6, 7, 11)


def test_zernike_slopes_are_the_derivatives_of_the_polynomials():
    rng = np.random.default_rng(0)
    radius = 0.5
    x, y = rng.uniform(-0.35, 0.35, (2, 200))
    h = 1e-6

    def z(j, x, y):
        return zernike(j, np.hypot(x, y) / radius, np.arctan2(y, x))

    for j in range(1, 29):
        value, zx, zy = zernike_with_gradient(j, x, y, radius, np)
        np.testing.assert_allclose(value, z(j, x, y), atol=1e-9)
        np.testing.assert_allclose(zx, (z(j, x + h, y) - z(j, x - h, y)) / (2 * h), atol=2e-5)
        np.testing.assert_allclose(zy, (z(j, x, y + h) - z(j, x, y - h)) / (2 * h), atol=2e-5)


def test_rim_piston_holds_the_rim_of_the_symmetric_terms():
    radius = 0.5
    phi = np.linspace(0, 2 * np.pi, 7)
    x, y = radius * np.cos(phi), radius * np.sin(phi)
    c = [0.0, 4.0, -3.0, 0.0, 2.5]  # Noll 3, 4, 6, 7, 11: only 4 and 11 are symmetric
    piston = rim_piston_um(TERMS, c)
    assert piston == pytest.approx(-(np.sqrt(3) * 4.0 + np.sqrt(5) * 2.5))
    symmetric = [0.0] * 11
    symmetric[0], symmetric[3], symmetric[10] = piston, 4.0, 2.5
    np.testing.assert_allclose(lens_sag_mm(tuple(symmetric), x, y, radius), 0.0, atol=1e-12)
    assert lens_sag_mm(tuple(symmetric), np.array([0.0]), np.array([0.0]), radius)[0] != 0.0  # the lens moves


def test_projected_step_climbs_d_and_lands_cv_on_its_limit():
    from cm2optics.illumination.gradient_search import projected_step

    gd, gc = np.array([2e-4, 1e-4, 0.0]), np.array([3e-3, -1e-3, 2e-3])  # 1/µm, like dD/dc and dCV′/dc
    # Inside, a step that stays inside: the full length along dD/dc.
    np.testing.assert_allclose(projected_step(gd, gc, 0.05, 0.10, 2.0), 2.0 * gd / np.linalg.norm(gd))
    # Outside (CV′ 0.103): the linearised CV′ lands on 0.10 and D still rises.
    for cv in (0.103, 0.097):  # and inside, where the full step would take CV′ past the limit
        step = projected_step(gd, gc, cv, 0.10, 2.0)
        assert cv + step @ gc == pytest.approx(0.10, abs=1e-12)
        assert step @ gd > 0
        tangent = step - (step @ gc) / (gc @ gc) * gc
        assert np.linalg.norm(tangent) == pytest.approx(2.0)
    # Far outside, the Newton step back is capped at the step length.
    step = projected_step(gd, gc, 0.5, 0.10, 2.0)
    assert -(step @ gc) / np.linalg.norm(gc) == pytest.approx(2.0)


@pytest.fixture(scope="module")
def jit():
    from cm2optics.optics.backend import is_jit, mitsuba

    mitsuba()
    if not is_jit():
        pytest.skip("gradients need Dr.Jit's LLVM or CUDA variant")


def test_rim_band_rays_are_re_aimed_onto_either_side_of_the_lens_rim(jit):
    """The boundary term's rays (cm2-v2 with 10 µm of coma, so that the rim's height varies by
    ±28 µm round the cavity): re-aimed 2 µm below the rim they meet the cavity wall (a vertical
    facet at r = a), 2 µm above it the lens (a facet facing the LED), every one of them; and the
    band holds about twice the rays when twice as wide."""
    from cm2optics.illumination.differentiable import _rim_crossings
    from cm2optics.illumination.geometry import build_scene
    from cm2optics.illumination.optimize import candidate_collimator
    from cm2optics.illumination.scene import mitsuba_scene
    from cm2optics.illumination.source import led_source
    from cm2optics.illumination.tracer import emit_rays
    from cm2optics.optics.backend import mitsuba
    from cm2optics.optics.collimator import collimator_profile

    mi = mitsuba()
    design, mesh, _ = candidate_collimator(load_preset("cm2-v2"), {"collimator.lens_freeform_um[7]": 10.0})
    scene = build_scene(design, mesh, excitation_filter=False, housing=False)  # the first hits need the parts only
    batch = emit_rays(scene, led_source(design), 20_000, 3)
    rim = _rim_crossings(scene, batch, 0.04)
    wider = _rim_crossings(scene, batch, 0.08)
    assert 60 < len(rim.index) and abs(len(wider.index) / len(rim.index) - 2.0) < 0.4, (
        len(rim.index),
        len(wider.index),
    )
    msc = mitsuba_scene(scene)
    rotation = scene.poses[batch.unit[rim.index], :3, :3]
    shift = scene.poses[batch.unit[rim.index], :3, 3]
    a = collimator_profile(design).cavity_radius_mm

    def first_hit(direction):
        def f32(v):
            return mi.Float(np.ascontiguousarray(v, np.float32))

        origin = batch.origin_mm[rim.index]
        si = msc.scene.ray_intersect(
            mi.Ray3f(
                mi.Point3f(*(f32(origin[:, k]) for k in range(3))),
                mi.Vector3f(*(f32(direction[:, k]) for k in range(3))),
            )
        )
        normal = np.stack([si.n.x.numpy(), si.n.y.numpy(), si.n.z.numpy()], 1)
        point = np.stack([si.p.x.numpy(), si.p.y.numpy(), si.p.z.numpy()], 1) - shift
        return np.einsum("nji,nj->ni", rotation, normal), np.einsum("nji,nj->ni", rotation, point)  # LED frame

    normal, point = first_hit(rim.below)
    assert np.all(np.abs(normal[:, 2]) < 0.05) and np.allclose(np.hypot(point[:, 0], point[:, 1]), a, atol=2e-4)
    normal, point = first_hit(rim.above)
    assert np.all(normal[:, 2] < -0.3) and np.all(np.hypot(point[:, 0], point[:, 1]) < a)


SEEDS = (1, 2, 3)


def _objective(base, c, start, rays, seed):
    from cm2optics.illumination.differentiable import smooth_objective
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.gradient_search import lens_terms
    from cm2optics.illumination.optimize import candidate_collimator
    from cm2optics.illumination.source import led_source

    design, mesh, _ = candidate_collimator(base, lens_terms(TERMS, c, start, base.collimator.lens_freeform_um[0]))
    return smooth_objective(
        design, mesh, led_source(design), design_filter_transmission(design), TERMS, rays, seed=seed, max_cv=0.10
    )


@pytest.fixture(scope="module")
def at_start(jit):
    """(base design, start terms, the objective and its gradient there for each seed): cm2-v2, the
    model LED and filter."""
    base = load_preset("cm2-v2")
    start = np.array([base.collimator.lens_freeform_um[j - 1] for j in TERMS])
    return base, start, {seed: _objective(base, start, start, 20_000, seed) for seed in SEEDS}


@pytest.mark.slow
@pytest.mark.parametrize("term", [4, 6, 7, 11])
def test_gradient_matches_finite_differences_of_the_same_objective(at_start, term):
    """dD/dc and dCV′/dc from Dr.Jit (with the rim's boundary term) against central differences
    (h = 1 µm, the mesh rebuilt, the same rays, 2·10⁴ of them) for defocus, astigmatism, coma and
    spherical (Noll 4, 6, 7, 11; the piston holding the rim for 4 and 11), averaged over three
    seeds. One seed's finite difference is noisy (the rays that change path between c ± h, each
    worth 1/(2 h N) = 2.5e-5 of D): Dr.Jit − FD scattered by 8e-5 (dD) and 1.5e-3 (dCV′) rms over
    these seeds and terms (BENCHMARKS.md), so the mean over three must agree within 3 × that / √3.
    Before the lens's hit point was told apart from the exit face above it, dD/dc₄ was −4.2e-5
    against +2.2e-4 (seed 3)."""
    base, start, at = at_start
    h, k = 1.0, TERMS.index(term)
    e = np.zeros(len(TERMS))
    e[k] = h
    gaps_d, gaps_cv = [], []
    for seed, f0 in at.items():
        up, down = _objective(base, start + e, start, 20_000, seed), _objective(base, start - e, start, 20_000, seed)
        gaps_d.append(f0.gradient_delivered[k] - (up.delivered - down.delivered) / (2 * h))
        gaps_cv.append(f0.gradient_cv[k] - (up.cv_corrected - down.cv_corrected) / (2 * h))
    assert abs(np.mean(gaps_d)) < 3 * 8e-5 / np.sqrt(len(SEEDS)), gaps_d
    assert abs(np.mean(gaps_cv)) < 3 * 1.5e-3 / np.sqrt(len(SEEDS)), gaps_cv

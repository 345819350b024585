"""Physics of the illumination tracer against closed forms: Fresnel, TIR, a Lambertian emitter,
the energy ledger, and ray-for-ray agreement with the plain NumPy reference tracer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from cm2optics.design.materials import Material
from cm2optics.illumination.excitation import TransmissionTable
from cm2optics.illumination.geometry import (
    Absorber,
    IlluminationScene,
    Medium,
    Part,
    Role,
    build_scene,
    collimator_from_solid,
    corner_normals,
)
from cm2optics.illumination.metrics import figures_of_merit
from cm2optics.illumination.reference_numpy import sample_tea_float32, trace_rays_numpy
from cm2optics.illumination.source import lambertian_profile, led_source, sample_led_rays
from cm2optics.illumination.tracer import EmittedBatch, Status, emit_rays, filter_table, trace, trace_rays

NO_FILTER = TransmissionTable(0.0, 1.0, math.pi / 2, np.ones((2, 2)))


def _plane(z: float, half: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], dtype=float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _scene(design, parts: list[Part], n: float) -> IlluminationScene:
    return IlluminationScene(
        design=design,
        label="test",
        parts=tuple(parts),
        poses=np.eye(4)[None],
        collimator=None,
        has_filter=False,
        has_housing=False,
        filter_material=Material.N_BK7,
        portal_z_mm=0.0,
        index_override={Medium.COLLIMATOR: lambda wl: np.full_like(wl, n)},
    )


def _beam(origin: np.ndarray, direction: np.ndarray) -> EmittedBatch:
    count = len(origin)
    d = np.broadcast_to(direction / np.linalg.norm(direction), (count, 3)).copy()
    return EmittedBatch(np.zeros(count, np.int32), origin, d, np.full(count, 470.0), 1.0 / count)


def _fresnel_unpolarised(cos_i: float, n1: float, n2: float) -> float:
    sin_t = n1 / n2 * math.sqrt(1 - cos_i**2)
    if sin_t >= 1:
        return 1.0
    cos_t = math.sqrt(1 - sin_t**2)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return 0.5 * (rs**2 + rp**2)


def test_glass_slab_transmits_92_percent_at_normal_incidence(v2):
    """n = 1.5: R = 0.04 per face; the incoherent sum of all passes gives T = (1 − R)/(1 + R)."""
    box = trimesh.creation.box(extents=[20.0, 20.0, 1.0])
    detector = _plane(3.0)
    scene = _scene(
        v2,
        [
            Part("slab", np.asarray(box.vertices), np.asarray(box.faces), Role.DIELECTRIC),
            Part("detector", *detector, Role.SAMPLE),
        ],
        n=1.5,
    )
    rays = 400_000
    rng = np.random.default_rng(1)
    origin = np.column_stack([rng.uniform(-5, 5, rays), rng.uniform(-5, 5, rays), np.full(rays, -2.0)])
    record = trace_rays(scene, _beam(origin, np.array([0.0, 0.0, 1.0])), NO_FILTER, seed=3)
    transmitted = np.mean(record.status == Status.SAMPLE)
    r = 0.04
    expected = (1 - r) / (1 + r)
    assert expected == pytest.approx(0.923, abs=1e-3)
    sigma = math.sqrt(expected * (1 - expected) / rays)
    assert abs(transmitted - expected) < 4 * sigma
    # Everything else was reflected back out of the slab's entry face and escaped.
    assert np.mean(record.status == Status.ESCAPED) == pytest.approx(1 - transmitted, abs=1e-12)


def _prism(length: float = 4.0, width: float = 10.0) -> trimesh.Trimesh:
    """Right-angle prism: legs along +x (bottom, z = 0) and +z (x = 0), hypotenuse facing (1, 0, 1)."""
    section = np.array([[0.0, 0.0], [length, 0.0], [0.0, length]])
    vertices = np.array([[x, y, z] for y in (-width / 2, width / 2) for x, z in section])
    faces = np.array([[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]])
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    trimesh.repair.fix_normals(mesh)
    assert mesh.is_watertight and mesh.volume > 0
    return mesh


@pytest.mark.parametrize("n", [1.5, 1.3])
def test_total_internal_reflection_in_a_right_angle_prism(v2, n):
    """Light enters the prism's bottom face normally and meets the hypotenuse at 45°: beyond the
    critical angle (n = 1.5: 41.8°) all of it is reflected towards −x, none crosses the
    hypotenuse; below it (n = 1.3: 50.3°) the Fresnel share crosses."""
    prism = _prism()
    side_v = np.array([[-1.0, -20, -20], [-1.0, 20, -20], [-1.0, 20, 20], [-1.0, -20, 20]])
    top_v, top_f = _plane(6.0)
    scene = _scene(
        v2,
        [
            Part("prism", np.asarray(prism.vertices), np.asarray(prism.faces), Role.DIELECTRIC),
            Part("side", side_v, np.array([[0, 1, 2], [0, 2, 3]]), Role.SAMPLE),
            Part("top", top_v, top_f, Role.ABSORBER, absorber=Absorber.HOUSING),
        ],
        n=n,
    )
    rays = 200_000
    rng = np.random.default_rng(2)
    origin = np.column_stack([rng.uniform(0.5, 3.0, rays), rng.uniform(-3, 3, rays), np.full(rays, -1.0)])
    record = trace_rays(scene, _beam(origin, np.array([0.0, 0.0, 1.0])), NO_FILTER, seed=5)
    top = np.mean(record.status == Status.ABSORBED + Absorber.HOUSING)
    side = np.mean(record.status == Status.SAMPLE)
    r0 = ((n - 1) / (n + 1)) ** 2
    r45 = _fresnel_unpolarised(math.cos(math.radians(45)), n, 1.0)
    if n == 1.5:
        assert r45 == 1.0
        assert top == 0.0
        # In through the bottom, out through the side; the side's reflection returns via TIR
        # and leaves through the bottom, so the side gets (1 − R0)² / (1 − R0²)·… ≈ (1 − R0)².
        assert side == pytest.approx((1 - r0) ** 2, abs=0.01)
    else:
        assert r45 < 1.0
        first_pass = (1 - r0) * (1 - r45)
        # Higher orders (side-face reflections sent back through the hypotenuse) add < 1 %.
        assert first_pass - 4 * math.sqrt(first_pass / rays) < top < first_pass + 0.01


def test_small_lambertian_emitter_gives_the_analytic_irradiance(v2):
    """E(r) = Φ h² / (π (h² + r²)²) on a plane at height h; encircled power R² / (h² + R²)."""
    h = 5.0
    detector = _plane(h, half=200.0)
    scene = _scene(v2, [Part("detector", *detector, Role.SAMPLE)], n=1.0)
    source = led_source(v2, profile=lambertian_profile(), radiant_flux_mw=1.0)
    source = type(source)(1e-4, source.profile, source.spectrum, 1.0)
    rays = 1_000_000
    emitted = sample_led_rays(source, rays, np.random.default_rng(4))
    batch = EmittedBatch(
        np.zeros(rays, np.int32), emitted.origin_mm, emitted.direction, emitted.wavelength_nm, 1.0 / rays
    )
    record = trace_rays(scene, batch, NO_FILTER)
    r = np.hypot(record.hit_mm[:, 0], record.hit_mm[:, 1])
    edges = np.array([0.0, 1.0, 2.0, 3.0, 5.0, 8.0, 12.0, 20.0])
    counts, _ = np.histogram(r[record.status == Status.SAMPLE], bins=edges)
    expected = rays * np.diff(edges**2 / (h**2 + edges**2))
    z = (counts - expected) / np.sqrt(expected)
    assert np.all(np.abs(z) < 4.5), z
    # Irradiance in a ring, mW/mm², against the closed form at the ring's power-weighted radius.
    inner, outer = 2.0, 2.5
    ring = np.sum((r >= inner) & (r < outer)) * (1.0 / rays) / (math.pi * (outer**2 - inner**2))
    radius = np.sqrt((inner**2 + outer**2) / 2)
    analytic = h**2 / (math.pi * (h**2 + radius**2) ** 2)
    assert ring == pytest.approx(analytic, rel=0.02)


def test_tea_random_numbers_match_mitsuba():
    from cm2optics.optics.backend import mitsuba

    mi = mitsuba()
    index = np.array([0, 1, 2, 12345, 2**31 + 7], dtype=np.uint32)
    ours = sample_tea_float32(index, 65536 * 3 + 7, 8)
    if hasattr(mi.UInt32, "numpy"):
        theirs = mi.sample_tea_float32(mi.UInt32(index), mi.UInt32(65536 * 3 + 7), 8).numpy()
    else:  # scalar variant
        theirs = np.array([mi.sample_tea_float32(int(i), 65536 * 3 + 7, 8) for i in index])
    np.testing.assert_allclose(ours, theirs, atol=1e-7)


def test_smooth_normals_keep_creases_and_follow_curved_surfaces():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    normals = corner_normals(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    exact = sphere.vertices[sphere.faces] / 2.0
    assert np.max(np.linalg.norm(normals - exact, axis=2)) < 0.02  # better than the facets' ≈ 0.1
    box = trimesh.creation.box(extents=[1, 2, 3])
    creased = corner_normals(np.asarray(box.vertices), np.asarray(box.faces))
    np.testing.assert_allclose(creased, np.repeat(box.face_normals[:, None, :], 3, axis=1), atol=1e-12)


def test_smooth_normals_crease_along_the_solids_edges_at_any_angle():
    """A cone of half-angle 20° on a cylinder: their edge is sharp (20°) but below the
    :data:`CREASE_DEG` threshold; shading by B-rep face keeps the side's normals horizontal and
    the cone's at 20° up to the edge, where the angle threshold averages them."""
    import cadquery as cq

    cone_deg = 20.0
    apex = 1.0 + 1.0 / math.tan(math.radians(cone_deg))
    solid = cq.Workplane("XZ").polyline([(0, 0), (1, 0), (1, 1), (0, apex)]).close().revolve(360, (0, 0), (0, 1))
    part = collimator_from_solid(solid.val(), "cone on a cylinder", Material.PMMA, tolerance_mm=0.002)
    vertices, faces = np.asarray(part.mesh.vertices), np.asarray(part.mesh.faces)
    corners = vertices[faces]  # (F, 3, 3)
    on_side = np.abs(np.hypot(corners[..., 0], corners[..., 1]).mean(axis=1) - 1.0) < 1e-3
    on_side &= corners[..., 2].mean(axis=1) > 0.05  # not the bottom disc's rim triangles
    on_side &= np.ptp(corners[..., 2], axis=1) > 1e-6
    on_cone = corners[..., 2].min(axis=1) >= 1.0 - 1e-9
    at_edge = np.abs(corners[..., 2] - 1.0) < 1e-9  # (F, 3) corners on the edge
    assert (on_side[:, None] & at_edge).any() and (on_cone[:, None] & at_edge).any()
    up = math.sin(math.radians(cone_deg))
    for face_ids, tight in ((part.face_ids, True), (None, False)):
        normals = corner_normals(vertices, faces, face_ids)
        side, cone = normals[on_side[:, None] & at_edge], normals[on_cone[:, None] & at_edge]
        errors = (np.abs(side[:, 2]).max(), np.abs(cone[:, 2] - up).max(), np.abs(np.hypot(*side[:, :2].T) - 1).max())
        assert (max(errors) < 5e-3) == tight  # the threshold (20° < CREASE_DEG) rounds the edge off


@pytest.fixture(scope="module")
def v2_scene_and_rays(v2):
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.geometry import collimator_from_design

    scene = build_scene(v2, collimator_from_design(v2, tolerance_mm=0.002))
    source = led_source(v2)
    return scene, source, design_filter_transmission(v2)


def test_energy_ledger_closes_within_the_monte_carlo_error(v2_scene_and_rays):
    scene, source, transmission = v2_scene_and_rays
    record = trace(scene, source, 200_000, transmission=transmission, seed=11)
    figures = figures_of_merit(record, scene)
    ledger = figures.ledger
    total = ledger["delivered"].value + ledger["absorbed"].value + ledger["escaped"].value
    sigma = math.sqrt(sum(ledger[k].stderr ** 2 for k in ("delivered", "absorbed", "escaped")))
    assert abs(total - 1.0) <= sigma
    assert ledger["unaccounted"].value == 0.0
    parts = [k for k in ledger if k.startswith("absorbed_")]
    assert sum(ledger[k].value for k in parts) == pytest.approx(ledger["absorbed"].value, abs=1e-12)
    assert ledger["absorbed_trapped"].value < 0.005  # few rays still bouncing after the last surface
    # Delivered power cannot exceed what passed the filter; the four LEDs deliver alike.
    assert figures.delivered_fraction.value < figures.throughput.value
    per_led = [u["delivered_fraction"] for u in figures.per_led]
    assert np.ptp(per_led) < 5 * figures.per_led[0]["delivered_fraction_stderr"] * math.sqrt(2)


def test_mitsuba_and_numpy_tracers_agree_ray_for_ray(v2_scene_and_rays):
    scene, source, transmission = v2_scene_and_rays
    batch = emit_rays(scene, source, 600, seed=2)
    table = filter_table(scene, source, transmission)
    ours = trace_rays(scene, batch, table, seed=2)
    reference = trace_rays_numpy(scene, batch, table, seed=2)
    # float32 against float64: a ray may part ways at a grazing hit, nearly all must not.
    assert np.mean(ours.status == reference.status) > 0.95
    assert np.mean(ours.passed == reference.passed) > 0.95
    both = (ours.status == Status.SAMPLE) & (reference.status == Status.SAMPLE) & (ours.bounces == reference.bounces)
    assert both.sum() > 100
    # Mitsuba leaves each surface ≈ 1.5 µm along its normal (float32 offset), NumPy 0.002 µm.
    assert np.median(np.abs(ours.hit_mm[both] - reference.hit_mm[both])) < 5e-3


def test_exit_direction_is_the_direction_in_air_after_the_filter():
    """The filter is a plane-parallel plate: a ray crossing it without reflection leaves in the
    direction it was emitted in (V1, a bare LED under its filter). The direction inside the glass
    (what the record held before) is bent towards the axis, by ≈ 1/n in sin θ."""
    from cm2optics.design import load_preset
    from cm2optics.illumination.compare import setup_from_options

    v1 = load_preset("cm2-v1")
    setup = setup_from_options(v1)
    scene = build_scene(v1, None)
    batch = emit_rays(scene, setup.source, 4000, seed=5)
    record = trace_rays(scene, batch, filter_table(scene, setup.source, setup.transmission), seed=5)
    straight = record.passed & (record.status == Status.SAMPLE) & (record.bounces == 3)  # coated face, back, sample
    assert straight.sum() > 200
    tilted = straight & (np.abs(batch.direction @ scene.unit_axes[0]) < math.cos(math.radians(15.0)))
    assert tilted.sum() > 50  # rays ≥ 15° off the axis, where the glass would bend them by ≥ 5°
    assert np.abs(record.exit_direction[straight] - batch.direction[straight]).max() < 1e-4

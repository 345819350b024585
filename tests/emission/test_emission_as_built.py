"""The emission tracer honours the design's as-built section: foci of a decentred, rotated or
rescaled array move by the first-order amounts, a lenslet's transmission scales its focus, the
sensor offset shifts the pixel grid, the vignetting delta cuts off-axis light; tilts are refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.source import fluorescent_bead
from cm2optics.optics import first_order

SETTINGS = PSFSettings(binning=8, band_nm=50.0)


def _foci(design: SystemDesign, position=(0.0, 0.0, 0.0)) -> dict[tuple[int, int], object]:
    """Full lenslets' foci by (row, col)."""
    model = EmissionModel(design, fluorescent_bead(0.0), settings=SETTINGS)
    out = {}
    for focus in model.foci(position):
        lenslet = model.optics.lenslets[focus.lenslet]
        if not lenslet.partial:
            out[(lenslet.row, lenslet.col)] = focus
    return out


@pytest.fixture(scope="module")
def nominal(v2: SystemDesign):
    return _foci(v2)


def test_decentred_array_moves_the_foci_by_one_plus_m(v2: SystemDesign, nominal):
    d = (0.05, -0.03)
    moved = _foci(v2.with_changes({"as_built.mla_decenter_x_mm": d[0], "as_built.mla_decenter_y_mm": d[1]}))
    m = first_order.magnification(v2)
    for key in ((1, 1), (0, 1), (1, 2)):
        shift = np.subtract(moved[key].ray_centroid_mm, nominal[key].ray_centroid_mm)
        np.testing.assert_allclose(shift, (1 + m) * np.array(d), rtol=0.03)


def test_rotation_and_pitch_move_the_lattice(v2: SystemDesign, nominal):
    rotated = _foci(v2.with_changes({"as_built.mla_rotation_deg": 1.0}))
    for key in ((1, 0), (1, 2), (0, 1)):
        a0 = math.atan2(*nominal[key].ray_centroid_mm[::-1])
        a1 = math.atan2(*rotated[key].ray_centroid_mm[::-1])
        assert math.isclose(math.degrees(a1 - a0), 1.0, abs_tol=0.02)
    delta = 0.02
    scaled = _foci(v2.with_changes({"as_built.lenslet_pitch_delta_mm": delta}))
    scale = (v2.mla.pitch_mm + delta) / v2.mla.pitch_mm
    for key in ((1, 0), (0, 0), (2, 2)):
        np.testing.assert_allclose(
            scaled[key].ray_centroid_mm, scale * np.array(nominal[key].ray_centroid_mm), atol=1e-3
        )


def test_transmission_scales_one_focus_and_sensor_offset_shifts_the_grid(v2: SystemDesign, nominal):
    dimmed = _foci(v2.with_changes({"as_built.lenslet_transmission": [1, 1, 1, 1, 1, 0.4, 1, 1, 1]}))
    for key, focus in nominal.items():
        expected = 0.4 if key == (1, 2) else 1.0
        assert math.isclose(dimmed[key].energy / focus.energy, expected, rel_tol=1e-6)
    offset_um = (38.4, -19.2)  # the sensor moves +x, −y: the image moves −2, +1 binned pixels (19.2 µm)
    shifted = _foci(
        v2.with_changes({"as_built.sensor_offset_x_um": offset_um[0], "as_built.sensor_offset_y_um": offset_um[1]})
    )
    pitch_um = v2.sensor.pixel_um * SETTINGS.binning
    for key in ((1, 1), (0, 2)):
        (r0, c0), (r1, c1) = nominal[key].centroid_px(), shifted[key].centroid_px()
        assert math.isclose(c1 - c0, -offset_um[0] / pitch_um, abs_tol=0.05)
        assert math.isclose(r1 - r0, -offset_um[1] / pitch_um, abs_tol=0.05)
        assert shifted[key].ray_centroid_mm == pytest.approx(nominal[key].ray_centroid_mm)


def test_narrower_vignetting_aperture_cuts_off_axis_light(v2: SystemDesign):
    position = (2.5, 0.0, 0.0)
    nominal = sum(f.energy for f in _foci(v2, position).values())
    narrower = sum(
        f.energy for f in _foci(v2.with_changes({"as_built.vignetting_radius_delta_mm": -0.4}), position).values()
    )
    assert narrower < 0.95 * nominal


def _chief_landing_mm(model: EmissionModel, lenslet: int, source_mm: np.ndarray) -> np.ndarray:
    """Where the first-order chief ray of ``lenslet`` meets the sensor plane z = 0 (device frame,
    mm): aimed from the source at the lens's front principal point (its curved vertex), it leaves
    the rear one (thickness/n above the flat face, both turned with a tilted array) parallel to
    itself; the plates below shift every case alike and are left out."""
    optics, design = model.optics, model.design
    cell = optics.lenslets[lenslet]
    n = 1.49  # PMMA: the rear principal point sits t/n above the flat face (t/n ≈ 0.67 t)
    front = np.array([cell.vertex_x_mm, cell.vertex_y_mm, optics.vertex_z_mm])
    rear = np.array([cell.vertex_x_mm, cell.vertex_y_mm, optics.flat_z_mm + design.mla.thickness_mm / n])
    if optics.mla_tilt:
        pivot, r = np.array(optics.mla_pivot_mm), np.array(optics.mla_tilt)
        front, rear = (pivot + r @ (p - pivot) for p in (front, rear))
    d = front - source_mm
    return rear[:2] - d[:2] * rear[2] / d[2]


def test_a_tilted_array_moves_each_focus_with_its_lenslet(v2: SystemDesign):
    """MLA tilted 1.5° about y (about its vertex plane): every focus moves as its first-order chief
    ray does, mostly with the rear principal point (≈ 1.1 mm under the vertex, so ≈ 28 µm along
    −x); the tilted lens's coma moves the ray centroids ≈ 10 % further (checked at 0.5–3°)."""
    tilted = v2.with_changes({"as_built.mla_tilt_y_deg": 1.5})
    models = {
        name: EmissionModel(d, fluorescent_bead(0.0), settings=SETTINGS) for name, d in (("0", v2), ("t", tilted))
    }
    for position in ((0.0, 0.0, 0.0), (0.5, 0.3, 0.2)):
        foci = {name: {f.lenslet: f for f in m.foci(position)} for name, m in models.items()}
        source = models["0"].device_point_mm(position)
        for lenslet in (0, 3, 4, 5, 8):
            traced = np.subtract(foci["t"][lenslet].ray_centroid_mm, foci["0"][lenslet].ray_centroid_mm)
            chief = _chief_landing_mm(models["t"], lenslet, source) - _chief_landing_mm(models["0"], lenslet, source)
            np.testing.assert_allclose(traced, chief, rtol=0.15, atol=1e-3)


@pytest.mark.parametrize(("axis", "angle"), [("x", 2.0), ("y", -3.0)])
def test_a_tilted_sensor_meets_each_focus_at_its_height(v2: SystemDesign, axis: str, angle: float):
    """Rays land where they meet the tilted plane z = y·tan θx (about x) or z = −x·tan θy (about y),
    read along the sensor's own axes: x/cos θ along a tilted axis; the closed form from the rays
    of the untilted sensor, followed along their last direction."""
    from cm2optics.emission.optics import emission_optics
    from cm2optics.emission.trace import RayBatch, trace_rays

    tilted = v2.with_changes({f"as_built.sensor_tilt_{axis}_deg": angle})
    model = EmissionModel(v2, fluorescent_bead(0.0), settings=SETTINGS)
    source = model.device_point_mm((0.3, -0.2, 0.0))
    grid = np.linspace(-0.12, 0.12, 9)
    u, v = (g.ravel() for g in np.meshgrid(grid - 0.01, grid + 0.02))
    lenslets = np.array([0, 2, 4, 6, 8])
    batch = RayBatch(
        np.repeat(source[None], len(lenslets), 0),
        np.tile(u, len(lenslets)),
        np.tile(v, len(lenslets)),
        lenslets,
        np.full(len(lenslets), 1.52),
        np.full(len(lenslets), 1.49),
        np.full(len(lenslets), 1.5),
        np.repeat(np.arange(len(lenslets)), len(u)),
    )
    flat = trace_rays(emission_optics(v2), batch, "numpy")
    tilt = trace_rays(emission_optics(tilted), batch, "numpy")
    ok = flat.traced & tilt.traced
    assert ok.sum() > 100
    theta = math.radians(angle)
    e = flat.direction[ok]
    x, y = flat.x_mm[ok], flat.y_mm[ok]
    if axis == "y":  # the plane z = −x·tan θ met along e from (x, y, 0)
        t = -x * math.tan(theta) / (e[:, 2] + e[:, 0] * math.tan(theta))
        height = t * e[:, 2]
        expected_x, expected_y = (x + t * e[:, 0]) / math.cos(theta), y + t * e[:, 1]
        np.testing.assert_allclose(height, -(x + t * e[:, 0]) * math.tan(theta), atol=1e-12)
    else:  # the plane z = y·tan θ
        t = y * math.tan(theta) / (e[:, 2] - e[:, 1] * math.tan(theta))
        expected_x, expected_y = x + t * e[:, 0], (y + t * e[:, 1]) / math.cos(theta)
    assert np.abs(t * e[:, 2]).max() > 0.05  # foci 1–2 mm off the axis: defocused by 50–100 µm
    np.testing.assert_allclose(tilt.x_mm[ok], expected_x, atol=1e-9)
    np.testing.assert_allclose(tilt.y_mm[ok], expected_y, atol=1e-9)
    np.testing.assert_allclose(tilt.opl_mm[ok] - flat.opl_mm[ok], t, atol=1e-9)


def test_scan_applies_the_sensor_side_effects(v2: SystemDesign, tmp_path):
    from cm2optics.emission.scan import ScanSettings, simulate_scan
    from cm2optics.formats.scan import read_scan

    settings = ScanSettings(psf=SETTINGS, source=fluorescent_bead(5.0))
    built = v2.with_changes(
        {
            "as_built.leakage_counts_per_ms": 3.0,
            "as_built.pixel_crosstalk_fraction": 0.3,
            "as_built.stray_light_fraction": 0.2,
        }
    )
    images = {}
    for name, design in (("nominal", v2), ("built", built)):
        simulate_scan(design, np.zeros((1, 3)), tmp_path / name, settings, workers=1, processes=False, progress=False)
        images[name] = read_scan(tmp_path / name).normalised()[0]
    nominal, measured = images["nominal"], images["built"]
    assert np.median(nominal) == 0.0
    assert math.isclose(float(np.median(measured)), 3.0, abs_tol=0.1)  # leakage: counts per ms on every pixel
    peak = np.unravel_index(np.argmax(nominal), nominal.shape)
    # crosstalk and the halo take light from the brightest pixel of each focus into its neighbours
    assert _peak_share(measured, peak, 3.0) < 0.9 * _peak_share(nominal, peak, 0.0)


def _peak_share(image: np.ndarray, peak: tuple[int, int], background: float) -> float:
    """The brightest pixel's share of its 3 × 3 neighbourhood, background removed."""
    r, c = peak
    window = image[r - 1 : r + 2, c - 1 : c + 2] - background
    return float(window[1, 1] / window.sum())

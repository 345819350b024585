"""Synthetic volumes: rasterisation against the literal fine-grid reference and closed forms,
emitter statistics, reproducibility by seed, noise statistics, config validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.design import load_preset
from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.optics import first_order
from cm2optics.synth import SynthConfig, add_noise, rasterize_balls, rasterize_balls_naive, sample_emitters, sample_rng
from cm2optics.synth.noise import noise_variance

GRID = VolumeGrid((41, 70, 90), (10.0, 4.15, 4.15))


def random_emitters(n: int, seed: int = 0, grid: VolumeGrid = GRID) -> Emitters:
    rng = np.random.default_rng(seed)
    half = [e / 2 for e in grid.extent_um]
    return Emitters(
        rng.uniform(-half[2] - 10, half[2] + 10, n),  # some cross the edges
        rng.uniform(-half[1] - 10, half[1] + 10, n),
        rng.uniform(-half[0] - 10, half[0] + 10, n),
        rng.uniform(8, 20, n),
        rng.uniform(0.5, 2.0, n),
    )


@pytest.mark.parametrize("kind", ["emission", "occupancy"])
@pytest.mark.parametrize("supersample", [5, 2])
def test_vectorised_rasterisation_equals_the_fine_grid_reference(kind, supersample):
    emitters = random_emitters(60)
    fast = rasterize_balls(emitters, GRID, supersample=supersample, kind=kind)
    slow = rasterize_balls_naive(emitters, GRID, supersample=supersample, kind=kind)
    assert fast.dtype == np.float32 and fast.shape == GRID.shape
    np.testing.assert_allclose(fast, slow, atol=1e-6)


def test_an_interior_emitter_keeps_its_intensity_and_its_volume():
    grid = VolumeGrid((21, 41, 41), (10.0, 4.15, 4.15))
    one = Emitters([1.3], [-2.1], [3.7], [20.0], [2.5])
    emission = rasterize_balls(one, grid)
    assert emission.sum() == pytest.approx(2.5, rel=1e-5)
    occupancy = rasterize_balls(one, grid, kind="occupancy")
    voxel = 10.0 * 4.15 * 4.15
    assert occupancy.sum() * voxel == pytest.approx(math.pi / 6 * 20.0**3, rel=0.03)
    assert occupancy.max() <= 1.0
    # the centroid is the centre (µm, the design's coordinates)
    z, y, x = (grid.axis_um(a) for a in range(3))
    w = emission / emission.sum()
    assert (w.sum((0, 1)) @ x, w.sum((0, 2)) @ y, w.sum((1, 2)) @ z) == pytest.approx(
        (1.3, -2.1, 3.7), abs=0.5
    )  # within a quarter of a 2-µm sub-voxel step


def test_supersampling_converges_to_the_ball_volume():
    grid = VolumeGrid((9, 15, 15), (10.0, 4.15, 4.15))
    one = Emitters([0.4], [0.9], [-1.2], [13.0], [1.0])
    exact = math.pi / 6 * 13.0**3 / (10.0 * 4.15 * 4.15)
    errors = [
        abs(rasterize_balls(one, grid, supersample=s, kind="occupancy").sum() - exact) / exact for s in (1, 5, 15)
    ]
    assert errors[2] < errors[1] < 0.1 and errors[2] < 0.02


def test_tiny_and_dark_emitters():
    grid = VolumeGrid((5, 9, 9), (10.0, 4.0, 4.0))
    tiny = Emitters([0.3], [0.0], [0.0], [0.1], [3.0])  # far smaller than a sub-voxel
    volume = rasterize_balls(tiny, grid)
    assert volume.sum() == pytest.approx(3.0) and volume[2, 4, 4] == pytest.approx(3.0)
    dark = Emitters([0.0], [0.0], [0.0], [10.0], [0.0])
    assert not np.any(rasterize_balls(dark, grid))


def test_rasterisation_rejects_bad_options():
    with pytest.raises(ValueError, match="supersample"):
        rasterize_balls(random_emitters(2), GRID, supersample=0)
    with pytest.raises(ValueError, match="kind"):
        rasterize_balls(random_emitters(2), GRID, kind="peak")
    with pytest.raises(ValueError, match="out"):
        rasterize_balls(random_emitters(2), GRID, out=np.zeros((2, 2, 2), np.float32))


# ----------------------------------------------------------------------------- emitters


def test_emitters_follow_the_papers_distributions():
    config = SynthConfig.paper()
    draws = [sample_emitters(config, sample_rng(7, i)) for i in range(6)]
    for draw in draws:
        e = draw.emitters
        assert 6.5 <= draw.fov_mm <= 7.5 and 10 <= draw.density_per_mm2 <= 100
        assert len(e) == round(draw.density_per_mm2 * math.pi * draw.fov_mm**2 / 4)
        assert np.all(np.hypot(e.x_um, e.y_um) <= draw.fov_mm * 500 + 1e-9)
        assert np.all(np.abs(e.z_um) <= 400)
        assert np.all((e.diameter_um >= 8) & (e.diameter_um <= 20))
        jitter = e.intensity / (e.diameter_um / 10.0) ** 2
        assert np.all((jitter >= 0.8) & (jitter <= 1.2))
    # uniform in the disc: half the emitters within 1/√2 of the radius
    e = draws[0].emitters
    inner = np.mean(np.hypot(e.x_um, e.y_um) < draws[0].fov_mm * 500 / math.sqrt(2))
    assert inner == pytest.approx(0.5, abs=0.05)


def test_same_seed_same_emitters_whatever_the_order():
    config = SynthConfig.scaled(4)
    a = [sample_emitters(config, sample_rng(3, i)).emitters for i in (0, 1, 2)]
    b = [sample_emitters(config, sample_rng(3, i)).emitters for i in (2, 1, 0)][::-1]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.x_um, y.x_um)
        np.testing.assert_array_equal(x.intensity, y.intensity)
    c = sample_emitters(config, sample_rng(4, 0)).emitters
    assert len(c) != len(a[0]) or not np.array_equal(c.x_um, a[0].x_um)


def test_paper_config_sizes_and_validation():
    config = SynthConfig.paper()
    assert config.grid.shape == (81, 1820, 1820)
    # The cm2-v2 preset's axial step and object pixel (the paper calibrated 4.15 µm).
    assert config.grid.voxel_um == first_order.voxel_um(load_preset("cm2-v2"))
    assert config.grid.voxel_um == pytest.approx((10.0, 4.15, 4.15), rel=0.01)
    assert config.view_px == 1920 and config.patch_px == 320 and config.supersample == 5
    small = SynthConfig.scaled(4)
    assert small.fov_mm == pytest.approx((6.5 / 4, 7.5 / 4)) and small.view_px == 480 and small.patch_px == 80
    assert SynthConfig.from_dict(small.to_dict()) == small
    with pytest.raises(ValueError, match="fov_mm"):
        SynthConfig(fov_mm=(7.5, 6.5))
    with pytest.raises(ValueError, match="noise"):
        SynthConfig(noise="gaussian")
    with pytest.raises(ValueError, match="patch_px"):
        SynthConfig(view_px=100, patch_px=200)
    with pytest.raises(ValueError, match="unknown synth parameter"):
        SynthConfig.from_dict({"fov": 3})
    with pytest.raises(ValueError, match="voxel_um"):
        SynthConfig(voxel_um=(10.0, 0.0, 4.0))


# ----------------------------------------------------------------------------- noise


@pytest.mark.parametrize("level", [0.0, 0.2, 1.0])
def test_poisson_gaussian_noise_statistics(level):
    config = SynthConfig()
    clean = np.full((400, 500), level)
    noisy = add_noise(clean, config, np.random.default_rng(1)).astype(np.float64)
    assert noisy.mean() == pytest.approx(level + 0.048, abs=4e-4)
    assert noisy.var() == pytest.approx(level / 500 + 0.017**2, rel=0.02)
    assert noise_variance(level, config) == pytest.approx(level / 500 + 0.017**2)


@pytest.mark.parametrize("level", [0.0, 0.5, 1.0])
def test_variance_model_noise_statistics(level):
    config = SynthConfig(noise="variance")
    clean = np.full((400, 500), level)
    noisy = add_noise(clean, config, np.random.default_rng(2)).astype(np.float64)
    assert noisy.mean() == pytest.approx(level, abs=2e-4)
    assert noisy.var() == pytest.approx(1.5e-4 * level + 5.4e-6, rel=0.02)


def test_noise_is_reproducible_and_none_is_identity():
    clean = np.random.default_rng(0).random((50, 60))
    config = SynthConfig()
    np.testing.assert_array_equal(
        add_noise(clean, config, sample_rng(5, 1, 1)), add_noise(clean, config, sample_rng(5, 1, 1))
    )
    np.testing.assert_array_equal(
        add_noise(clean, SynthConfig(noise="none"), np.random.default_rng()), clean.astype(np.float32)
    )
    with pytest.raises(ValueError, match="finite"):
        add_noise(np.array([[np.nan]]), config, np.random.default_rng())

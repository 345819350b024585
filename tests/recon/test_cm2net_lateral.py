"""CM²Net's lateral calibration: the output planes resampled onto the object grid (orientation,
the chief ray's pixel, a depth-dependent scale and shift), the least-squares fit recovering known
coefficients, and the correction stored under the weights' SHA-256. Milliseconds to seconds."""

from __future__ import annotations

import numpy as np
import pytest
from tiny_net import tiny

from cm2optics.recon.net.lateral import LateralCorrection, fit_lateral_correction, volume_on_grid


def _blob(shape: tuple[int, int], centre: tuple[float, float], sigma: float = 1.5) -> np.ndarray:
    y, x = np.mgrid[: shape[0], : shape[1]]
    return np.exp(-((y - centre[0]) ** 2 + (x - centre[1]) ** 2) / (2 * sigma**2)).astype(np.float32)


def _centroid(plane: np.ndarray) -> np.ndarray:
    y, x = np.mgrid[: plane.shape[0], : plane.shape[1]]
    return np.array([(plane * y).sum(), (plane * x).sum()]) / plane.sum()


@pytest.mark.parametrize("orientation", [(-1.0, -1.0), (1.0, -1.0)])
def test_the_output_planes_land_on_the_object_grid_with_the_chief_ray_at_pixel_v_over_2(orientation):
    """Raw pixel i holds the target at sign·(i − V//2)·voxel; the object grid is centred at
    (V − 1)/2. A blob at raw (20, 13) of a 48-px plane, voxel 4 µm: with the image inverted in y
    and x its object position is (−4, +11) voxels from the axis, i.e. index (19.5, 34.5)."""
    V, voxel = 48, 4.0
    raw = _blob((V, V), (20.0, 13.0))[None]
    out = volume_on_grid(raw, np.zeros(1), (voxel, voxel), np.array(orientation))
    u = np.array([orientation[0] * (20 - V // 2), orientation[1] * (13 - V // 2)])  # voxels from the axis
    np.testing.assert_allclose(_centroid(out[0]), u + (V - 1) / 2.0, atol=0.02)


def test_a_depth_dependent_scale_and_shift_is_undone_per_plane():
    """The network put an emitter at û = s(z)·u + b(z); the corrected plane has it back at u."""
    V, voxel = 64, 4.0
    correction = LateralCorrection((0.01, 0.1, 0.0), ((1.0, 5.0, 0.0), (-2.0, 0.0, 20.0)))
    z = np.array([-0.15, 0.0, 0.2])
    s, b = correction.at(z)
    u = np.array([30.0, -50.0])  # µm from the axis, (y, x)
    raw = np.stack([_blob((V, V), V // 2 + (s[k] * u + b[k]) / voxel) for k in range(len(z))])  # orientation +1
    out = volume_on_grid(raw, z, (voxel, voxel), np.ones(2), correction)
    for k in range(len(z)):
        np.testing.assert_allclose(_centroid(out[k]), u / voxel + (V - 1) / 2.0, atol=0.03)
    # without the correction the deepest plane keeps it at û, 4 µm from u
    plain = volume_on_grid(raw, z, (voxel, voxel), np.ones(2))
    np.testing.assert_allclose(_centroid(plain[2]), (s[2] * u + b[2]) / voxel + (V - 1) / 2.0, atol=0.03)
    assert np.linalg.norm(s[2] * u + b[2] - u) > 3.9


def test_the_fit_recovers_known_coefficients_from_noisy_pairs():
    rng = np.random.default_rng(3)
    truth = LateralCorrection((0.004, 0.07, 0.5), ((-0.3, -24.0, -200.0), (0.2, 3.0, -80.0)))
    u = rng.uniform(-900, 900, (600, 2))
    z = rng.uniform(-0.19, 0.19, 600)
    s, b = truth.at(z)
    found = s[:, None] * u + b + rng.normal(0, 1.0, (600, 2))
    fitted = fit_lateral_correction(u, z, found)
    assert np.all(np.abs(np.subtract(fitted.scale, truth.scale)) <= [3e-4, 3e-3, 0.1])
    assert np.all(np.abs(np.subtract(fitted.shift_um, truth.shift_um)) <= [0.3, 2.0, 30.0])
    with pytest.raises(ValueError, match="at least 9"):
        fit_lateral_correction(u[:5], z[:5], found[:5])


def test_the_correction_is_stored_under_the_weights_hash(tmp_path):
    import json

    from cm2optics.recon.net.lateral import METADATA_KEY
    from cm2optics.recon.net.train import make_net
    from cm2optics.recon.net.weights import WeightsError, load_weights, save_weights, store_metadata

    config = tiny()
    net, _ = make_net(config)
    folder = save_weights(net, config, tmp_path / "w")
    card = (folder / "MODEL_CARD.md").read_text()
    assert load_weights(folder).lateral is None
    correction = LateralCorrection((0.001, 0.07, 0.0), ((0.0, -24.0, 1.0), (0.5, 0.0, -80.0)))
    store_metadata(folder, {METADATA_KEY: correction.to_json()})
    loaded = load_weights(folder)  # the sums were rewritten: still verifies
    assert loaded.lateral == correction and (folder / "MODEL_CARD.md").read_text() == card
    store_metadata(folder, {METADATA_KEY: json.dumps({"scale": [0.0], "shift_um": []})})
    with pytest.raises(WeightsError, match=METADATA_KEY):
        load_weights(folder)

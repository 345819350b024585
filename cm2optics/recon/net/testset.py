"""CM²Net on test sets it never saw, beside FISTA on the same measurements (issue 15's sets).

The test volumes are made the paper's way — on the training sensor window, grid and noise, with
the paper's densities (U[10, 100] per mm²) and diameters (8–20 µm) and a seed no training,
validation or reference volume used; or over the whole field (``field_mm``: a disc of that
diameter, the network given views that hold it) — and imaged

(a) through the forward model the weights were trained through (as in training), or
(b) by the emission ray tracer (``traced``: a factory of an imaging source such as
    :class:`cm2optics.emission.image.TracedSource`, given the weights' 3D-LSV model; no LSV model
    in the loop — the analogue of the paper's experiments, where the model mismatch is real);

then reconstructed by the network and by FISTA with the weights' 3D-LSV model (for (b), optionally
a model of its own, e.g. built from a traced PSF scan: the device's calibrated model), each thresholded
at its own F1-optimal threshold, scored, and broken down against field radius, depth, size and
density (the paper's Fig. 6) by :func:`cm2optics.recon.compare.compare_baselines`.

Run (a)::

    python -m cm2optics.recon.net.testset reconstruction/cm2net-cpu out/cm2net-test-a --n-volumes 10

and (b), which needs the tracer, from the command line: ``cm2 net-testset WEIGHTS OUT --traced``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["TEST_SEED", "check_seed", "net_test_set"]

#: The test set's seed: the training data use the config's seed, validation that + 7919.
TEST_SEED = 1_000_003


def net_test_set(
    weights: str | Path,
    out_dir: str | Path,
    *,
    n_volumes: int = 10,
    seed: int = TEST_SEED,
    fista_iterations: int = 60,
    workers: int = 1,
    threads: int = 1,
    reuse: bool = False,
    traced: Callable[[Any], Any] | None = None,
    model: str | Path | None = None,
    imaging_model: str | Path | None = None,
    field_mm: float | None = None,
    log=print,
) -> dict[str, Any]:
    """Make the test set, reconstruct it with the weights and with FISTA, evaluate; returns the
    summary that ``out_dir/comparison.json`` holds (runs ``cm2net`` and ``lsv-fista``; the network
    alone when ``fista_iterations`` is 0).

    traced: ``traced(reference)`` → the source that images the test volumes instead of the 3D-LSV
    model the runs use (set (b); made in this process, reused when the saved set records the same
    traced design, binning and sensor window). model: a 3D-LSV model file both
    reconstructions use instead of the weights' forward model (which still images set (a)): for
    (b) e.g. one built from a traced PSF scan of the design (``cm2 psf simulate`` → ``cm2 lsv
    build``), the calibrated model a real device is reconstructed with; or a lower-rank build of
    the weights' own scan, for a faster FISTA. Its geometry must be the weights' (checked by the
    network's run); cut to the views' sensor window and written to
    ``out_dir/forward-model.lsv.h5``. imaging_model: a 3D-LSV model file that images set (a)
    instead of the weights' forward model (e.g. a higher-rank build of ``model``'s scan).

    field_mm: the test volumes' field, a disc of this diameter (default: the training field), the
    network given views that hold it (:func:`~cm2optics.recon.net.infer.field_view_px`) instead
    of the training views; it needs ``model`` (the weights' forward model is cut to the training
    views), of the whole sensor, which images set (a) itself unless ``imaging_model`` does."""
    from cm2optics.lsv.model import load_model
    from cm2optics.recon.compare import compare_baselines
    from cm2optics.recon.net.data import forward_imaging, sensor_window
    from cm2optics.recon.net.infer import field_view_px
    from cm2optics.recon.net.weights import load_weights
    from cm2optics.synth.imaging import Imaging

    loaded = load_weights(weights)
    config = loaded.config
    check_seed(seed, config.seed)
    if field_mm is not None and model is None:
        raise ValueError("a whole-field test set needs a 3D-LSV model of the whole sensor (model)")
    if imaging_model is not None and traced is not None:
        raise ValueError("imaging_model images set (a), traced images set (b): give one of them")
    field = {} if field_mm is None else {"fov_mm": (field_mm, field_mm), "field_shape": "disk"}
    test = config.synth.with_changes(
        view_px=0, patch_px=0, patches_per_volume=0, store_volume=False, density_per_mm2=(10.0, 100.0), **field
    )
    view_px = config.synth.view_px
    if field_mm is not None:
        view_px = field_view_px(field_mm, test.voxel_um[1], loaded.planes.max_shift_px)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model_path = out_dir / "forward-model.lsv.h5"
    imaging_source = forward_imaging(config).source  # the training sensor window
    source = imaging_source if model is None else sensor_window(load_model(model), view_px)
    if not hasattr(source, "save"):
        raise ValueError(f"{config.forward_model}: a test set needs a 3D-LSV forward model, not a toy operator")
    if model is not None or traced is not None or not model_path.is_file():
        source.save(model_path)
    net_run = {"method": "net", "weights": str(Path(weights).resolve()), "preprocess": "none"}
    runs = {
        "cm2net": net_run if field_mm is None else net_run | {"view_px": view_px},
        "lsv-fista": {"forward": "lsv", "method": "fista", "l1": 0.02, "max_iter": fista_iterations},
    }
    if fista_iterations == 0:
        del runs["lsv-fista"]
    imaging = None  # set (a) imaged by the reconstruction model itself, on Dask workers
    if traced is not None:
        imaging = Imaging(traced(source), test.grid)
    elif imaging_model is not None:
        imaging = Imaging(sensor_window(load_model(imaging_model), view_px), test.grid)
    elif model is not None and field_mm is None:
        imaging = Imaging(imaging_source, test.grid)  # set (a): the weights' own model images it
    return compare_baselines(
        model_path,
        out_dir,
        n_volumes=n_volumes,
        seed=seed,
        config=test,
        runs=runs,
        workers=workers,
        threads=threads,
        reuse=reuse,
        log=log,
        imaging=imaging,
    )


def check_seed(seed: int, training_seed: int) -> None:
    """Refuse a test seed whose volumes the run made: training, validation or reference histogram."""
    from cm2optics.recon.net.data import VALIDATION_SEED_OFFSET
    from cm2optics.recon.net.train import REFERENCE_SEED_OFFSET

    used = {
        training_seed: "training",
        training_seed + VALIDATION_SEED_OFFSET: "validation",
        training_seed + REFERENCE_SEED_OFFSET: "reference-histogram",
    }
    if seed in used:
        raise ValueError(f"seed {seed} is the {used[seed]} data's seed: choose another for a test set")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cm2optics.recon.net.testset", description=__doc__.split("\n\n")[0])
    parser.add_argument("weights", help="weights folder, e.g. reconstruction/cm2net-cpu")
    parser.add_argument("out_dir", help="folder for the test set, the reconstructions and comparison.json/.md")
    parser.add_argument("--n-volumes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=TEST_SEED)
    parser.add_argument("--fista-iterations", type=int, default=60)
    parser.add_argument("--workers", type=int, default=1, help="Dask workers making the test set")
    parser.add_argument("--reuse", action="store_true", help="reuse the test set and runs already in OUT_DIR")
    args = parser.parse_args(argv)
    summary = net_test_set(
        args.weights,
        args.out_dir,
        n_volumes=args.n_volumes,
        seed=args.seed,
        fista_iterations=args.fista_iterations,
        workers=args.workers,
        reuse=args.reuse,
    )
    keys = ("recall", "precision", "f1", "rmse_lateral_um", "rmse_axial_um", "seconds_per_volume", "threshold")
    print(json.dumps({name: {k: run.get(k) for k in keys} for name, run in summary["runs"].items()}, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

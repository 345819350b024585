"""``cm2 train``: train CM²Net from a YAML config, resumable."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from cm2optics.cli.options import JsonOption, OverwriteOption, check_output, user_errors

__all__ = ["train_command"]


@user_errors
def train_command(
    config: Annotated[
        Path,
        typer.Argument(help="Training config (YAML), e.g. reconstruction/configs/cm2net-cpu.yaml."),
    ],
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue from the run's checkpoint (out_dir/checkpoint.pt).")
    ] = False,
    max_steps: Annotated[
        int | None,
        typer.Option("--max-steps", min=1, help="Stop (with a checkpoint) once this many steps are done in all."),
    ] = None,
    device: Annotated[
        str | None, typer.Option("--device", help="cpu or cuda:N (default: the process's GPU if any, else cpu).")
    ] = None,
    ablation: Annotated[
        str | None,
        typer.Option(
            "--ablation",
            help="Train (or export) one of the paper's ablations instead of the config's network: no-demix, "
            "enhancement-only or synthesis-only; the run goes to <out_dir>-<ablation>.",
        ),
    ] = None,
    export: Annotated[
        Path | None,
        typer.Option(
            "--export",
            help="Do not train: write the weights of the run's latest checkpoint (out_dir/checkpoint.pt, a run still "
            "training or stopped) into this folder as a weights folder, e.g. reconstruction/cm2net-cpu.",
        ),
    ] = None,
    keep: Annotated[
        str | None,
        typer.Option(
            "--keep",
            help="With --export: which weights — last (the latest checkpoint's), best (the best validation scoring's) "
            "or average (the mean of the last ones'); default: the config's keep_weights.",
        ),
    ] = None,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Train CM²Net (view demixing, shift-and-add refocusing, view synthesis + refocus enhancement)
    on volumes simulated on the fly through the config's forward model.

    Checkpoints carry the model, optimiser, scheduler, step and RNG states and the config's hash, so
    an interrupted run continues exactly with --resume (another config is refused). Several
    processes or machines: the same command under torchrun (gloo on CPUs, NCCL on GPUs). Writes
    the loss curve (PNG), per-epoch validation metrics and, at the end, the weights folder
    (safetensors, config, model card, SHA256SUMS) into the config's out_dir.
    """
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.recon.net.config import load_config
    from cm2optics.recon.net.train import train

    if keep is not None:
        from cm2optics.recon.net.config import KEEP_WEIGHTS, ConfigError

        if export is None:
            raise ConfigError("--keep chooses the weights --export writes; give --export")
        if keep not in KEEP_WEIGHTS:
            raise ConfigError(f"--keep {keep}: must be one of {', '.join(KEEP_WEIGHTS)}")
    if not config.is_file():
        raise FileNotFoundError(f"{config}: no such config file")
    settings = load_config(config)
    if ablation is not None:
        settings = _ablated(settings, ablation)
    out_dir = Path(settings.out_dir)
    if export is not None:
        _export(out_dir, export, config, overwrite, keep)
        return
    check_output(out_dir, command="train", kind="folder", inputs=[config], overwrite=overwrite, option="out_dir")
    claim_folder(out_dir, "train")
    summary = train(settings, resume=resume, max_steps=max_steps, device=device)
    shown = {k: v for k, v in summary.items() if k != "metrics"}
    if as_json:
        print(json.dumps(summary, indent=2, default=str))
    else:
        typer.echo(json.dumps(shown, indent=1, default=str))


def _ablated(settings, ablation: str):
    """The config with ``ablation`` and its own run folder ``<out_dir>-<ablation>``."""
    from cm2optics.recon.net.config import ABLATIONS, ConfigError

    if ablation not in ABLATIONS[1:]:
        raise ConfigError(f"--ablation {ablation}: must be one of {', '.join(ABLATIONS[1:])}")
    return settings.with_changes(ablation=ablation, out_dir=f"{str(settings.out_dir).rstrip('/')}-{ablation}")


def _export(run_dir: Path, folder: Path, config: Path, overwrite: bool, keep: str | None = None) -> None:
    """``--export``: the run's latest checkpoint as a weights folder (written whole, or not at all)."""
    from rich.console import Console

    from cm2optics.recon.net.checkpoint import CheckpointError
    from cm2optics.recon.net.train import CHECKPOINT, export_weights

    if not (run_dir / CHECKPOINT).is_file():
        raise CheckpointError(f"{run_dir / CHECKPOINT}: no checkpoint to export (out_dir of {config}); train first")
    check_output(
        folder, command="train", kind="folder", inputs=[config, run_dir], overwrite=overwrite, option="--export"
    )
    saved = export_weights(run_dir, folder, keep)
    Console(stderr=True).print(f"[green]weights:[/] {saved}")


@user_errors
def net_testset_command(
    weights: Annotated[Path, typer.Argument(help="Weights folder, e.g. reconstruction/cm2net-cpu.")],
    out_dir: Annotated[
        Path,
        typer.Argument(metavar="OUT", help="Folder for the test set, the reconstructions and comparison.json/.md."),
    ],
    traced: Annotated[
        bool,
        typer.Option(
            "--traced",
            help="Issue 15's set (b): image the test volumes with the emission ray tracer (cm2 psf image; no 3D-LSV "
            "model in the loop) instead of the weights' forward model (set (a)).",
        ),
    ] = False,
    preset: Annotated[
        str | None,
        typer.Option(
            "--preset", "-p", help="--traced: the design to trace (default: the preset of an analytic forward model)."
        ),
    ] = None,
    binning: Annotated[
        int | None,
        typer.Option("--binning", "-b", help="--traced: the sensor binning (default: an analytic forward model's)."),
    ] = None,
    model: Annotated[
        Path | None,
        typer.Option(
            "--model",
            "-m",
            help="The 3D-LSV model (.lsv.h5) both reconstructions use instead of the weights' forward model (which "
            "still images set (a)): with --traced e.g. one built from a traced PSF scan of the design (cm2 psf simulate "
            "→ cm2 lsv build), the device's calibrated model; or a lower-rank build of the weights' own scan for a "
            "faster FISTA. Its geometry must be the weights'.",
        ),
    ] = None,
    imaging_model: Annotated[
        Path | None,
        typer.Option(
            "--imaging-model",
            help="Set (a): the 3D-LSV model (.lsv.h5) that images the test volumes instead of the weights' forward "
            "model, e.g. a higher-rank build of --model's scan.",
        ),
    ] = None,
    field_mm: Annotated[
        float | None,
        typer.Option(
            "--field-mm",
            min=0.01,
            help="Test volumes over a disc of this diameter, mm (e.g. 7: the whole field), the network given "
            "views that hold it instead of the training views; needs --model of the whole sensor, which images "
            "set (a) unless --imaging-model does. Default: the weights' training field.",
        ),
    ] = None,
    n_volumes: Annotated[int, typer.Option("--n-volumes", min=1, help="Test volumes.")] = 10,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of the test volumes (never the run's).")] = 1_000_003,
    fista_iterations: Annotated[
        int, typer.Option("--fista-iterations", min=0, help="FISTA iterations (0: score the network alone).")
    ] = 60,
    workers: Annotated[int, typer.Option("--workers", min=0, help="Dask workers making set (a).")] = 1,
    reuse: Annotated[
        bool,
        typer.Option(
            "--reuse",
            help="Reuse the reconstructions already in OUT made with the same options on the same test set (the "
            "test set itself is reused whenever it matches): e.g. score other weights beside a FISTA run already made.",
        ),
    ] = False,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """CM²Net beside FISTA (the weights' 3D-LSV model) on a test set it never saw, at the paper's
    densities (U[10, 100] per mm²) and diameters (8–20 µm), each at its own F1-optimal threshold,
    with the paper's Fig. 6 breakdowns: comparison.json, comparison.md and figures in OUT."""
    from cm2optics.cli.options import output_folder
    from cm2optics.errors import UserError
    from cm2optics.recon.net.testset import net_test_set
    from cm2optics.recon.net.weights import load_weights

    loaded = load_weights(weights)
    factory = None
    if traced:
        factory = _traced_factory(loaded.config.forward_model, preset, binning)
    elif preset is not None or binning is not None:
        raise UserError("--preset and --binning choose what --traced traces; give --traced or leave them out")
    for option, path in (("--model", model), ("--imaging-model", imaging_model)):
        if path is not None and not path.is_file():
            raise UserError(f"{option} {path}: no such file")
    if field_mm is not None and model is None:
        raise UserError("--field-mm: a whole-field test set needs --model, a 3D-LSV model of the whole sensor")
    if imaging_model is not None and traced:
        raise UserError("--imaging-model images set (a); --traced traces set (b): give one of them")
    inputs = [weights] + [path for path in (model, imaging_model) if path is not None]
    output_folder(out_dir, "net-testset", inputs=inputs, overwrite=overwrite)
    summary = net_test_set(
        weights,
        out_dir,
        n_volumes=n_volumes,
        seed=seed,
        fista_iterations=fista_iterations,
        workers=workers,
        reuse=reuse,
        traced=factory,
        model=model,
        imaging_model=imaging_model,
        field_mm=field_mm,
        log=(lambda _: None) if as_json else typer.echo,
    )
    keys = ("recall", "precision", "f1", "rmse_lateral_um", "rmse_axial_um", "seconds_per_volume", "threshold")
    shown = {name: {k: run.get(k) for k in keys} for name, run in summary["runs"].items()}
    shown |= {
        f"{name} at its operating threshold": {k: run["at_operating_threshold"].get(k) for k in keys}
        for name, run in summary["runs"].items()
        if run.get("at_operating_threshold")
    }
    typer.echo(json.dumps(shown, indent=1 if not as_json else 2, default=str))


def _traced_factory(forward_model: str, preset: str | None, binning: int | None):
    """``model → TracedSource`` of the design ``preset`` at ``binning``, both defaulting to those of
    an ``analytic:<preset>:<binning>`` forward model."""
    from cm2optics.design import load_preset
    from cm2optics.emission.image import TracedSource
    from cm2optics.errors import UserError

    parts = forward_model.split(":")
    if parts[0] == "analytic":
        preset = preset or parts[1]
        binning = binning or (int(parts[2]) if len(parts) > 2 else 1)
    if preset is None or binning is None:
        raise UserError(
            f"--traced: the weights' forward model {forward_model!r} names no design; give --preset and --binning"
        )
    design = load_preset(preset)
    return lambda model: TracedSource(design, model, binning)

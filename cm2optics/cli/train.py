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
    export: Annotated[
        Path | None,
        typer.Option(
            "--export",
            help="Do not train: write the weights of the run's latest checkpoint (out_dir/checkpoint.pt, a run still "
            "training or stopped) into this folder as a weights folder, e.g. reconstruction/cm2net-cpu.",
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

    if not config.is_file():
        raise FileNotFoundError(f"{config}: no such config file")
    settings = load_config(config)
    out_dir = Path(settings.out_dir)
    if export is not None:
        _export(out_dir, export, config, overwrite)
        return
    check_output(out_dir, command="train", kind="folder", inputs=[config], overwrite=overwrite, option="out_dir")
    claim_folder(out_dir, "train")
    summary = train(settings, resume=resume, max_steps=max_steps, device=device)
    shown = {k: v for k, v in summary.items() if k != "metrics"}
    if as_json:
        print(json.dumps(summary, indent=2, default=str))
    else:
        typer.echo(json.dumps(shown, indent=1, default=str))


def _export(run_dir: Path, folder: Path, config: Path, overwrite: bool) -> None:
    """``--export``: the run's latest checkpoint as a weights folder (written whole, or not at all)."""
    from rich.console import Console

    from cm2optics.recon.net.checkpoint import CheckpointError
    from cm2optics.recon.net.train import CHECKPOINT, export_weights

    if not (run_dir / CHECKPOINT).is_file():
        raise CheckpointError(f"{run_dir / CHECKPOINT}: no checkpoint to export (out_dir of {config}); train first")
    check_output(
        folder, command="train", kind="folder", inputs=[config, run_dir], overwrite=overwrite, option="--export"
    )
    saved = export_weights(run_dir, folder)
    Console(stderr=True).print(f"[green]weights:[/] {saved}")

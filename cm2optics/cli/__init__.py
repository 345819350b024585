"""The ``cm2`` command: one subcommand per pipeline stage, each a thin layer over one library call.

A mistake a user can make (bad preset, bad option, missing file, refused output) ends in one line
on stderr and exit status 2; a bug in cm2optics ends in an "internal error" report and exit
status 3 (``--debug`` or ``CM2_DEBUG=1`` print tracebacks); ``--json`` makes a command print
machine-readable output on stdout. The shared options, the list parser and the error handler
are in :mod:`cm2optics.cli.options`; the output policy in :mod:`cm2optics.formats.outputs`.
"""

from __future__ import annotations

import sys
import warnings
from typing import Annotated

import typer

import cm2optics
from cm2optics.cli.cad import cad_app
from cm2optics.cli.calibrate import calibrate_app
from cm2optics.cli.demo import compare_baselines_command, demo_command
from cm2optics.cli.design import design_app
from cm2optics.cli.evaluate import evaluate_command
from cm2optics.cli.illum import illum_app
from cm2optics.cli.lsv import lsv_app, simulate_command
from cm2optics.cli.options import DebugOption, set_debug
from cm2optics.cli.psf import psf_app
from cm2optics.cli.reconstruct import reconstruct_command
from cm2optics.cli.spectra import spectra_app
from cm2optics.cli.synth import synth_command
from cm2optics.cli.train import net_testset_command, train_command

__all__ = ["app"]

app = typer.Typer(
    help="cm2optics: design, simulate and reconstruct computational miniature mesoscopes (CM²).\n\n"
    "Start with `cm2 design show --preset cm2-v2`, export printable parts with "
    "`cm2 cad export --preset cm2-v2 --out cad/`, or run everything at demo size with `cm2 demo`.\n\n"
    "Outputs: no command deletes or overwrites a file it did not write; an existing output file or "
    "a non-empty folder another program wrote is replaced only with --overwrite. Exit status: 0 ok, "
    "1 checks failed, 2 a bad input (one line naming the file or option), 3 a bug (internal error), "
    "130 interrupted.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.add_typer(design_app, name="design")
app.add_typer(cad_app, name="cad")
app.add_typer(spectra_app, name="spectra")
app.add_typer(illum_app, name="illum")
app.add_typer(psf_app, name="psf")
app.add_typer(lsv_app, name="lsv")
app.add_typer(calibrate_app, name="calibrate")
app.command("simulate")(simulate_command)
app.command("synth")(synth_command)
app.command("evaluate")(evaluate_command)
app.command("reconstruct")(reconstruct_command)
app.command("demo")(demo_command)
app.command("compare-baselines")(compare_baselines_command)
app.command("train")(train_command)
app.command("net-testset")(net_testset_command)


def _version(value: bool) -> None:
    if value:
        print(f"cm2optics {cm2optics.__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show the version and exit.")
    ] = False,
    debug: DebugOption = False,
) -> None:
    """cm2optics command line."""
    set_debug(debug)
    warnings.showwarning = _warning_line


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Show a warning to a user as one line on stderr (no source file and line)."""
    print(f"warning: {message}", file=sys.stderr, flush=True)

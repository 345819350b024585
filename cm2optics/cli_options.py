"""What every ``cm2`` subcommand shares: the common options and the one-line user errors.

Its own module so that the stage CLIs (``cm2optics/*/cli.py``) and the top-level
:mod:`cm2optics.cli`, which imports them, can all use it without an import cycle.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console

from cm2optics.design import DesignError

__all__ = ["BinningOption", "JsonOption", "PresetOption", "user_errors"]

F = TypeVar("F", bound=Callable[..., Any])
err = Console(stderr=True, soft_wrap=True)

PresetOption = Annotated[
    str,
    typer.Option("--preset", "-p", help="Preset name (cm2-v2, cm2-v1) or path to a design YAML."),
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON on stdout.")]
BinningOption = Annotated[
    int, typer.Option("--binning", "-b", help="Sensor pixels per saved pixel along each axis (1–16).")
]


def user_errors(command: F) -> F:
    """Turn errors a user can cause into one clear line and exit status 2."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except (DesignError, ValueError, FileNotFoundError, NotADirectoryError, PermissionError) as error:
            err.print(f"[bold red]error:[/] {error}", highlight=False)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            err.print("[yellow]interrupted: nothing half-written was left behind[/]")
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]

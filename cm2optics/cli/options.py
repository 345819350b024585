"""What every ``cm2`` command shares: the common options, the one list parser, the output
checks and the error handler.

Errors: a :class:`~cm2optics.errors.UserError` (bad option, bad file, refused output) or a file
error (missing, a folder where a file was expected, no permission) ends in one line on stderr
naming the file or option, exit status 2. Anything else is a bug: a short "internal error"
message, the path of the written traceback and exit status 3. ``--debug`` or ``CM2_DEBUG=1``
prints the traceback always. Ctrl-C ends with exit status 130.
"""

from __future__ import annotations

import functools
import math
import os
import re
import signal
import socket
import sys
import tempfile
import threading
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any, TypeVar
from urllib.parse import urlparse

import typer
from rich.console import Console
from rich.markup import escape

from cm2optics.errors import UserError
from cm2optics.formats.outputs import check_output

__all__ = [
    "BinningOption",
    "JsonOption",
    "OverwriteOption",
    "PresetOption",
    "check_dask_address",
    "check_output",
    "output_folder",
    "parse_float_list",
    "parse_names",
    "parse_int_list",
    "user_errors",
]

F = TypeVar("F", bound=Callable[..., Any])
err = Console(stderr=True, soft_wrap=True)

#: Exit status of a user error, of an internal error (a bug), and of Ctrl-C.
USER_EXIT, INTERNAL_EXIT, INTERRUPT_EXIT = 2, 3, 130

PresetOption = Annotated[
    str,
    typer.Option("--preset", "-p", help="Preset name (cm2-v2, cm2-v1) or path to a design YAML."),
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON on stdout.")]
BinningOption = Annotated[
    int, typer.Option("--binning", "-b", help="Sensor pixels per saved pixel along each axis (1–16).")
]
OverwriteOption = Annotated[
    bool,
    typer.Option(
        "--overwrite",
        help="Replace an existing output file, or write into a non-empty folder another program wrote "
        "(files of the same name are replaced; no other file is deleted). Inputs are never overwritten.",
    ),
]
DebugOption = Annotated[
    bool, typer.Option("--debug", help="Print the full traceback of any error (also: CM2_DEBUG=1).")
]

_debug = False


def set_debug(value: bool) -> None:
    """Show tracebacks of every error (the top-level ``--debug``)."""
    global _debug
    _debug = bool(value)


def debugging() -> bool:
    return _debug or os.environ.get("CM2_DEBUG", "").strip().lower() not in ("", "0", "false", "no")


# ----------------------------------------------------------------------------- lists


def parse_float_list(
    text: str | None,
    n: int | tuple[int, int] | None = None,
    *,
    name: str,
    example: str = "",
    sep: str = ",",
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
    repeat_single: bool = False,
) -> tuple[float, ...] | None:
    """``"10,4.15,4.15"`` → ``(10.0, 4.15, 4.15)``; None stays None.

    n: the count required (an int), a range ``(least, most)``, or None for any count ≥ 1.
    low/high: the allowed range of each value (``low_open``/``high_open``: the bound excluded); values
    must be finite. repeat_single: one value stands for all ``n``. Any fault raises a
    :class:`UserError` naming ``name``, the text and an example.
    """
    if text is None:
        return None
    hint = f", e.g. {example}" if example else ""
    if isinstance(n, int):
        count = f"{n} number{'s' if n > 1 else ''}"
    elif n is not None:
        count = f"{n[0]}–{n[1]} numbers"
    else:
        count = "numbers"
    raw = str(text).lower().replace("×", "x") if sep == "x" else str(text)
    items = [part.strip() for part in raw.split(sep)]
    try:
        values = tuple(float(part) for part in items)
    except ValueError:
        raise UserError(f"{name} = {text!r}: give {count} separated by {sep!r}{hint}") from None
    if repeat_single and isinstance(n, int) and len(values) == 1:
        values = values * n
    least, most = (n, n) if isinstance(n, int) else (n if n is not None else (1, sys.maxsize))
    if not least <= len(values) <= most:
        raise UserError(f"{name} = {text!r}: give {count} separated by {sep!r}{hint} (got {len(values)})")
    for value in values:
        below = value <= low if low_open else value < low
        above = value >= high if high_open else value > high
        if not math.isfinite(value) or below or above:
            lower = ("> " if low_open else "≥ ") + f"{low:g}"
            bound = lower if math.isinf(high) else f"within {low:g}–{high:g}{' (excluded)' if high_open else ''}"
            raise UserError(f"{name} = {text!r}: every value must be finite and {bound} (got {value:g})")
    return values


def parse_names(
    text: str, *, name: str, allowed: tuple[str, ...] | None = None, n: int | None = None, what: str = "names"
) -> tuple[str, ...]:
    """``"stl, STEP"`` → ``("stl", "step")``: comma-separated names, no repeats.

    allowed: the names accepted (compared in lower case, returned in lower case); without it the
    names are kept as written (file names). n: the count required.
    """
    parts = [part.strip() for part in str(text).split(",")]
    if allowed is not None:
        parts = [p.lower() for p in parts if p]
    names = tuple(dict.fromkeys(parts)) if allowed is not None else tuple(parts)
    bad = [x for x in names if (allowed is not None and x not in allowed) or not x]
    if not names or bad or (n is not None and len(names) != n):
        choices = f"; allowed {what} are {', '.join(allowed)}" if allowed else ""
        count = f"{n} " if n is not None else ""
        raise UserError(f"{name} = {text!r}: give {count}{what} separated by commas{choices}")
    return names


def parse_int_list(text: str | None, n: int | tuple[int, int] | None = None, **kwargs: Any) -> tuple[int, ...] | None:
    """:func:`parse_float_list` for whole numbers (``"9x9x11"`` with ``sep="x"``)."""
    values = parse_float_list(text, n, **kwargs)
    if values is None:
        return None
    if not all(float(v).is_integer() for v in values):
        raise UserError(f"{kwargs['name']} = {text!r}: every value must be a whole number")
    return tuple(int(v) for v in values)


# ----------------------------------------------------------------------------- checks


def output_folder(
    path: Path, command: str, *, inputs: Iterable[Path | str | None] = (), overwrite: bool = False
) -> Path:
    """Check that ``command`` may write the folder ``path`` (:func:`check_output`), then mark it
    as this command's output, so that a re-run (or a resumed run) may write into it again."""
    from cm2optics.formats.outputs import claim_folder

    check_output(path, command=command, kind="folder", inputs=inputs, overwrite=overwrite)
    return claim_folder(path, command)


def check_dask_address(address: str | None, timeout_s: float = 3.0) -> None:
    """Refuse a Dask scheduler address that does not answer, before any work is done."""
    if not address:
        return
    url = urlparse(address if "://" in address else f"tcp://{address}")
    if url.scheme not in ("tcp", "tls"):
        return
    try:
        host, port = url.hostname, url.port
    except ValueError:
        host, port = None, None
    if not host or not port:
        raise UserError(f"--dask-address {address!r}: give tcp://HOST:PORT, e.g. tcp://127.0.0.1:8786")
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as error:
        raise UserError(
            f"--dask-address {address}: no Dask scheduler answers there ({error.strerror or error}); "
            "start one (dask scheduler) or leave the option out for a local cluster"
        ) from None


# ----------------------------------------------------------------------------- errors


def _file_message(error: OSError) -> str:
    """One line naming the user's file for an OSError."""
    name = error.filename
    if name is None:
        return str(error)
    reasons = {
        FileNotFoundError: "no such file or folder",
        IsADirectoryError: "is a folder, not a file",
        NotADirectoryError: "is not a folder",
        PermissionError: "permission denied",
        FileExistsError: "already exists",
    }
    reason = reasons.get(type(error), error.strerror or str(error))
    return f"{name}: {reason}"


def _user_message(error: BaseException) -> str | None:
    """The one-line message of a user error, or None for anything else (a bug)."""
    message = _plain_user_message(error)
    if message is not None:  # a reader's "no such file" for an existing folder: say what it is
        found = re.search(r"([^\s'\"=]+)'?: no such[\w ]*", message)
        if found and Path(found.group(1)).is_dir():
            message = message[: found.start()] + f"{found.group(1)}: is a folder, not a file" + message[found.end() :]
    return message


def _plain_user_message(error: BaseException) -> str | None:
    if isinstance(error, UserError):
        return str(error)
    if isinstance(error, (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)):
        text = str(error)
        return text if error.filename is None and text else _file_message(error)
    if _undecodable(error):
        path = _file_in_traceback(error)
        if path is not None:
            return f"{path}: cannot be read: not the expected file format ({type(error).__name__}: {error})"
    if isinstance(error, ValueError) and _raised_on_purpose(error):
        # A plain ValueError raised by a cm2optics validation (not by numpy & co.): a user's bad value.
        return str(error)
    return None


def _undecodable(error: BaseException) -> bool:
    """A reader's complaint about a file's bytes (text encoding, TIFF, HDF5, NumPy, ZIP)."""
    if isinstance(error, UnicodeDecodeError):
        return True
    name = type(error).__name__
    module = type(error).__module__.split(".")[0]
    return name in ("TiffFileError", "BadZipFile") or (module in ("tifffile", "h5py", "numpy") and "Error" in name)


def _file_in_traceback(error: BaseException) -> Path | None:
    """The user's file a failing cm2optics reader was reading (a local ``path``-like existing file)."""
    package = str(Path(__file__).resolve().parents[1])
    tb = error.__traceback__
    found = None
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_filename.startswith(package):
            for value in frame.f_locals.values():
                if isinstance(value, Path) and value.is_file():
                    found = value
        tb = tb.tb_next
    return found


def _raised_on_purpose(error: BaseException) -> bool:
    """Whether the innermost frame is a ``raise`` in cm2optics with a message that names a value."""
    frames = traceback.extract_tb(error.__traceback__)
    if not frames:
        return False
    last = frames[-1]
    package = str(Path(__file__).resolve().parents[1])
    return last.filename.startswith(package) and (last.line or "").lstrip().startswith("raise ") and bool(str(error))


def report_internal(error: BaseException) -> int:
    """Print the "this is a bug" message and where the traceback is; returns the exit status."""
    text = "".join(traceback.format_exception(type(error), error, error.__traceback__))
    if debugging():
        err.print(text, markup=False, highlight=False, end="")
    else:
        fd, name = tempfile.mkstemp(prefix="cm2-traceback-", suffix=".txt")
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
        err.print(
            f"[bold red]internal error[/] (this is a bug in cm2optics, not in your input): "
            f"{type(error).__name__}: {error}\ntraceback written to {name}; please report it "
            "(run with --debug or CM2_DEBUG=1 to print it)",
            highlight=False,
        )
    return INTERNAL_EXIT


def _terminate_as_interrupt() -> Any:
    """SIGTERM ends a command the way Ctrl-C does: finished work kept, nothing half-written left.
    Returns the handler it replaced (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, interrupt)


def user_errors(command: F) -> F:
    """Turn user errors into one line and exit 2, bugs into an internal-error report and exit 3."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        previous = _terminate_as_interrupt()
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except KeyboardInterrupt:
            err.print("[yellow]interrupted: nothing half-written was left behind[/]")
            raise typer.Exit(INTERRUPT_EXIT) from None
        except Exception as error:  # noqa: BLE001 - sorted into user errors and bugs below
            message = _user_message(error)
            if message is None:
                raise typer.Exit(report_internal(error)) from None
            if debugging():
                err.print("".join(traceback.format_exception(error)), markup=False, highlight=False, end="")
            message = " ".join(line.strip() for line in message.splitlines() if line.strip())  # one line
            err.print(f"[bold red]error:[/] {escape(message)}", highlight=False)
            raise typer.Exit(USER_EXIT) from None
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)

    return wrapper  # type: ignore[return-value]

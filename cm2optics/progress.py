"""One rich progress bar for long loops (a PSF scan, a training run), shared by every stage."""

from __future__ import annotations


def progress_bar(label: str, *extra_columns, enabled: bool = True):
    """A rich ``Progress`` with a label, bar, done/total, elapsed and remaining time.

    ``label`` is the first column's text (a rich format string such as ``"{task.description}"``);
    ``extra_columns`` are appended after the remaining time. The bar stays on screen when done
    (``transient=False``) and is silent when ``enabled`` is false.
    """
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn(label),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        *extra_columns,
        disable=not enabled,
        transient=False,
    )

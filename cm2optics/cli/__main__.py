"""``python -m cm2optics.cli``: the ``cm2`` command."""

from cm2optics.cli import app

app(prog_name="cm2")

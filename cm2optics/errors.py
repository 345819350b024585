"""The one base class of the errors a user can cause.

A :class:`UserError` is a mistake in what the user gave (a file, an option, a field): the ``cm2``
command reports it in one line with exit status 2. Anything else that escapes a command is a bug
in cm2optics and is reported as an internal error (exit status 3). The domain errors
(``DesignError``, ``ScanError``, ``VolumeError``, ``ModelError``) derive from it; it derives from
``ValueError`` so that code catching ``ValueError`` keeps working.

This module imports nothing from the package, so every layer (design, formats, stages, cli) may use it.
"""

from __future__ import annotations

__all__ = ["OutputError", "UserError"]


class UserError(ValueError):
    """A bad input: the message names the file or the field, the value and what is allowed."""


class OutputError(UserError):
    """An output the command refuses to write (it would overwrite an input or a user's files)."""

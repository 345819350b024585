"""The one base class of every file-format error."""

from __future__ import annotations

from cm2optics.errors import UserError

__all__ = ["FormatError"]


class FormatError(UserError):
    """A file that does not follow its format; the message names the file (and line or field)."""

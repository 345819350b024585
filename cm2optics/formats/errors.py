"""The one base class of every file-format error."""

from __future__ import annotations

__all__ = ["FormatError"]


class FormatError(ValueError):
    """A file that does not follow its format; the message names the file (and line or field)."""

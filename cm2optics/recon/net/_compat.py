"""The few names CM²Net takes from modules that are moving (``volume_io`` → ``formats``).

Kept in one place so that the package restructuring changes one import here, not every module.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

try:  # the restructured layout
    from cm2optics.formats.volume_io import Emitters, VolumeGrid  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - the layout before the move
    from cm2optics.volume_io import Emitters, VolumeGrid

__all__ = ["Emitters", "VolumeGrid", "write_atomic"]


def write_atomic(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary name next to ``path``, then rename it to ``path``
    (a reader never sees a half-written file; the temporary goes away on failure)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path

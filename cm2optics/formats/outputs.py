"""The output policy of every ``cm2`` command: never delete or overwrite what the command did not create.

- An output that is an input, lies inside an input folder, or would contain an input is refused.
- An output under an existing regular file, or one whose nearest existing folder is read-only, is
  refused with a message naming the user's path (not a temporary name).
- An existing output file, or a non-empty folder that is not this command's own earlier output,
  is replaced only with ``overwrite=True`` (``--overwrite``). A command recognises its own folder
  by the marker :data:`MARKER` it leaves there (``{"command": ..., "key": ...}``).
- A folder is written in a staging folder beside it and swapped in by :func:`swap_in_folder`,
  which never removes files it did not write.

Imports no stage; stages (``write_scan``, ``simulate_scan``) and the CLI call it.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cm2optics.errors import OutputError

__all__ = [
    "MARKER",
    "output_lock",
    "OutputError",
    "check_output",
    "claim_folder",
    "folder_owner",
    "swap_in_folder",
]

#: File a command leaves in each folder it writes: what wrote it (and with which inputs).
MARKER = ".cm2optics-output.json"


def _resolved(path: str | Path) -> Path:
    return Path(os.path.abspath(Path(path).expanduser()))


def _inside(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def folder_owner(folder: str | Path) -> dict[str, Any] | None:
    """The marker of a folder a cm2 command wrote (``{"command": ..., "key": ...}``), else None."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def claim_folder(folder: str | Path, command: str, key: str | None = None) -> Path:
    """Create ``folder`` (if needed) and mark it as ``command``'s output."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MARKER).write_text(json.dumps({"command": command, "key": key}) + "\n", encoding="utf-8")
    return folder


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _visible(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name != MARKER]


def check_output(
    path: str | Path,
    *,
    command: str,
    kind: str = "file",
    inputs: Iterable[str | Path | None] = (),
    overwrite: bool = False,
    option: str = "--out",
) -> Path:
    """Check that ``command`` may write ``path`` (a ``"file"`` or a ``"folder"``); returns it resolved.

    Raises :class:`OutputError` (a user error naming ``option`` and the path) when it may not.
    Nothing is created or changed.
    """
    if kind not in ("file", "folder"):
        raise ValueError(f"kind = {kind!r}: must be file or folder")
    target = _resolved(path)
    shown = f"{option} {path}"
    for item in inputs:
        if item is None or not Path(item).exists():
            continue  # a preset name, or a file that the command will report missing
        source = _resolved(item)
        if target == source:
            raise OutputError(f"{shown}: is the input {item}; write the output to another path")
        if source.is_dir() and _inside(target, source):
            raise OutputError(f"{shown}: lies inside the input folder {item}; write the output elsewhere")
        if kind == "folder" and _inside(source, target):
            raise OutputError(f"{shown}: would hold the input {item}; write the output to another folder")
    ancestor = target.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    for parent in [target.parent, *target.parent.parents]:
        if parent.exists() and not parent.is_dir():
            raise OutputError(f"{shown}: {parent} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OutputError(f"{shown}: the folder {ancestor} is not writable")
    if kind == "file":
        if target.is_dir():
            raise OutputError(f"{shown}: is a folder; give a file name")
        if target.exists():
            if not os.access(target, os.W_OK):
                raise OutputError(f"{shown}: exists and is read-only")
            if not overwrite:
                raise OutputError(f"{shown}: exists; pass --overwrite to replace it")
        return target
    if target.exists():
        if not target.is_dir():
            raise OutputError(f"{shown}: is a file, not a folder")
        if not os.access(target, os.W_OK | os.X_OK):
            raise OutputError(f"{shown}: the folder is not writable")
        owner = folder_owner(target)
        own = owner is not None and owner.get("command") == command
        if _visible(target) and not own and not overwrite:
            raise OutputError(
                f"{shown}: the folder is not empty and was not written by `cm2 {command}`; "
                "choose an empty or new folder, or pass --overwrite to write into it (no file is deleted)"
            )
    return target


def swap_in_folder(staging: Path, folder: Path, command: str) -> Path:
    """Move the finished ``staging`` folder to ``folder`` without deleting files the command did not write.

    ``folder`` absent or empty: one rename. ``folder`` this command's earlier output that holds
    nothing else (every file listed in its marker's ``files``): the old folder is renamed aside and
    removed after the rename. Otherwise each new file replaces its namesake and the rest stay.
    """
    staging, folder = Path(staging), Path(folder)
    files = sorted(str(p.relative_to(staging)) for p in staging.rglob("*") if p.is_file() and p.name != MARKER)
    (staging / MARKER).write_text(json.dumps({"command": command, "files": files}) + "\n", encoding="utf-8")
    os.chmod(staging, 0o777 & ~_umask())  # mkdtemp made it private; the folder gets ordinary permissions
    if not folder.exists():
        os.replace(staging, folder)
        return folder
    if not _visible(folder):
        (folder / MARKER).unlink(missing_ok=True)
        folder.rmdir()
        os.replace(staging, folder)
        return folder
    owner = folder_owner(folder) or {}
    listed = set(owner.get("files") or ())
    present = {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() and p.name != MARKER}
    if owner.get("command") == command and present <= listed:
        aside = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old-", dir=folder.parent))
        os.replace(folder, aside / "old")
        os.replace(staging, folder)
        shutil.rmtree(aside, ignore_errors=True)
        return folder
    stale = listed - set(files) if owner.get("command") == command else set()
    for name in files + [MARKER]:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        os.replace(staging / name, folder / name)
    for name in stale:
        (folder / name).unlink(missing_ok=True)
    shutil.rmtree(staging, ignore_errors=True)
    return folder


@contextmanager
def output_lock(path: str | Path, command: str) -> Iterator[Path]:
    """Hold ``.<name>.lock`` beside ``path`` while ``command`` writes it; a second run into the same
    output is refused at once (:class:`OutputError`) instead of mixing its files with the first's."""
    import fcntl

    target = _resolved(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    lock = target.parent / f".{target.name}.lock"
    handle = open(lock, "a+")  # noqa: SIM115 - held for the whole block
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputError(
                f"--out {path}: another `cm2 {command}` is writing there now (lock {lock}); "
                "wait for it to finish or choose another --out"
            ) from None
        try:
            yield lock
        finally:
            lock.unlink(missing_ok=True)
    finally:
        handle.close()

"""Training checkpoints: everything a run needs to continue exactly where it stopped.

One file (``checkpoint.pt``, written under a temporary name and renamed) with the network,
optimiser and scheduler states, the epoch, the step within it and the global step, the loss
history, the RNG states (torch, numpy's global generator, Python's ``random``) and the config
hash; resuming with a config of another hash is refused (:class:`CheckpointError`).
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cm2optics.errors import UserError
from cm2optics.formats.atomic import write_atomic

__all__ = ["CheckpointError", "load_checkpoint", "rng_state", "save_checkpoint", "set_rng_state"]

VERSION = 1


class CheckpointError(UserError):
    """A checkpoint that cannot be resumed (missing, unreadable, or another config)."""


def rng_state() -> dict[str, Any]:
    return {"torch": torch.random.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def set_rng_state(state: dict[str, Any]) -> None:
    torch.random.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def save_checkpoint(path: str | Path, **state: Any) -> Path:
    """Write ``state`` (plus the RNG states and a version) atomically."""
    payload = {"version": VERSION, "rng": rng_state(), **state}
    return write_atomic(Path(path), lambda tmp: torch.save(payload, tmp))


def load_checkpoint(path: str | Path, config_hash: str) -> dict[str, Any]:
    """Read a checkpoint and check that it belongs to a config of hash ``config_hash``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # noqa: BLE001 - any unreadable file is the same user error
        raise CheckpointError(f"{path}: not a readable checkpoint ({error})") from None
    if not isinstance(state, dict) or state.get("version") != VERSION:
        raise CheckpointError(f"{path}: not a CM²Net checkpoint of version {VERSION}")
    if state.get("config_hash") != config_hash:
        raise CheckpointError(
            f"{path}: made with config {str(state.get('config_hash'))[:12]}…, this config is {config_hash[:12]}… "
            "(only the runtime fields — epochs, out_dir, threads, workers, checkpoint_every — may change on resume)"
        )
    return state

"""Files around a synthetic data set: its config file and the export of samples for the other commands."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from cm2optics.errors import UserError

__all__ = ["export_sample", "read_config_file"]


def read_config_file(path: Path) -> dict[str, Any]:
    """A JSON/YAML mapping of SynthConfig fields (a manifest's ``config`` works too)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such config file")
    try:
        text = path.read_text(encoding="utf-8")
        if path.suffix.lower() in (".yaml", ".yml"):
            import yaml

            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
    except (UnicodeDecodeError, ValueError) as error:  # yaml.YAMLError is not a ValueError
        raise UserError(f"{path}: not a readable JSON/YAML synth config ({type(error).__name__}: {error})") from None
    except Exception as error:
        if type(error).__module__.startswith("yaml"):
            raise UserError(f"{path}: not a readable YAML synth config ({error})") from None
        raise
    if not isinstance(data, dict):
        raise UserError(f"{path}: a synth config is a mapping of SynthConfig fields")
    return data.get("config", data)


def export_sample(sample_path: str | Path, out_dir: str | Path) -> dict[str, str]:
    """Write a sample's measurement (float32 TIFF), volume (ImageJ TIFF) and emitters (CSV) for
    ``cm2 reconstruct`` and ``cm2 evaluate``; returns the paths."""
    import numpy as np
    import tifffile

    from cm2optics.formats.atomic import write_atomic
    from cm2optics.formats.emitters import write_emitters
    from cm2optics.formats.volume import write_volume
    from cm2optics.synth.dataset import read_sample

    data = read_sample(sample_path)
    out_dir = Path(out_dir)
    stem = Path(sample_path).stem
    paths = {"measurement": out_dir / f"{stem}_measurement.tif", "emitters": out_dir / f"{stem}_emitters.csv"}
    measurement = np.ascontiguousarray(data["measurement"], dtype=np.float32)
    write_atomic(paths["measurement"], lambda tmp: tifffile.imwrite(tmp, measurement))
    write_emitters(paths["emitters"], data["emitters"])
    if "volume" in data:
        paths["volume"] = out_dir / f"{stem}_volume.tif"
        write_volume(paths["volume"], data["volume"], tuple(data["grid"]["voxel_um"]))
    return {k: str(v) for k, v in paths.items()}

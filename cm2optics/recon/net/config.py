"""CM²Net's configuration: one frozen, validated dataclass, read from YAML, with a hash.

Every size is a field: the network's width (``channels``) and depth (``blocks`` residual blocks
per sub-network), the number of output planes (``n_planes``, the volume grid's ``nz``) and of
refocused planes (``refocus_planes``; 0 picks one plane per pixel of disparity over the volume's
depth range), the patch size (``synth.patch_px``), and the training schedule. The synthetic data
recipe is a nested :class:`~cm2optics.synth.config.SynthConfig` (``synth:`` in YAML).

:meth:`NetConfig.hash` fingerprints everything that changes the weights a run produces; the
runtime fields (:data:`RUNTIME_FIELDS`: where to write, how many threads/workers, how many
epochs to run, how often to checkpoint) are left out, so a run can be resumed with more epochs or
on another machine. Relative paths in a YAML file are taken from the current directory.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import yaml

from cm2optics.errors import UserError
from cm2optics.synth.config import SynthConfig

__all__ = ["ABLATIONS", "KEEP_WEIGHTS", "LOSSES", "NORMS", "RUNTIME_FIELDS", "ConfigError", "NetConfig", "load_config"]

NORMS = ("batch", "group", "none")
KEEP_WEIGHTS = ("last", "best", "average")
LOSSES = ("bce", "weighted-bce", "focal")
TARGETS = ("occupancy", "emission")
#: The paper's ablations (Fig. 4): the full network, or without view demixing, or one branch.
ABLATIONS = ("none", "no-demix", "enhancement-only", "synthesis-only")
#: Fields that do not change the weights a step produces (left out of the hash).
RUNTIME_FIELDS = frozenset({"out_dir", "epochs", "workers", "threads", "checkpoint_every", "progress"})


class ConfigError(UserError):
    """A configuration that cannot be used (names the field, the value and what is allowed)."""


def _int(name: str, value: Any, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"{name} = {value!r}: must be an integer within {low}–{high}")


def _float(name: str, value: Any, low: float, high: float, *, open_low: bool = False) -> None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} = {value!r}: must be a number") from None
    if not math.isfinite(v) or v > high or v < low or (open_low and v == low):
        bound = "<" if open_low else "≤"
        raise ConfigError(f"{name} = {value!r}: must satisfy {low} {bound} {name} ≤ {high}")


def _choice(name: str, value: Any, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"{name} = {value!r}: must be one of {', '.join(allowed)}")


@dataclass(frozen=True)
class NetConfig:
    """Architecture — channels: feature maps per layer; blocks: residual blocks (conv–BN–PReLU–
    conv–BN) per sub-network (demixing, view synthesis, enhancement); fusion_blocks: residual
    blocks after the two branches are summed; n_planes: output planes P (= the grid's nz);
    refocus_planes: shift-and-add planes N (0: one per pixel of disparity over the depth range);
    norm: ``batch`` (synchronised across DDP ranks), ``group`` or ``none``; ablation: ``none``
    (the full network), ``no-demix`` (the raw views go to the refocusing and the view synthesis;
    no demixing net, no demixing loss), ``enhancement-only`` (refocus enhancement, no view
    synthesis) or ``synthesis-only`` (view synthesis, no refocusing branch) — the paper's ablations.

    Data — forward_model: a model file (3D-LSV HDF5 or PSF stack), ``analytic:<preset>:<binning>``
    (the analytic CM²-like model of :mod:`cm2optics.lsv.toy`, built in memory) or
    ``toy:gaussian`` (the depth-wise Gaussian toy, tests); toy_sensor_px: the toy's sensor side;
    synth: the synthetic recipe (views, patches, densities, noise); seed: data and weights seed;
    train_volumes: volumes per epoch; val_volumes: validation volumes (fixed);
    fresh_volumes: new volumes every epoch (else the same ``train_volumes`` every epoch);
    interleave_volumes: consecutive batches cycle over groups of this many volumes, each batch
    from one volume (1: a volume's batches in a row) — with as many DataLoader ``workers``, each
    worker renders only its own volume of the group instead of every one;
    register_views: resample each view onto the model's affine geometry before the network
    (:mod:`~cm2optics.recon.net.register`: the lenslets' distortion differs, so off axis the nine
    views disagree by up to tens of pixels), in training and at inference alike;
    mix_forward_model, mix_fraction, mix_synth: a second data source mixed into training — of
    each epoch's ``train_volumes``, round(mix_fraction · train_volumes) (seeded choice) are imaged
    through ``mix_forward_model`` with the recipe ``synth`` changed by the fields in ``mix_synth``
    (e.g. a smaller field and views: fov_mm, view_px, patches_per_volume; the grid and patch size
    stay the network's), from their own seed; the refocusing shifts must agree (empty / 0: none);
    val_mix_volumes: validation volumes of the mixed source (its model and recipe, its own seed),
    scored beside the ``val_volumes`` (0: none);
    curriculum_epochs: epochs over which the density grows linearly from
    curriculum_start_density (per mm²) to ``synth.density_per_mm2`` (0: no curriculum);
    target: ``occupancy`` (fraction of each voxel inside an emitter, the paper's binned balls)
    or ``emission`` (clipped to 1).

    Training — batch_size: the global batch (split over DDP ranks); lr, lr_factor, lr_patience:
    Adam and ReduceLROnPlateau on the validation loss; alpha_demix, alpha_volume: loss weights;
    volume_loss: ``bce``, ``weighted-bce`` (weight 1 + (pos_weight − 1)·target) or ``focal``
    (γ = focal_gamma); border_px: patch margin left out of the volume loss (−1: the largest
    refocusing shift); detect_threshold: the validation's detection threshold on the sigmoid output
    (also the inference's default for weights that carry no operating threshold chosen on validation
    volumes, :mod:`~cm2optics.recon.net.operating`);
    val_every: also score the validation volumes every this many steps within an epoch (0: at the
    epoch ends only); keep_weights: the weights the run ends with (its ``weights/`` folder and
    ``cm2 train --export``): ``last`` (the last step's), ``best`` (those of the validation scoring
    with the highest score: the F1 at the best of :data:`VALIDATION_THRESHOLDS`, averaged over the
    two sources when there is a mixed one) or ``average`` (the mean of the weights at the last
    ``keep_average`` validation scorings). All three out of the hash at their defaults (0, last).

    Start — init_weights: a weights folder whose learned tensors the run starts from (fine-tuning
    on another forward model: the refocusing comes from this config's model, see
    :func:`~cm2optics.recon.net.train.start_from_weights`; empty: a fresh network).

    Runtime — epochs, out_dir, checkpoint_every (steps; 0: at epoch ends only), workers
    (DataLoader workers), threads (torch threads per process; 0: torch's default), progress.
    """

    channels: int = 32
    blocks: int = 4
    fusion_blocks: int = 1
    n_planes: int = 80
    refocus_planes: int = 0
    norm: str = "batch"
    ablation: str = "none"
    forward_model: str = "analytic:cm2-v2:1"
    toy_sensor_px: int = 160
    synth: SynthConfig = field(default_factory=SynthConfig)
    seed: int = 0
    train_volumes: int = 64
    val_volumes: int = 4
    fresh_volumes: bool = True
    interleave_volumes: int = 1
    register_views: bool = False
    mix_forward_model: str = ""
    mix_fraction: float = 0.0
    mix_synth: dict = field(default_factory=dict)
    val_mix_volumes: int = 0
    curriculum_epochs: int = 0
    curriculum_start_density: tuple[float, float] = (5.0, 20.0)
    target: str = "occupancy"
    batch_size: int = 2
    lr: float = 1e-4
    lr_factor: float = 0.9
    lr_patience: int = 2
    alpha_demix: float = 1.0
    alpha_volume: float = 1.0
    volume_loss: str = "bce"
    pos_weight: float = 10.0
    focal_gamma: float = 2.0
    init_weights: str = ""
    border_px: int = -1
    detect_threshold: float = 0.5
    val_every: int = 0
    keep_weights: str = "last"
    keep_average: int = 4
    epochs: int = 10
    out_dir: str = "runs/cm2net"
    checkpoint_every: int = 0
    workers: int = 0
    threads: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.synth, dict):
            try:
                object.__setattr__(self, "synth", SynthConfig.from_dict(self.synth))
            except ValueError as error:
                raise ConfigError(f"synth: {error}") from None
        if not isinstance(self.synth, SynthConfig):
            raise ConfigError(f"synth = {self.synth!r}: must be a mapping of synthetic-data parameters")
        _int("channels", self.channels, 1, 4096)
        _int("blocks", self.blocks, 0, 256)
        _int("fusion_blocks", self.fusion_blocks, 0, 64)
        _int("n_planes", self.n_planes, 1, 4096)
        _int("refocus_planes", self.refocus_planes, 0, 4096)
        _choice("norm", self.norm, NORMS)
        _choice("ablation", self.ablation, ABLATIONS)
        if not isinstance(self.forward_model, str) or not self.forward_model:
            raise ConfigError(
                f"forward_model = {self.forward_model!r}: must name a model file, analytic:… or toy:gaussian"
            )
        if not isinstance(self.init_weights, str):
            raise ConfigError(f"init_weights = {self.init_weights!r}: must name a weights folder (or be empty)")
        _int("toy_sensor_px", self.toy_sensor_px, 16, 100_000)
        _int("seed", self.seed, 0, 2**31 - 1)
        _int("train_volumes", self.train_volumes, 1, 10_000_000)
        _int("val_volumes", self.val_volumes, 0, 1_000_000)
        if not isinstance(self.fresh_volumes, bool):
            raise ConfigError(f"fresh_volumes = {self.fresh_volumes!r}: must be true or false")
        _int("interleave_volumes", self.interleave_volumes, 1, 10_000_000)
        if not isinstance(self.register_views, bool):
            raise ConfigError(f"register_views = {self.register_views!r}: must be true or false")
        self._check_mix()
        _int("curriculum_epochs", self.curriculum_epochs, 0, 100_000)
        try:
            lo, hi = (float(v) for v in self.curriculum_start_density)
        except (TypeError, ValueError):
            raise ConfigError(
                f"curriculum_start_density = {self.curriculum_start_density!r}: must be (low, high) per mm²"
            ) from None
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise ConfigError(f"curriculum_start_density = {self.curriculum_start_density!r}: need 0 ≤ low ≤ high")
        object.__setattr__(self, "curriculum_start_density", (lo, hi))
        _choice("target", self.target, TARGETS)
        _int("batch_size", self.batch_size, 1, 65_536)
        _float("lr", self.lr, 0.0, 1.0, open_low=True)
        _float("lr_factor", self.lr_factor, 0.0, 1.0, open_low=True)
        _int("lr_patience", self.lr_patience, 0, 10_000)
        _float("alpha_demix", self.alpha_demix, 0.0, 1e6)
        _float("alpha_volume", self.alpha_volume, 0.0, 1e6)
        _choice("volume_loss", self.volume_loss, LOSSES)
        _float("pos_weight", self.pos_weight, 0.0, 1e6, open_low=True)
        _float("focal_gamma", self.focal_gamma, 0.0, 100.0)
        _int("border_px", self.border_px, -1, 100_000)
        _float("detect_threshold", self.detect_threshold, 0.0, 1.0, open_low=True)
        _int("val_every", self.val_every, 0, 10_000_000)
        _choice("keep_weights", self.keep_weights, KEEP_WEIGHTS)
        _int("keep_average", self.keep_average, 1, 1000)
        _int("val_mix_volumes", self.val_mix_volumes, 0, 1_000_000)
        if self.val_mix_volumes and not self.mix_forward_model:
            raise ConfigError(f"val_mix_volumes = {self.val_mix_volumes}: needs a mixed source (mix_forward_model)")
        if self.keep_weights != "last" and not (self.val_volumes or self.val_mix_volumes):
            raise ConfigError(f"keep_weights = {self.keep_weights}: needs validation volumes (val_volumes)")
        _int("epochs", self.epochs, 0, 1_000_000)
        _int("checkpoint_every", self.checkpoint_every, 0, 10_000_000)
        _int("workers", self.workers, 0, 256)
        _int("threads", self.threads, 0, 1024)
        s = self.synth
        if not (s.view_px and s.patch_px):
            raise ConfigError(
                f"synth.view_px = {s.view_px}, synth.patch_px = {s.patch_px}: CM²Net trains on patches of views; both must be > 0"
            )
        if s.patches_per_volume < 1:
            raise ConfigError(f"synth.patches_per_volume = {s.patches_per_volume}: must be ≥ 1")
        if s.grid.shape[0] != self.n_planes:
            raise ConfigError(
                f"n_planes = {self.n_planes}: the synthetic grid has {s.grid.shape[0]} planes "
                f"(depth_um = {s.depth_um} at {s.voxel_um[0]} µm: nz = depth/dz + 1); make them agree"
            )
        if self.border_px >= 0 and 2 * self.border_px >= s.patch_px:
            raise ConfigError(f"border_px = {self.border_px}: leaves nothing of a {s.patch_px}-px patch")

    def _check_mix(self) -> None:
        if not isinstance(self.mix_forward_model, str):
            raise ConfigError(f"mix_forward_model = {self.mix_forward_model!r}: must name a model file (or be empty)")
        _float("mix_fraction", self.mix_fraction, 0.0, 1.0)
        if not isinstance(self.mix_synth, dict):
            raise ConfigError(f"mix_synth = {self.mix_synth!r}: must be a mapping of synth fields to change")
        if bool(self.mix_forward_model) != (self.mix_fraction > 0):
            raise ConfigError(
                f"mix_forward_model = {self.mix_forward_model!r}, mix_fraction = {self.mix_fraction}: "
                "a mixed source needs both (or neither)"
            )
        if self.mix_synth and not self.mix_forward_model:
            raise ConfigError("mix_synth is set but mix_forward_model is empty")
        fixed = sorted({"voxel_um", "depth_um", "patch_px"} & set(self.mix_synth))
        if fixed:
            raise ConfigError(f"mix_synth: {', '.join(fixed)} must stay the network's (the grid and patches)")
        if self.mix_forward_model:
            self.mix_config()  # its recipe must be valid

    def mix_config(self) -> NetConfig:
        """The config of the mixed source's volumes: its model, ``synth`` changed by ``mix_synth``."""
        try:
            synth = SynthConfig.from_dict({**self.synth.to_dict(), **self.mix_synth})
        except (TypeError, ValueError) as error:
            raise ConfigError(f"mix_synth: {error}") from None
        return replace(
            self,
            forward_model=self.mix_forward_model,
            synth=synth,
            mix_forward_model="",
            mix_fraction=0.0,
            mix_synth={},
            val_mix_volumes=0,
        )

    # -- dictionaries, YAML, hash ---------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, SynthConfig):
                value = value.to_dict()
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NetConfig:
        if not isinstance(data, dict):
            raise ConfigError(f"a CM²Net config must be a mapping, got {type(data).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"unknown CM²Net parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}")
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**values)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, allow_unicode=True)

    def save(self, path: str | Path) -> Path:
        from cm2optics.formats.atomic import write_atomic

        text = "# CM²Net configuration (cm2optics.recon.net.config.NetConfig)\n" + self.to_yaml()
        return write_atomic(Path(path), lambda tmp: tmp.write_text(text, encoding="utf-8"))

    def hash(self) -> str:
        """SHA-256 (hex) of the fields that change the weights (not :data:`RUNTIME_FIELDS`; nor
        ``ablation`` when ``none`` nor an empty ``init_weights`` nor ``interleave_volumes`` of 1 nor
        ``register_views`` when false nor the ``mix_*`` fields when there is no mixed source nor
        ``val_mix_volumes``, ``val_every``, ``keep_weights`` at 0, 0, last (``keep_average`` only
        with ``average``), so that configs written before they existed keep their hash)."""
        data = {k: v for k, v in self.to_dict().items() if k not in RUNTIME_FIELDS}
        if data["ablation"] == "none":
            del data["ablation"]
        if not data["init_weights"]:
            del data["init_weights"]
        if data["interleave_volumes"] == 1:
            del data["interleave_volumes"]
        if not data["register_views"]:
            del data["register_views"]
        if not data["mix_forward_model"]:
            for name in ("mix_forward_model", "mix_fraction", "mix_synth"):
                del data[name]
        for name, default in (("val_mix_volumes", 0), ("val_every", 0), ("keep_weights", "last")):
            if data[name] == default:
                del data[name]
        if data.get("keep_weights") != "average":
            del data["keep_average"]
        return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()

    def with_changes(self, **changes: Any) -> NetConfig:
        return replace(self, **changes)

    def volume_grid(self):
        """The training volumes' grid (z, y, x)."""
        return self.synth.grid


def load_config(path: str | Path) -> NetConfig:
    """Read a YAML config; a missing file or a bad value raises :class:`ConfigError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({error})") from None
    try:
        return NetConfig.from_dict(data or {})
    except (ConfigError, TypeError) as error:
        raise ConfigError(f"{path}: {error}") from None

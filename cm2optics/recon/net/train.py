"""Training CM²Net: plain functions in the manner of torchvision's reference scripts.

- :func:`train_one_epoch`: one pass over a DataLoader (progress bar, optional checkpoints).
- :func:`evaluate`: validation loss and detection metrics (recall, precision, F1, Jaccard,
  lateral/axial RMSE from :mod:`cm2optics.metrics`), pooled over the validation patches.
- :func:`train`: the run — config in, ``out_dir`` out (``checkpoint.pt``, ``history.json``,
  ``loss_curve.png``, ``weights/``); ``resume=True`` continues from the checkpoint exactly (same
  data order, optimiser and scheduler states, RNG states): a run stopped after any step and
  resumed ends with the weights of an uninterrupted one.

Adam (``lr``, the paper's 1e-4) and ReduceLROnPlateau on the validation loss (×``lr_factor``
after ``lr_patience`` stalled epochs, counted as Keras/TF does — the paper's framework).

Distributed: the same script under ``torchrun --nproc_per_node=K`` (env ``WORLD_SIZE`` > 1):
gloo on CPU, NCCL on GPUs; each rank takes its contiguous share of every global batch, batch
norm pools its statistics over the ranks (:class:`~.model.SyncBatchNorm2d`) and DDP averages the
gradients, so K processes follow the loss curve of one with the same global batch. Rank 0
writes the files.

``python -m cm2optics.recon.net.train CONFIG [--resume]`` runs :func:`train` (the ``cm2 train``
command will call the same function).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from cm2optics.formats.atomic import write_atomic
from cm2optics.formats.volume import VolumeGrid
from cm2optics.progress import progress_bar
from cm2optics.recon.net.checkpoint import CheckpointError, load_checkpoint, save_checkpoint, set_rng_state
from cm2optics.recon.net.config import NetConfig, load_config
from cm2optics.recon.net.data import (
    PatchDataset,
    PatchSource,
    epoch_items,
    forward_imaging,
    pixel_voxel_um,
    rank_items,
    steps_per_epoch,
    validation_items,
)
from cm2optics.recon.net.loss import cm2net_loss
from cm2optics.recon.net.model import CM2Net, build_net
from cm2optics.recon.net.refocus import RefocusPlanes, refocus_planes

__all__ = [
    "evaluate",
    "export_weights",
    "kept_weights",
    "make_net",
    "make_optimiser",
    "make_scheduler",
    "train",
    "train_one_epoch",
]

CHECKPOINT, HISTORY, CURVE = "checkpoint.pt", "history.json", "loss_curve.png"
#: Where a run keeps the weights of its best validation scoring, and those of its last ones
#: (``keep_weights`` best / average).
BEST, AVERAGE = "best.pt", "average.pt"
#: Thresholds at which a run's validation scorings take the F1 (``f1_best``) when it keeps weights
#: by validation, scores every ``val_every`` steps or a mixed source's volumes.
VALIDATION_THRESHOLDS = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


# ----------------------------------------------------------------------------- pieces
def make_net(config: NetConfig) -> tuple[CM2Net, int]:
    """A fresh network for ``config`` (its refocusing from the forward model's geometry) and the
    loss border (px)."""
    imaging = forward_imaging(config)
    grid = config.synth.grid
    z = grid.axis_mm(0)
    planes = refocus_planes(imaging.source, (float(z[0]), float(z[-1])), config.refocus_planes)
    if config.mix_forward_model:  # the network's refocusing serves both sources' views
        mixed = refocus_planes(
            forward_imaging(config.mix_config()).source, (float(z[0]), float(z[-1])), config.refocus_planes
        )
        if not np.array_equal(mixed.shifts_px, planes.shifts_px):
            raise ValueError(
                f"mix_forward_model = {config.mix_forward_model!r}: its refocusing shifts differ from forward_model's "
                "(the network has one set)"
            )
    border = config.border_px if config.border_px >= 0 else planes.max_shift_px
    if 2 * border >= config.synth.patch_px:
        raise ValueError(
            f"the refocusing shifts reach {border} px: a {config.synth.patch_px}-px patch keeps nothing; "
            "use larger patches or set border_px"
        )
    return build_net(config, planes, z), border


def start_from_weights(net: CM2Net, folder: str | Path) -> None:
    """Fine-tuning: load the learned tensors of the weights ``folder`` (the same architecture)
    into ``net``, keeping ``net``'s own refocusing (shifts and plane depths from its forward
    model). The learned resampling of the refocus planes onto the output depths keeps what
    training added to its initial linear interpolation, the interpolation moved onto ``net``'s
    planes (the same disparity index may sit at another depth in another model)."""
    from cm2optics.recon.net.weights import load_weights

    loaded = load_weights(folder)
    source, target = loaded.net.state_dict(), net.state_dict()
    refocusing = {"refocus.shifts", "refocus_z_mm", "refocus_disparity_px"}
    wrong = sorted(
        k
        for k in (set(source) | set(target)) - refocusing
        if k not in source or k not in target or source[k].shape != target[k].shape
    )
    if wrong:
        raise ValueError(f"init_weights {folder}: not this config's architecture ({', '.join(wrong[:4])} differ)")
    if not torch.allclose(source["volume_z_mm"], target["volume_z_mm"]):
        raise ValueError(f"init_weights {folder}: its output planes are not this config's")
    state = {k: (target[k] if k in refocusing else source[k].clone()) for k in target}
    if "resample.weight" in state:
        z_out = target["volume_z_mm"].numpy()
        old, new = (
            RefocusPlanes(s["refocus_z_mm"].numpy(), s["refocus_disparity_px"].numpy(), s["refocus.shifts"].numpy())
            for s in (source, target)
        )
        moved = new.resampling(z_out) - old.resampling(z_out)
        state["resample.weight"] = state["resample.weight"] + torch.from_numpy(moved)[:, :, None, None]
    net.load_state_dict(state)


def make_optimiser(net: torch.nn.Module, config: NetConfig) -> torch.optim.Optimizer:
    return torch.optim.Adam(net.parameters(), lr=config.lr)


def make_scheduler(optimiser: torch.optim.Optimizer, config: NetConfig):
    # Keras counts a reduction after `patience` stalled epochs, torch after `patience + 1`
    return torch.optim.lr_scheduler.ReduceLROnPlateau(
        optimiser, mode="min", factor=config.lr_factor, patience=max(config.lr_patience - 1, 0)
    )


def _world() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _mean_over_ranks(value: torch.Tensor) -> float:
    value = value.detach().clone()
    rank, world = _world()
    if world > 1:
        dist.all_reduce(value)
        value /= world
    return float(value)


def _progress(enabled: bool):
    from rich.progress import TextColumn

    return progress_bar("{task.description}", TextColumn("{task.fields[info]}"), enabled=enabled)


# ----------------------------------------------------------------------------- epoch
def train_one_epoch(
    net: torch.nn.Module,
    optimiser: torch.optim.Optimizer,
    batches: Iterable[dict[str, torch.Tensor]],
    config: NetConfig,
    border: int,
    *,
    device: torch.device | str = "cpu",
    on_step: Callable[[int, dict[str, float]], bool] | None = None,
    total: int | None = None,
    description: str = "train",
    progress: bool = False,
) -> list[dict[str, float]]:
    """One pass over ``batches``; returns the per-step losses (means over all ranks).

    on_step(i, losses) is called after step i (0-based in this pass); it may return True to stop
    the pass there (a checkpoint-and-stop, or a time limit)."""
    net.train()
    out: list[dict[str, float]] = []
    with _progress(progress) as bar:
        task = bar.add_task(description, total=total, info="")
        for i, batch in enumerate(batches):
            views, demixed, volume = (batch[k].to(device, non_blocking=True) for k in ("views", "demixed", "volume"))
            optimiser.zero_grad(set_to_none=True)
            demix_logits, volume_logits = net(views)
            loss, parts = cm2net_loss(demix_logits, volume_logits, demixed, volume, config, border)
            loss.backward()
            optimiser.step()
            record = {
                "loss": _mean_over_ranks(loss),
                "demix": _mean_over_ranks(parts["demix"]),
                "volume": _mean_over_ranks(parts["volume"]),
            }
            if not math.isfinite(record["loss"]):
                raise FloatingPointError(f"the training loss became {record['loss']} at step {i} of this pass")
            out.append(record)
            bar.update(task, advance=1, info=f"loss {record['loss']:.4f}")
            if on_step is not None and on_step(i, record):
                break
    return out


@torch.no_grad()
def evaluate(
    net: torch.nn.Module,
    config: NetConfig,
    border: int,
    *,
    device: torch.device | str = "cpu",
    items=None,
    source: PatchSource | None = None,
    threshold: float | None = None,
    thresholds: Iterable[float] = (),
) -> dict[str, Any]:
    """Validation loss and detection scores over the validation patches (or ``items``).

    Each patch's prediction, less the loss border, is binarised at ``threshold`` (default
    ``config.detect_threshold``), its components matched to the true emitters whose centres lie
    in it (:func:`cm2optics.metrics.evaluate_volume`), and the counts pooled. ``thresholds``: also
    the pooled F1 at each of them, the best as ``f1_best`` at ``threshold_best``."""
    from cm2optics.metrics import evaluate_volume, pooled_scores

    module = getattr(net, "module", net)
    module.eval()
    items = validation_items(config) if items is None else list(items)
    if not items:
        return {}
    source = source or PatchSource(config)
    threshold = config.detect_threshold if threshold is None else threshold
    grid = config.synth.grid
    p = config.synth.patch_px
    inner = VolumeGrid((grid.shape[0], p - 2 * border, p - 2 * border), pixel_voxel_um(config, source.scale))
    totals = {"loss": 0.0, "demix": 0.0, "volume": 0.0}
    evaluations = []
    thresholds = [float(t) for t in thresholds]
    kept: list[tuple[np.ndarray, Any]] = []  # (prediction, truth) per patch, for ``thresholds``
    for start in range(0, len(items), max(config.batch_size, 1)):
        chunk = items[start : start + max(config.batch_size, 1)]
        arrays = [source.patch(it) for it in chunk]
        views, demixed, volume = (
            torch.from_numpy(np.stack([a[k] for a in arrays])).to(device) for k in ("views", "demixed", "volume")
        )
        demix_logits, volume_logits = module(views)
        loss, parts = cm2net_loss(demix_logits, volume_logits, demixed, volume, config, border)
        totals["loss"] += float(loss) * len(chunk)
        totals["demix"] += float(parts["demix"]) * len(chunk)
        totals["volume"] += float(parts["volume"]) * len(chunk)
        prob = torch.sigmoid(volume_logits).cpu().numpy()
        for it, pred in zip(chunk, prob, strict=True):
            crop = pred[:, border : p - border, border : p - border] if border else pred
            truth = source.truth(it, border)
            evaluations.append(evaluate_volume(crop, inner, truth, threshold))
            if thresholds:
                kept.append((crop, truth))
    n = len(items)
    metrics = {f"val_{k}": v / n for k, v in totals.items()}
    scores = pooled_scores(evaluations)
    for key in ("recall", "precision", "f1", "jaccard", "rmse_lateral_um", "rmse_axial_um", "n_tp", "n_fp", "n_fn"):
        if key in scores:
            metrics[key] = scores[key]
    metrics["threshold"] = threshold
    if thresholds:
        f1 = [
            pooled_scores([evaluate_volume(c, inner, t, value) for c, t in kept]).get("f1", 0.0) for value in thresholds
        ]
        best = int(np.argmax(f1))
        metrics["f1_best"], metrics["threshold_best"] = float(f1[best]), thresholds[best]
    return metrics


# ----------------------------------------------------------------------------- files
def running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last ``window`` values at each position (fewer at the start), same length."""
    values = np.asarray(values, float)
    if len(values) == 0:
        return values
    cumulative = np.concatenate([[0.0], np.cumsum(values)])
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - window, 0)
    return (cumulative[ends] - cumulative[starts]) / (ends - starts)


def plot_history(history: dict[str, Any], path: str | Path) -> Path:
    """The loss curve (per step) and validation loss (per epoch) as a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax, ax_f1 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.6, 1]})
    steps = history.get("steps", [])
    if steps:
        x = np.arange(1, len(steps) + 1)
        for (key, style), colour in zip(
            (("loss", "-"), ("demix", ":"), ("volume", "--")), ("C0", "C1", "C2"), strict=True
        ):
            values = np.array([s[key] for s in steps], float)
            ax.plot(x, values, style, lw=0.5, color=colour, alpha=0.2)
            ax.plot(x, running_mean(values, 100), style, lw=1.5, color=colour, label=f"train {key} (mean of 100 steps)")
    epochs = [e for e in history.get("epochs", []) if "val_loss" in e]
    if epochs:
        ax.plot([e["step"] for e in epochs], [e["val_loss"] for e in epochs], "o-", color="C3", label="validation loss")
        for key, marker in (("f1", "o-"), ("precision", "^--"), ("recall", "v--")):
            ax_f1.plot([e["step"] for e in epochs], [e.get(key, np.nan) for e in epochs], marker, ms=3, label=key)
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    if steps or epochs:
        ax.legend(fontsize=7)
    ax.set_title("CM²Net training")
    ax_f1.set_xlabel("step")
    ax_f1.set_ylim(0, 1)
    ax_f1.grid(alpha=0.3)
    ax_f1.set_title("validation detection (threshold of the config)", fontsize=9)
    if epochs:
        ax_f1.legend(fontsize=7)
    fig.tight_layout()
    return write_atomic(Path(path), lambda tmp: fig.savefig(tmp, format="png"))


def _write_history(out: Path, history: dict[str, Any]) -> None:
    text = json.dumps(history, indent=1)
    write_atomic(out / HISTORY, lambda tmp: tmp.write_text(text, encoding="utf-8"))


#: Volumes whose views make the reference histogram (seeded apart from training and validation).
REFERENCE_VOLUMES = 4
REFERENCE_SEED_OFFSET = 104729


def _histogram(source: PatchSource, config: NetConfig, count: int = REFERENCE_VOLUMES) -> np.ndarray:
    """Quantiles (0…1 in 256 steps) of the views of ``count`` volumes made like the training ones
    (the final density range, seed ``config.seed + REFERENCE_SEED_OFFSET``): the reference for
    histogram matching. A run computes it once, at its start, and carries it in its checkpoints
    (key ``histogram``), so that the final weights and ``export_weights`` need not render again."""
    values = [
        source.volume(config.seed + REFERENCE_SEED_OFFSET, i, tuple(config.synth.density_per_mm2))["views"].ravel()
        for i in range(count)
    ]
    return np.quantile(np.concatenate(values), np.linspace(0.0, 1.0, 256))


def _inherited_histogram(config: NetConfig) -> np.ndarray | None:
    """The reference histogram of ``init_weights`` when they were trained on this run's views (the
    same forward model, recipe and registration: the same distribution of views), else None — a
    fine-tuning run that goes on through the same data need not render the reference volumes again."""
    if not config.init_weights:
        return None
    from cm2optics.recon.net.weights import load_weights

    loaded = load_weights(config.init_weights)
    own = loaded.config
    same = (own.forward_model, own.synth, own.register_views) == (
        config.forward_model,
        config.synth,
        config.register_views,
    )
    return loaded.histogram if same and loaded.histogram is not None else None


# ----------------------------------------------------------------------------- run
def _setup_distributed(device: str | None) -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        backend = (
            "nccl" if (device or "").startswith("cuda") or (device is None and torch.cuda.is_available()) else "gloo"
        )
        dist.init_process_group(backend)
    rank, world = _world()
    if device is None:
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    return rank, world, dev


def train(
    config: NetConfig | str | Path,
    resume: bool = False,
    *,
    max_steps: int | None = None,
    device: str | None = None,
) -> dict[str, Any]:
    """Train (or resume) a run; returns its summary (out_dir, steps, last losses and metrics).

    config: a :class:`NetConfig` or a YAML path. resume: continue from ``out_dir/checkpoint.pt``.
    max_steps: stop (with a checkpoint) once this many steps are done in all — a planned
    interruption; the run resumes from there. device: ``cpu``, ``cuda:N`` (default: the rank's
    GPU when there is one)."""
    if not isinstance(config, NetConfig):
        config = load_config(config)
    if config.threads:
        torch.set_num_threads(config.threads)
    rank, world, dev = _setup_distributed(device)
    out = Path(config.out_dir)
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    net, border = make_net(config)
    if config.init_weights and not resume:
        start_from_weights(net, config.init_weights)
    net.to(dev)
    optimiser = make_optimiser(net, config)
    scheduler = make_scheduler(optimiser, config)
    history: dict[str, Any] = {"config_hash": config.hash(), "steps": [], "epochs": [], "seconds_per_step": []}
    pos = _Position()
    carried: dict[str, Any] = {}
    if resume:
        pos.epoch, pos.step_in_epoch, pos.global_step, history, carried = _restore(
            out / CHECKPOINT, config, net, optimiser, scheduler
        )
    model: torch.nn.Module = net
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(net, device_ids=[dev.index] if dev.type == "cuda" else None)
    n_steps = _steps_per_epoch_or_raise(config)
    source = PatchSource(config, cache=max(2, config.val_volumes)) if rank == 0 or config.val_volumes else None
    if rank == 0 and not resume:  # a fresh run: no kept weights of an earlier one
        for name in (BEST, AVERAGE):
            (out / name).unlink(missing_ok=True)
    facts = {
        "histogram": carried.get("histogram"),
        "hardware": _hardware(dev, world),
    }
    if rank == 0 and facts["histogram"] is None:
        inherited = _inherited_histogram(config)
        histogram = inherited if inherited is not None else _histogram(source, config)
        facts["histogram"] = [float(v) for v in histogram]
    checkpoint = _checkpointer(out / CHECKPOINT, net, optimiser, scheduler, config, history, pos, rank, world, facts)
    validate = _validator(net, config, border, dev, source, history, out, rank)

    while pos.epoch < config.epochs and not pos.stopped:
        loader = _epoch_loader(config, pos, rank, world)
        train_one_epoch(
            model,
            optimiser,
            loader,
            config,
            border,
            device=dev,
            on_step=_step_hook(pos, history, config, n_steps, max_steps, checkpoint, validate),
            total=n_steps - pos.step_in_epoch,
            description=f"epoch {pos.epoch + 1}/{config.epochs}",
            progress=config.progress and rank == 0,
        )
        if pos.stopped:
            break
        metrics = validate(pos.global_step)
        record = _epoch_record(pos.epoch, pos.global_step, optimiser, history["steps"][-n_steps:], metrics)
        scheduler.step(metrics.get("val_loss", record["train_loss"]))
        history["epochs"].append(record)
        pos.epoch, pos.step_in_epoch = pos.epoch + 1, 0
        checkpoint(pos.epoch, 0)
        if rank == 0:
            _report_epoch(out, history, record, config.progress)
        if pos.stop_at_epoch_end and pos.epoch < config.epochs:
            pos.stopped = True
    summary = _summary(out, config, history, pos, world=world)
    if rank == 0 and not pos.stopped and pos.epoch >= config.epochs:
        summary["weights"] = str(_save_final_weights(net, config, out, history, pos, facts))
    if world > 1:
        dist.barrier()
    return summary


def _checkpointer(
    path: Path,
    net: torch.nn.Module,
    optimiser: torch.optim.Optimizer,
    scheduler: Any,
    config: NetConfig,
    history: dict[str, Any],
    pos: _Position,
    rank: int,
    world: int,
    facts: dict[str, Any],
) -> Callable[[int, int], None]:
    """``checkpoint(epoch, step_in_epoch)``: rank 0 saves the whole state to ``path`` with the
    run's ``facts`` (reference histogram, hardware); every rank waits for it when there are several."""

    def checkpoint(e: int, s: int) -> None:
        if rank == 0:
            save_checkpoint(
                path,
                model=net.state_dict(),
                optimiser=optimiser.state_dict(),
                scheduler=scheduler.state_dict(),
                epoch=e,
                step_in_epoch=s,
                global_step=pos.global_step,
                history=history,
                config_hash=config.hash(),
                config=config.to_dict(),
                **facts,
            )
        if world > 1:
            dist.barrier()

    return checkpoint


def _extended_validation(config: NetConfig) -> bool:
    """Whether the run scores beyond the epoch ends' plain validation: ``val_every``, a mixed
    source's validation volumes or weights kept by validation."""
    return bool(config.val_every or config.val_mix_volumes or config.keep_weights != "last")


def _validator(
    net: torch.nn.Module,
    config: NetConfig,
    border: int,
    device: torch.device,
    source: PatchSource | None,
    history: dict[str, Any],
    out: Path,
    rank: int,
) -> Callable[[int], dict[str, Any]]:
    """``validate(step)``: the validation metrics of the net as it stands (``{}`` without
    validation volumes), the net left in training mode.

    With :func:`_extended_validation` each scoring also takes the F1 at the best of
    :data:`VALIDATION_THRESHOLDS` (``f1_best``), scores the mixed source's ``val_mix_volumes``
    (keys ``mix_…``), appends its record (``step``, the metrics, ``score``: the mean ``f1_best``
    over the sources) to ``history["validations"]`` and, on rank 0, keeps the weights the config
    asks for (:data:`BEST`, :data:`AVERAGE`)."""
    extended = _extended_validation(config)
    sources: list[tuple[str, PatchSource | None, list | None]] = []
    if config.val_volumes:
        sources.append(("", source, None))
    if extended and config.val_mix_volumes:
        mix = config.mix_config()
        sources.append(("mix_", PatchSource(mix, cache=config.val_mix_volumes), validation_items(config, 1)))

    def validate(step: int) -> dict[str, Any]:
        if not sources:
            return {}
        metrics: dict[str, Any] = {}
        for prefix, src, items in sources:
            scored = evaluate(
                net,
                config,
                border,
                device=device,
                items=items,
                source=src,
                thresholds=VALIDATION_THRESHOLDS if extended else (),
            )
            metrics |= {f"{prefix}{k}": v for k, v in scored.items()}
        net.train()
        if not extended:
            return metrics
        prefixes = [prefix for prefix, _, _ in sources]
        metrics["score"] = float(np.mean([metrics[f"{prefix}f1_best"] for prefix in prefixes]))
        record = {"step": step, **metrics}
        validations = history.setdefault("validations", [])
        validations[:] = [v for v in validations if v["step"] < step] + [record]
        if rank == 0:
            _keep_weights(net, config, out, history, record)
        return metrics

    return validate


def _keep_weights(
    net: torch.nn.Module, config: NetConfig, out: Path, history: dict[str, Any], record: dict[str, Any]
) -> None:
    """After a validation scoring: ``best`` — the net's state to :data:`BEST` if its score beats
    every earlier scoring's (``history["best"]``); ``average`` — appended to the last
    ``keep_average`` states in :data:`AVERAGE` (states of later steps, from before a resume, dropped)."""
    state = {k: v.detach().clone() for k, v in net.state_dict().items()}
    if config.keep_weights == "best":
        best = history.get("best")
        if best is None or record["score"] > best["score"] or best["step"] >= record["step"]:
            history["best"] = {"step": record["step"], "score": record["score"]}
            payload = {"model": state, "record": record, "config_hash": config.hash()}
            write_atomic(out / BEST, lambda tmp: torch.save(payload, tmp))
    elif config.keep_weights == "average":
        path = out / AVERAGE
        kept = torch.load(path, map_location="cpu", weights_only=False)["states"] if path.is_file() else []
        kept = [k for k in kept if k["step"] < record["step"]] + [
            {"step": record["step"], "model": state, "record": record}
        ]
        payload = {"states": kept[-config.keep_average :], "config_hash": config.hash()}
        write_atomic(path, lambda tmp: torch.save(payload, tmp))


def kept_weights(run_dir: str | Path, config: NetConfig, keep: str | None = None) -> tuple[dict, dict] | None:
    """(state dict, facts) of the weights a run keeps (``keep``, default the config's
    ``keep_weights``): the best validation scoring's, or the mean of the last ones' (floating
    tensors averaged, counters the last's); None for ``last`` (the latest checkpoint's)."""
    keep = keep or config.keep_weights
    if keep == "last":
        return None
    path = Path(run_dir) / (BEST if keep == "best" else AVERAGE)
    if not path.is_file():
        raise CheckpointError(
            f"{path}: no {keep} weights kept yet (keep_weights: {keep}; the run keeps them at its validation scorings)"
        )
    state = torch.load(path, map_location="cpu", weights_only=False)
    if state.get("config_hash") != config.hash():
        raise CheckpointError(f"{path}: kept by a run of another config ({str(state.get('config_hash'))[:12]}…)")
    if keep == "best":
        record = state["record"]
        return state["model"], {
            "weights kept": f"best validation score {record['score']:.4f} at step {record['step']}",
            "record": record,
        }
    states = state["states"]
    average = {}
    for key, last in states[-1]["model"].items():
        if torch.is_floating_point(last):
            average[key] = torch.stack([k["model"][key] for k in states]).mean(0)
        else:
            average[key] = last.clone()
    steps = [k["step"] for k in states]
    record = dict(states[-1]["record"])
    return average, {
        "weights kept": f"mean of the weights at the {len(steps)} validation scorings at steps {steps}",
        "record": record,
    }


@dataclass
class _Position:
    """Where a training run stands: the epoch (0-based), the step within it, the optimiser steps
    in all, and whether it stopped (or stops once the epoch is done) for ``max_steps``."""

    epoch: int = 0
    step_in_epoch: int = 0
    global_step: int = 0
    stopped: bool = False
    stop_at_epoch_end: bool = False


def _epoch_loader(config: NetConfig, pos: _Position, rank: int, world: int) -> DataLoader:
    """This rank's batches of the current epoch, from the step the run stands at."""
    items = rank_items(config, epoch_items(config, pos.epoch), rank, world, pos.step_in_epoch)
    return DataLoader(
        PatchDataset(config, items),
        batch_size=config.batch_size // world,
        shuffle=False,
        num_workers=config.workers,
        persistent_workers=False,
    )


def _step_hook(
    pos: _Position,
    history: dict[str, Any],
    config: NetConfig,
    n_steps: int,
    max_steps: int | None,
    checkpoint: Callable[[int, int], None],
    validate: Callable[[int], dict[str, Any]] | None = None,
) -> Callable[[int, dict[str, float]], bool]:
    """The ``on_step`` callback of one epoch: records each step's loss and time (s), scores the
    validation volumes every ``val_every`` steps (``validate``; the epoch's end scores them
    anyway), checkpoints every ``checkpoint_every`` steps and stops at ``max_steps``; returns True
    to stop the epoch."""
    e, first, last = pos.epoch, pos.step_in_epoch, [time.perf_counter()]

    def on_step(i: int, record: dict[str, float]) -> bool:
        pos.global_step += 1
        now = time.perf_counter()
        history["steps"].append(record)
        history["seconds_per_step"].append(now - last[0])
        last[0] = now
        s = first + i + 1
        if validate is not None and config.val_every and pos.global_step % config.val_every == 0 and s < n_steps:
            validate(pos.global_step)
            last[0] = time.perf_counter()  # the scoring's time is not a step's
        if config.checkpoint_every and pos.global_step % config.checkpoint_every == 0 and s < n_steps:
            checkpoint(e, s)
        if max_steps is not None and pos.global_step >= max_steps:
            if s == n_steps:  # the epoch's last step: finish the epoch (validation, checkpoint), then stop
                pos.stop_at_epoch_end = True
                return False
            checkpoint(e, s)
            pos.stopped = True
            return True
        return False

    return on_step


def _restore(
    path: Path, config: NetConfig, net: torch.nn.Module, optimiser: torch.optim.Optimizer, scheduler: Any
) -> tuple[int, int, int, dict[str, Any], dict[str, Any]]:
    """Load a checkpoint into the net, optimiser, scheduler and the RNGs; returns the epoch, the
    step within it, the global step, the history to continue from and what else it carried
    (``histogram``; absent from checkpoints of older versions)."""
    state = load_checkpoint(path, config.hash())
    net.load_state_dict(state["model"])
    optimiser.load_state_dict(state["optimiser"])
    scheduler.load_state_dict(state["scheduler"])
    set_rng_state(state["rng"])
    carried = {"histogram": state.get("histogram")}
    return state["epoch"], state["step_in_epoch"], state["global_step"], state["history"], carried


def _steps_per_epoch_or_raise(config: NetConfig) -> int:
    """The optimiser steps per epoch; a ValueError when the training patches make no batch."""
    n_steps = steps_per_epoch(config)
    if n_steps == 0:
        raise ValueError(
            f"train_volumes × patches_per_volume = {config.train_volumes * config.synth.patches_per_volume} patches "
            f"make no batch of {config.batch_size}"
        )
    return n_steps


def _epoch_record(
    epoch: int, global_step: int, optimiser: torch.optim.Optimizer, train_losses: list[dict], metrics: dict
) -> dict[str, Any]:
    """The history record of a finished epoch (0-based ``epoch``): its mean training loss, the
    learning rate and the validation metrics."""
    return {
        "epoch": epoch + 1,
        "step": global_step,
        "lr": optimiser.param_groups[0]["lr"],
        "train_loss": float(np.mean([s["loss"] for s in train_losses])),
        **metrics,
    }


def _report_epoch(out: Path, history: dict[str, Any], record: dict[str, Any], progress: bool) -> None:
    """Write the history and its curve; print the epoch's record when ``progress``."""
    _write_history(out, history)
    plot_history(history, out / CURVE)
    if progress:
        shown = {k: round(v, 4) if isinstance(v, float) else v for k, v in record.items()}
        print(f"epoch {record['epoch']}: {shown}", flush=True)


def _summary(out: Path, config: NetConfig, history: dict[str, Any], pos: _Position, *, world: int) -> dict[str, Any]:
    """The run's summary: where it is, how far it got, its last loss and metrics."""
    return {
        "out_dir": str(out),
        "epochs_done": pos.epoch,
        "global_step": pos.global_step,
        "stopped": pos.stopped,
        "world_size": world,
        "config_hash": config.hash(),
        "last_loss": history["steps"][-1]["loss"] if history["steps"] else None,
        "seconds_per_step": float(np.median(history["seconds_per_step"])) if history["seconds_per_step"] else None,
        "metrics": history["epochs"][-1] if history["epochs"] else {},
    }


def _hardware(device: torch.device, world: int) -> dict[str, Any]:
    """Where the run trains: device type, torch threads per process and processes."""
    return {"device": device.type, "threads": torch.get_num_threads(), "processes": world}


def _hardware_line(hardware: dict[str, Any] | None, config: NetConfig) -> str:
    """The model card's hardware line, from the run's own facts (its checkpoint's), or — for a
    checkpoint that predates them — from the config's ``threads``."""
    if hardware:
        threads = hardware["threads"]
        return (
            f"{str(hardware['device']).upper()}, {threads} torch thread{'s' if threads != 1 else ''} per process, "
            f"{hardware['processes']} process{'es' if hardware['processes'] != 1 else ''}"
        )
    if config.threads:
        return f"{config.threads} torch thread{'s' if config.threads != 1 else ''} per process (the config's threads)"
    return "torch's default threads (the config's threads = 0); device not recorded"


def _training_facts(
    epoch: int, global_step: int, history: dict[str, Any], config: NetConfig, hardware: dict[str, Any] | None
) -> dict[str, Any]:
    """The model card's training facts of a run at ``epoch`` (epochs done) and ``global_step``."""
    seconds = history.get("seconds_per_step") or []
    return {
        "epochs completed": epoch,
        "optimiser steps": global_step,
        "patches seen": global_step * config.batch_size,
        "median seconds per step": round(float(np.median(seconds)), 3) if seconds else None,
        "training wall time (h, steps only)": round(float(np.sum(seconds)) / 3600.0, 2),
        "hardware": _hardware_line(hardware, config),
    }


def _last_metrics(history: dict[str, Any]) -> dict[str, Any]:
    last = history["epochs"][-1] if history.get("epochs") else {}
    return {k: v for k, v in last.items() if isinstance(v, int | float)}


def _save_final_weights(
    net: torch.nn.Module, config: NetConfig, out: Path, history: dict[str, Any], pos: _Position, facts: dict[str, Any]
) -> Path:
    """Save the trained weights to ``out/weights`` with the training facts and the metrics."""
    from cm2optics.recon.net.weights import save_weights

    training = _training_facts(pos.epoch, pos.global_step, history, config, facts["hardware"])
    metrics = _last_metrics(history)
    kept = kept_weights(out, config)
    if kept is not None:
        import copy

        state, facts_kept = kept
        net = copy.deepcopy(net)
        net.load_state_dict(state)
        training["weights kept"] = facts_kept["weights kept"]
        metrics = {k: v for k, v in facts_kept["record"].items() if isinstance(v, int | float)}
    return save_weights(net, config, out / "weights", metrics=metrics, training=training, histogram=facts["histogram"])


def export_weights(run_dir: str | Path, folder: str | Path, keep: str | None = None) -> Path:
    """The weights of the latest checkpoint in ``run_dir`` (a run that is still training, or
    stopped) as a weights folder: safetensors, config, model card with the training facts and the
    last validation metrics, SHA256SUMS, and the reference histogram of the training views. With
    ``keep`` (default: the config's ``keep_weights``) ``best`` or ``average``, the weights the run
    keeps instead (:func:`kept_weights`), with the metrics of their validation scoring.

    The network is rebuilt from the checkpoint's tensors (no forward model); the histogram is the
    one the checkpoint carries — only a checkpoint of an older version makes it again
    (:data:`REFERENCE_VOLUMES` volumes, minutes at full resolution). The folder is written under a
    temporary name and swapped in whole (files of others in it are kept)."""
    import shutil
    import tempfile

    from cm2optics.formats.outputs import swap_in_folder
    from cm2optics.recon.net.weights import WeightsError, net_from_tensors, save_weights

    path = Path(run_dir) / CHECKPOINT
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to export (has the run `{run_dir}` written one yet?)")
    try:
        config = NetConfig.from_dict(torch.load(path, map_location="cpu", weights_only=False)["config"])
    except Exception as error:  # noqa: BLE001 - any unreadable file is the same user error
        raise CheckpointError(f"{path}: not a readable CM²Net checkpoint ({error})") from None
    state = load_checkpoint(path, config.hash())
    tensors = {k.removeprefix("module."): v for k, v in state["model"].items()}
    metrics = _last_metrics(state["history"])
    kept = kept_weights(run_dir, config, keep)
    if kept is not None:
        tensors = {k.removeprefix("module."): v for k, v in kept[0].items()}
        metrics = {k: v for k, v in kept[1]["record"].items() if isinstance(v, int | float)}
    try:
        net = net_from_tensors(config, tensors, str(path), "its config")
    except WeightsError as error:
        raise CheckpointError(str(error)) from None
    histogram = state.get("histogram")
    if histogram is None:
        histogram = _histogram(PatchSource(config), config)
    training = _training_facts(state["epoch"], state["global_step"], state["history"], config, state.get("hardware"))
    if kept is not None:
        training["weights kept"] = kept[1]["weights kept"]
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    try:
        save_weights(net, config, staging, metrics=metrics, training=training, histogram=histogram)
        return swap_in_folder(staging, folder, "train")
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    import argparse

    from cm2optics.recon.net.config import ConfigError

    parser = argparse.ArgumentParser(
        prog="python -m cm2optics.recon.net.train", description="Train CM²Net from a YAML config."
    )
    parser.add_argument("config", help="YAML config (reconstruction/configs/cm2net-cpu.yaml, …)")
    parser.add_argument("--resume", action="store_true", help="continue from out_dir/checkpoint.pt")
    parser.add_argument(
        "--max-steps", type=int, default=None, help="stop (with a checkpoint) after this many steps in all"
    )
    parser.add_argument("--device", default=None, help="cpu or cuda:N (default: the rank's GPU, else cpu)")
    args = parser.parse_args(argv)
    try:
        summary = train(args.config, resume=args.resume, max_steps=args.max_steps, device=args.device)
    except (ConfigError, CheckpointError, FileNotFoundError, ValueError) as error:
        print(f"error: {error}", flush=True)
        return 2
    finally:
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()
    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps({k: v for k, v in summary.items() if k != "metrics"}, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""Trained CM²Net weights on disk: a folder that says what it is and proves it is intact.

::

    weights/
      model.safetensors   the state dict (refocusing planes and shifts included as buffers);
                          metadata: format, config hash, reference histogram for inference,
                          lateral correction of the output planes (once fitted), operating
                          threshold chosen on validation volumes (once chosen)
      config.yaml         the NetConfig that built it
      MODEL_CARD.md       data, training, metrics, geometry, intended use, limitations
      SHA256SUMS          SHA-256 of the two files above and of any shipped forward model
                          (``sha256sum -c`` reads it)
      *.lsv.h5            optional: the 3D-LSV model the weights were trained through, when
                          ``config.yaml``'s ``forward_model`` names it by a path relative to the
                          folder (so the weights work from any directory)

:func:`load_weights` checks the SHA-256 sums, rebuilds the network from ``config.yaml`` and the
stored planes and refuses weights whose tensors do not match it; every failure is a
:class:`WeightsError` (a :class:`ValueError`) naming the file.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.errors import UserError
from cm2optics.formats.atomic import write_atomic
from cm2optics.recon.net.config import ConfigError, NetConfig, load_config
from cm2optics.recon.net.lateral import METADATA_KEY as LATERAL_KEY
from cm2optics.recon.net.lateral import LateralCorrection
from cm2optics.recon.net.model import CM2Net
from cm2optics.recon.net.operating import METADATA_KEY as OPERATING_KEY
from cm2optics.recon.net.operating import OperatingThreshold
from cm2optics.recon.net.refocus import RefocusPlanes

__all__ = [
    "CARD_FILE",
    "CONFIG_FILE",
    "FORMAT",
    "GeometryMismatchError",
    "LoadedNet",
    "NetError",
    "NetInputError",
    "SUMS_FILE",
    "WEIGHTS_FILE",
    "WeightsError",
    "load_weights",
    "net_from_tensors",
    "shipped_weights",
    "save_weights",
    "store_metadata",
]

FORMAT = "cm2optics-cm2net"
#: The weights shipped with the project: ``reconstruction/<name>`` at the top of the repository.
SHIPPED = "cm2net-cpu"
WEIGHTS_FILE, CONFIG_FILE, CARD_FILE, SUMS_FILE = "model.safetensors", "config.yaml", "MODEL_CARD.md", "SHA256SUMS"
MODEL_GLOB = "*.lsv.h5"  # forward models shipped inside a weights folder


class NetError(UserError):
    """A CM²Net input a user can get wrong."""


class WeightsError(NetError):
    """A weights folder that cannot be used: missing file, failed hash, tensors unlike the config."""


class NetInputError(NetError):
    """A measurement the network cannot take (shape, dtype, non-finite values)."""


class GeometryMismatchError(NetError):
    """A forward model whose geometry (lenslets, refocusing shifts, pixel/voxel scale) is not the
    one the weights were trained with."""


@dataclass(frozen=True)
class LoadedNet:
    net: CM2Net
    config: NetConfig
    folder: Path
    histogram: np.ndarray | None  # reference quantiles of training views (for histogram matching)
    metadata: dict[str, str]
    lateral: LateralCorrection | None = None  # the output planes' lateral correction, if fitted
    operating: OperatingThreshold | None = None  # the detection threshold chosen on validation, if chosen

    @property
    def threshold(self) -> float:
        """The default detection threshold: the operating one if chosen, else the config's."""
        return self.operating.threshold if self.operating is not None else self.config.detect_threshold

    @property
    def planes(self) -> RefocusPlanes:
        return self.net.planes


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _card(net: CM2Net, config: NetConfig, metrics: dict[str, Any] | None, training: dict[str, Any] | None) -> str:
    import cm2optics

    planes = net.planes
    s = config.synth
    lines = [
        "# CM²Net model card",
        "",
        f"Made {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')} with cm2optics {getattr(cm2optics, '__version__', '?')}; "
        f"config hash `{config.hash()}`.",
        "",
        "## Model",
        "",
        f"- CM²Net (Xue et al., Optica 2022): view demixing → shift-and-add refocusing ({planes.n_planes} planes) → "
        f"view synthesis + refocus enhancement → fusion; {config.channels} channels, {config.blocks} residual blocks "
        f"per sub-network, {config.fusion_blocks} after fusion, norm = {config.norm}; {net.parameter_count():,} parameters.",
        f"- Input: {net.n_views} views cropped at the chief rays (any size; trained on {s.patch_px}-px patches of "
        f"{s.view_px}-px views), normalised like the synthetic measurements (peak of the clean image = 1).",
        f"- Output: {config.n_planes} planes at {s.voxel_um[0]:g} µm (z) × {s.voxel_um[1]:g} × {s.voxel_um[2]:g} µm "
        "voxels, σ(logit) ∈ [0, 1] per voxel, in the views' orientation (the inference flips it to the volume's).",
        f"- Refocusing disparities {planes.disparity_px.min():g}…{planes.disparity_px.max():g} px, "
        f"depths {planes.z_mm.min() * 1000:.1f}…{planes.z_mm.max() * 1000:.1f} µm, largest shift {planes.max_shift_px} px.",
        "",
        "## Training data",
        "",
        f"- Forward model: `{config.forward_model}`; synthetic volumes made on the fly (cm2optics.synth), seed {config.seed}.",
        f"- Field {s.fov_mm[0]:g}–{s.fov_mm[1]:g} mm, depth {s.depth_um:g} µm, emitters {s.diameter_um[0]:g}–{s.diameter_um[1]:g} µm, "
        f"density {s.density_per_mm2[0]:g}–{s.density_per_mm2[1]:g} per mm², noise {s.noise}"
        + (f" ({s.peak_photons:g} peak photons)" if s.noise == "poisson-gaussian" else "")
        + ".",
        f"- {config.train_volumes} volumes × {s.patches_per_volume} patches per epoch"
        + (", new volumes each epoch" if config.fresh_volumes else "")
        + (
            f"; density curriculum over {config.curriculum_epochs} epochs from {config.curriculum_start_density}"
            if config.curriculum_epochs
            else ""
        )
        + ".",
        f"- Loss: {config.alpha_demix:g}·BCE(demixed) + {config.alpha_volume:g}·{config.volume_loss}(volume), "
        f"Adam {config.lr:g}, ×{config.lr_factor:g} after {config.lr_patience} stalled epochs, global batch {config.batch_size}.",
        "",
    ]
    if training:
        lines += ["## Training run", ""] + [f"- {k}: {v}" for k, v in training.items()] + [""]
    lines += ["## Validation metrics", ""]
    if metrics:
        lines += ["| metric | value |", "|---|---|"]
        lines += [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in metrics.items()]
    else:
        lines.append("None recorded.")
    lines += [
        "",
        "## Intended use and limitations",
        "",
        "- Sparse fluorescent emitters (cells, beads) imaged by the CM² whose forward model made the training data; "
        "another device or a re-fitted model must match its geometry (checked at load: lenslets, refocusing shifts, "
        "one view pixel per voxel).",
        "- Trained on simulated data only; measured frames should be histogram-matched to the training statistics.",
        "- Dense or continuous structures (vessels) come out fragmented: the BCE loss on sparse beads biases towards sparsity.",
        "",
        "## Files",
        "",
        f"`{WEIGHTS_FILE}` (safetensors), `{CONFIG_FILE}`, this card; SHA-256 in `{SUMS_FILE}`.",
        "",
    ]
    return "\n".join(lines)


def save_weights(
    net: CM2Net,
    config: NetConfig,
    folder: str | Path,
    *,
    metrics: dict[str, Any] | None = None,
    training: dict[str, Any] | None = None,
    histogram: np.ndarray | None = None,
) -> Path:
    """Write the weights folder (each file atomically, the sums last); returns the folder."""

    folder = Path(folder)
    net = getattr(net, "module", net)
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    metadata = {"format": FORMAT, "config_hash": config.hash()}
    if histogram is not None:
        metadata["histogram"] = json.dumps([float(v) for v in np.asarray(histogram, float)])
    _write_tensors(folder, state, metadata)
    config.save(folder / CONFIG_FILE)
    card = _card(net, config, metrics, training)
    write_atomic(folder / CARD_FILE, lambda tmp: tmp.write_text(card, encoding="utf-8"))
    _write_sums(folder)
    return folder


def _write_tensors(folder: Path, state: dict, metadata: dict[str, str]) -> None:
    from safetensors.torch import save_file

    write_atomic(folder / WEIGHTS_FILE, lambda tmp: save_file(state, str(tmp), metadata=metadata))


def _write_sums(folder: Path) -> None:
    names = (WEIGHTS_FILE, CONFIG_FILE, *sorted(p.name for p in folder.glob(MODEL_GLOB)))
    sums = "".join(f"{_sha256(folder / name)}  {name}\n" for name in names)
    write_atomic(folder / SUMS_FILE, lambda tmp: tmp.write_text(sums, encoding="utf-8"))


def store_metadata(folder: str | Path, entries: dict[str, str]) -> None:
    """Add ``entries`` to the metadata of the (checked) weights in ``folder``: the tensors, config
    and card stay, ``model.safetensors`` and the SHA-256 sums are rewritten."""
    loaded = load_weights(folder)
    folder = Path(folder)
    state = {k: v.detach().cpu().contiguous() for k, v in loaded.net.state_dict().items()}
    _write_tensors(folder, state, {**loaded.metadata, **entries})
    _write_sums(folder)


def _check_sums(folder: Path) -> None:
    sums = folder / SUMS_FILE
    if not sums.is_file():
        raise WeightsError(f"{sums}: missing (a weights folder lists the SHA-256 of its files)")
    listed = {}
    for line in sums.read_text(encoding="utf-8").splitlines():
        parts = line.split()
        if len(parts) == 2:
            listed[parts[1].lstrip("*")] = parts[0].lower()
    models = {p.name for p in folder.glob(MODEL_GLOB)} | {n for n in listed if n.endswith(MODEL_GLOB[1:])}
    for name in (WEIGHTS_FILE, CONFIG_FILE, *sorted(models)):
        path = folder / name
        if not path.is_file():
            raise WeightsError(f"{path}: missing")
        if name not in listed:
            raise WeightsError(f"{sums}: lists no SHA-256 for {name}")
        actual = _sha256(path)
        if actual != listed[name]:
            raise WeightsError(
                f"{path}: SHA-256 {actual[:16]}… does not match {SUMS_FILE} ({listed[name][:16]}…): corrupt or edited"
            )


def load_weights(folder: str | Path, device: str = "cpu") -> LoadedNet:
    """The network of a weights folder, checked (see the module docstring), in eval mode."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    folder = Path(folder)
    if not folder.is_dir():
        raise WeightsError(f"{folder}: no such weights folder")
    _check_sums(folder)
    try:
        config = load_config(folder / CONFIG_FILE)
    except ConfigError as error:
        raise WeightsError(str(error)) from None
    path = folder / WEIGHTS_FILE
    try:
        tensors = load_file(str(path), device="cpu")
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            metadata = dict(f.metadata() or {})
    except (SafetensorError, OSError, ValueError) as error:
        raise WeightsError(f"{path}: not a readable safetensors file ({error})") from None
    if metadata.get("format") != FORMAT:
        raise WeightsError(f"{path}: not CM²Net weights (format = {metadata.get('format')!r})")
    if metadata.get("config_hash") != config.hash():
        raise WeightsError(
            f"{path}: trained with config {metadata.get('config_hash', '?')[:12]}…, {CONFIG_FILE} is {config.hash()[:12]}…"
        )
    shipped_model = folder / config.forward_model
    if (
        not Path(config.forward_model).is_absolute()
        and config.forward_model.endswith(MODEL_GLOB[1:])
        and shipped_model.is_file()
    ):
        config = config.with_changes(forward_model=str(shipped_model.resolve()))
    net = net_from_tensors(config, tensors, f"{path}", f"{folder / CONFIG_FILE}")
    net.to(device).eval()
    histogram = np.asarray(json.loads(metadata["histogram"]), float) if "histogram" in metadata else None
    try:
        lateral = LateralCorrection.from_json(metadata[LATERAL_KEY]) if LATERAL_KEY in metadata else None
    except (ValueError, KeyError, TypeError) as error:
        raise WeightsError(f"{path}: unreadable {LATERAL_KEY} metadata ({error})") from None
    try:
        operating = OperatingThreshold.from_json(metadata[OPERATING_KEY]) if OPERATING_KEY in metadata else None
    except (ValueError, KeyError, TypeError) as error:
        raise WeightsError(f"{path}: unreadable {OPERATING_KEY} metadata ({error})") from None
    return LoadedNet(net, config, folder, histogram, metadata, lateral, operating)


def net_from_tensors(config: NetConfig, tensors: dict, where: str, config_name: str = CONFIG_FILE) -> CM2Net:
    """The CM²Net of ``config`` with the state ``tensors`` (a state dict: the refocusing planes and
    output depths are among its buffers, so no forward model is needed), in train mode; a
    :class:`WeightsError` naming ``where`` when the tensors do not describe that network."""
    try:
        planes = RefocusPlanes(
            tensors["refocus_z_mm"].numpy(), tensors["refocus_disparity_px"].numpy(), tensors["refocus.shifts"].numpy()
        )
        z_out = tensors["volume_z_mm"].numpy()
        net = CM2Net(config, planes, z_out)
    except (KeyError, ValueError) as error:
        raise WeightsError(f"{where}: does not describe a CM²Net of {config_name} ({error})") from None
    expected = net.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    wrong = sorted(k for k in set(expected) & set(tensors) if tuple(expected[k].shape) != tuple(tensors[k].shape))
    if missing or unexpected or wrong:
        detail = "; ".join(
            part
            for part in (
                f"missing {', '.join(missing[:4])}" if missing else "",
                f"unexpected {', '.join(unexpected[:4])}" if unexpected else "",
                ", ".join(
                    f"{k} is {tuple(tensors[k].shape)}, the config needs {tuple(expected[k].shape)}" for k in wrong[:3]
                ),
            )
            if part
        )
        raise WeightsError(f"{where}: tensors do not match {config_name}: {detail}")
    net.load_state_dict(tensors)
    return net


def shipped_weights(name: str = SHIPPED) -> Path:
    """Where the project's shipped weights ``name`` lie: ``reconstruction/<name>`` in the
    repository that holds this package (a clone, or an editable install of one), found from the
    package's own location, never from the current directory. The folder may be absent (an
    installed wheel carries no weights): check ``.is_dir()``."""
    import cm2optics

    return Path(cm2optics.__file__).resolve().parent.parent / "reconstruction" / name

"""Attribution: which physical effects explain the residual, with what values.

The comparison happens on compact features measured in fixed windows (:mod:`.features`): every
focus's energy, centroid and width, and each frame's background in 4 × 4 blocks outside the
foci. Each feature's noise follows from the sensor's noise model, so a misfit is a χ².

Starting from the nominal design, every candidate effect is fitted to the residual (linearised
by finite differences, nuisance registration parameters — offset, flux scale, dark — free
alongside); the one that lowers the Bayesian information criterion most is kept if it lowers it
by more than ``BIC_THRESHOLD`` and passes the guard (:func:`guard`: it removes at least
``MIN_EXCESS_SHARE`` of the χ² above the noise floor, and its fit matches the residual's pattern —
it does not buy large gains at a few foci with losses at the others, neither in χ² nor counted
focus by focus among those it acts on, and every observable it changes markedly (the foci's
energies, centroids, widths, the background, the pixels themselves) holds at least a quarter of that
change in its residual, as a physical effect predicts all of them; else the next finalist is
tried, and when none passes the rest of the residual is left unexplained); all kept parameters
are then refitted jointly by Gauss–Newton
with the simulator in the loop; and the search repeats until χ² reaches the noise floor or no
candidate is significant. Uncertainties are the square roots of the covariance's diagonal,
scaled by the reduced χ² where it exceeds 1. A calibration source larger than declared
(``source_size``) and the effects that widen the foci alike (:data:`WIDENING_RIVALS`) are told
apart by their fits; the declared size stands unless the larger source fits better by
``BIC_THRESHOLD`` (:func:`_declared_source_first`), and a close call is said in ``ambiguities``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cm2optics.calibrate.effects import Effect, Parameter, apply_image_effects, leakage_counts
from cm2optics.calibrate.features import away_from_foci, circular_windows, focus_windows, window_features
from cm2optics.calibrate.noise import SensorNoise, estimate_noise, quantisation_step
from cm2optics.calibrate.register import Registration, register
from cm2optics.calibrate.simulate import Simulator, Values

#: ΔBIC a candidate must gain to be kept ("very strong" evidence on Kass & Raftery's scale).
BIC_THRESHOLD = 10.0
#: Reduced χ² at which the loop stops: the model explains the data to the noise.
CHI2_FLOOR = 1.2
#: Background blocks per side outside the foci.
BLOCKS = 4
NUISANCE = ("offset_row_px", "offset_col_px", "flux_scale", "dark_level")
NUISANCE_STEPS = (0.05, 0.05, 1e-3, 0.5)

Progress = Callable[[str], None]

#: A sensor's smooth gain non-uniformity (an uncorrected flat field): a nuisance of the sensor,
#: not an effect of the optics, fitted where the data ask for it (a candidate like the effects,
#: under the same criterion and guard) so that a library effect beside it is judged against the
#: residual the gain leaves; never reported among the effects nor written into the design. The
#: gain 1 + a·u + b·v + c·u² + d·u·v + e·v² over the sensor, u and v the pixel's row and column
#: from the sensor's centre in half-heights and half-widths (the constant is the flux scale's).
_FLAT_FIELD_TERMS = ("gain_row", "gain_col", "gain_row2", "gain_row_col", "gain_col2")
FLAT_FIELD = Effect(
    "flat_field",
    tuple(Parameter(name, 0.0, -0.5, 0.5, 0.01) for name in _FLAT_FIELD_TERMS),
    "the sensor's gain varies smoothly over its area (an uncorrected flat field): a nuisance of the sensor",
)


def flat_field_gain(shape: tuple[int, int], values: dict[str, float]) -> np.ndarray:
    """(y, x) the relative gain of :data:`FLAT_FIELD` with ``values`` over a sensor of ``shape``."""
    u = ((np.arange(shape[0], dtype=np.float32) - (shape[0] - 1) / 2) / (shape[0] / 2))[:, None]
    v = ((np.arange(shape[1], dtype=np.float32) - (shape[1] - 1) / 2) / (shape[1] / 2))[None, :]
    terms = (u, v, u * u, u * v, v * v)
    return 1 + sum(np.float32(values.get(name, 0.0)) * t for name, t in zip(_FLAT_FIELD_TERMS, terms, strict=True))


@dataclass
class FeatureSpace:
    """Fixed windows, the data's features and their noise."""

    centres: np.ndarray
    radii: np.ndarray
    block_of: np.ndarray  # (N, y, x) block index of every pixel outside the foci, −1 inside
    data: np.ndarray
    sigma: np.ndarray
    exposure_ms: np.ndarray

    def __post_init__(self) -> None:
        n, h, w = self.block_of.shape
        self._windows = circular_windows((h, w), self.centres, self.radii)
        blocks = BLOCKS * BLOCKS  # one bincount over the whole stack; pixels near a focus go to a last bin
        labels = np.where(self.block_of >= 0, self.block_of + blocks * np.arange(n)[:, None, None], n * blocks)
        self._labels = labels.ravel()
        self._block_pixels = np.bincount(self._labels, minlength=n * blocks + 1)[:-1].reshape(n, blocks)

    def features(self, counts: np.ndarray, dark: float) -> np.ndarray:
        """The features of raw frames (N, y, x) counts, less a dark level (counts)."""
        n = len(counts)
        return self.features_of_rate(counts, np.ones(n), 1.0, 0.0, np.zeros(n), dark)

    def features_of_rate(
        self,
        rate: np.ndarray,
        exposure_ms: np.ndarray,
        scale: float,
        dark: float,
        leak_counts: np.ndarray,
        dark_measured: float,
    ) -> np.ndarray:
        """The features of the frames ``dark + exposure·scale·rate + leak`` (rate (N, y, x) per ms,
        exposure (N,) ms, leak (N,) counts) measured less ``dark_measured`` (counts): read at the
        windows' pixels and summed over the background blocks, no full frame of counts formed."""
        rows, cols, inside, complete = self._windows
        gain = np.asarray(exposure_ms, np.float64) * scale
        offset = dark - dark_measured + np.asarray(leak_counts, np.float64)
        index = np.arange(len(rate))[:, None, None, None]
        values = offset[:, None, None, None] + gain[:, None, None, None] * rate[index, rows, cols]
        f = window_features(np.where(inside, values, 0.0), rows, cols, complete)
        sums = np.bincount(self._labels, weights=rate.ravel(), minlength=self._labels.max() + 1)[:-1]
        with np.errstate(invalid="ignore", divide="ignore"):
            means = sums.reshape(self._block_pixels.shape) / self._block_pixels
        blocks = np.where(self._block_pixels > 20, offset[:, None] + gain[:, None] * means, np.nan)
        return np.concatenate(
            [
                f.energy.ravel(),
                f.centroid_px[..., 0].ravel(),
                f.centroid_px[..., 1].ravel(),
                f.width_px.ravel(),
                blocks.ravel(),
            ]
        )


def _block_sums(values: np.ndarray, block_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per image (N, B²) sums of ``values`` (N, y, x) over each background block, and pixel counts."""
    n, blocks = len(values), BLOCKS * BLOCKS
    sums, counts = np.zeros((n, blocks)), np.zeros((n, blocks))
    for i in range(n):  # one bincount per image
        labels = block_of[i].ravel()
        keep = labels >= 0
        sums[i] = np.bincount(labels[keep], weights=values[i].ravel()[keep], minlength=blocks)
        counts[i] = np.bincount(labels[keep], minlength=blocks)
    return sums, counts


def _blocks(shape: tuple[int, int], centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(N, y, x) background block of every pixel (B × B blocks over the frame), −1 near a focus."""
    rows = np.arange(shape[0])[:, None]
    cols = np.arange(shape[1])[None, :]
    label = (rows * BLOCKS // shape[0]) * BLOCKS + (cols * BLOCKS // shape[1])
    return np.where(away_from_foci(shape, centres, 2.5 * radii), label, -1)


def _feature_sigma(space: FeatureSpace, model_signal: np.ndarray, noise: SensorNoise) -> np.ndarray:
    """σ of every feature propagated from the pixel noise of the model's expected counts."""
    var = noise.variance(model_signal).astype(np.float64)
    rows, cols, inside, _ = circular_windows(model_signal.shape[-2:], space.centres, space.radii)
    idx = np.arange(len(space.centres))[:, None, None, None]
    v = np.where(inside, var[idx, rows, cols], 0.0)
    signal = np.where(inside, np.clip(model_signal[idx, rows, cols], 0, None), 0.0)
    energy = signal.sum(axis=(-2, -1))
    with np.errstate(invalid="ignore", divide="ignore"):
        r0 = (signal * rows).sum(axis=(-2, -1)) / energy
        c0 = (signal * cols).sum(axis=(-2, -1)) / energy
        dr2 = (rows - r0[..., None, None]) ** 2
        dc2 = (cols - c0[..., None, None]) ** 2
        w2 = (signal * (dr2 + dc2)).sum(axis=(-2, -1)) / energy
        s_e = np.sqrt(v.sum(axis=(-2, -1)))
        s_r = np.sqrt((v * dr2).sum(axis=(-2, -1))) / energy
        s_c = np.sqrt((v * dc2).sum(axis=(-2, -1))) / energy
        s_w2 = np.sqrt((v * (dr2 + dc2 - w2[..., None, None]) ** 2).sum(axis=(-2, -1))) / energy
        s_w = s_w2 / (2.0 * np.sqrt(w2))
    sums, counts = _block_sums(var, space.block_of)
    with np.errstate(invalid="ignore", divide="ignore"):
        blocks = np.where(counts > 20, np.sqrt(sums) / counts, np.nan)
    return np.concatenate([s_e.ravel(), s_r.ravel(), s_c.ravel(), s_w.ravel(), blocks.ravel()])


@dataclass
class State:
    """Current parameter values: nuisance (4) and the kept effects' parameters."""

    nuisance: np.ndarray
    values: Values = field(default_factory=dict)

    def copy(self) -> State:
        return State(self.nuisance.copy(), {k: dict(v) for k, v in self.values.items()})


@dataclass(frozen=True)
class Step:
    """One round of the loop: what was added and the misfit after it."""

    added: str | None
    chi2: float
    bic: float


@dataclass(frozen=True)
class Attribution:
    effects: dict[str, dict[str, float]]
    uncertainties: dict[str, dict[str, float]]
    steps: tuple[Step, ...]
    registration: Registration
    noise: SensorNoise
    chi2_before: float
    chi2_after: float
    feature_residual: np.ndarray  # normalised residuals (data − model)/σ after the fit
    feature_shape: tuple[int, int]
    #: the sensor's fitted gain pattern (:data:`FLAT_FIELD`'s parameters) where the fit kept one, else None
    flat_field: dict[str, float] | None = None
    #: sentences on choices the data barely make (a larger source against crosstalk or a narrow halo)
    ambiguities: tuple[str, ...] = ()


class Problem:
    """The data, the simulator and the candidates: evaluates features for a parameter state."""

    def __init__(
        self,
        simulator: Simulator,
        counts: np.ndarray,
        exposure_ms: np.ndarray,
        positions_mm: np.ndarray,
        valid: np.ndarray,
        candidates: tuple[Effect, ...],
        counts_per_electron: float | None,
        flat_field: bool = True,
    ):
        """flat_field: whether the sensor's smooth gain (:data:`FLAT_FIELD`) is a candidate."""
        self.simulator = simulator
        self.counts = counts.astype(np.float32)
        self.exposure = np.asarray(exposure_ms, np.float32)
        self.positions = np.asarray(positions_mm, float)
        self.valid = valid
        self.candidates = tuple(c for c in candidates if simulator.supports(c)) + ((FLAT_FIELD,) if flat_field else ())
        nominal = simulator.rates(self.positions, {})
        self.registration, model_counts = register(self.counts, self.exposure, nominal, valid)
        model_signal = model_counts - np.float32(self.registration.dark_level)
        residual = self.counts - model_counts
        lit = model_signal > 1e-3 * float(model_signal.max())
        self.noise = estimate_noise(
            residual[valid],
            model_signal[valid],
            (valid & ~lit)[valid],
            counts_per_electron,
            quantisation_step(counts[valid]),
        )
        self.noise_known = counts_per_electron is not None
        predicted = simulator.focus_centres_px(self.positions) + np.asarray(self.registration.offset_px)
        centres, radii = focus_windows(model_signal, predicted, simulator.pitch_px())
        block_of = _blocks(self.counts.shape[-2:], centres, radii)
        block_of[~valid] = -1
        space = FeatureSpace(centres, radii, block_of, np.empty(0), np.empty(0), self.exposure)
        space.data = space.features(self.counts, self.registration.dark_level)
        space.sigma = _feature_sigma(space, model_signal, self.noise)
        self.space = space
        self.use = np.isfinite(space.data) & np.isfinite(space.sigma) & (space.sigma > 0)
        n, foci = centres.shape[:2]
        focus = np.arange(n * foci)  # features: energy, centroid row, column, width per focus; then blocks
        self.feature_groups = np.concatenate(
            [focus, focus, focus, focus, n * foci + np.repeat(np.arange(n), BLOCKS**2)]
        )
        self._sectors: np.ndarray | None = None
        self.feature_kinds = np.repeat(np.arange(len(OBSERVABLES)), [n * foci, 2 * n * foci, n * foci, n * BLOCKS**2])
        self._rates: dict[tuple, np.ndarray] = {}
        self._image_rates: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self.expensive = frozenset(getattr(simulator, "retraced", ()))
        self.anchor: Values = {}
        self._anchor_state = self.start()
        self._derivatives: dict[tuple[str, str], np.ndarray] = {}

    def start(self) -> State:
        r = self.registration
        return State(np.array([r.offset_px[0], r.offset_px[1], r.flux_scale, r.dark_level], float))

    def _shifted_rate(self, state: State) -> np.ndarray:
        """The simulator's images with the optical effects and the state's frame offset (cached)."""
        optical = {k: v for k, v in state.values.items() if not _is_image_side(k)}
        offset = (round(float(state.nuisance[0]), 9), round(float(state.nuisance[1]), 9))
        key = (repr(sorted((k, sorted(v.items())) for k, v in optical.items())), offset)
        if key not in self._rates:
            if len(self._rates) > 24:
                self._rates.clear()
            self._rates[key] = self.simulator.rates(self.positions, optical, offset)
        return self._rates[key]

    def model_counts(self, state: State) -> np.ndarray:
        """Expected raw counts (N, y, x) of the data under ``state``."""
        rate = apply_image_effects(self._shifted_rate(state), state.values, self.simulator.pixel_um)
        if FLAT_FIELD.key in state.values:
            rate = rate * flat_field_gain(rate.shape[-2:], state.values[FLAT_FIELD.key])
        leak = leakage_counts(state.values, self.exposure)[:, None, None]
        scale, dark = state.nuisance[2], state.nuisance[3]
        return (dark + self.exposure[:, None, None] * (scale * rate) + leak).astype(np.float32)

    def exact_features(self, state: State) -> np.ndarray:
        """The model's features under ``state`` (its counts as :meth:`model_counts`), the simulator
        run with every value as it is, measured like the data's (the same windows, the same dark
        level subtracted, so that a change of the fitted dark shows)."""
        rate = self._image_rate(state)
        leak = leakage_counts(state.values, self.exposure)
        scale, dark = float(state.nuisance[2]), float(state.nuisance[3])
        return self.space.features_of_rate(rate, self.exposure, scale, dark, leak, self.registration.dark_level)

    def _image_rate(self, state: State) -> np.ndarray:
        """The simulator's images with the sensor-side effects applied (cached: the flux, dark
        and leakage columns of a Jacobian reuse the same blurred images)."""
        rate = self._shifted_rate(state)
        image_side = {k: v for k, v in state.values.items() if k in ("stray_light", "pixel_crosstalk", FLAT_FIELD.key)}
        if not image_side:
            return rate
        key = (id(rate), repr(sorted((k, sorted(v.items())) for k, v in image_side.items())))
        if key not in self._image_rates:
            if len(self._image_rates) > 8:
                self._image_rates.clear()
            out = apply_image_effects(rate, image_side, self.simulator.pixel_um)
            if FLAT_FIELD.key in image_side:
                out = out * flat_field_gain(out.shape[-2:], image_side[FLAT_FIELD.key])
            self._image_rates[key] = (rate, out)
        return self._image_rates[key][1]

    def features(self, state: State) -> np.ndarray:
        """The model's features under ``state``: exact, except that the simulator's expensive
        effects (``simulator.retraced``: a fresh trace each) are run at their anchor values and
        their departures from it added linearly, by derivatives taken once at the anchor
        (:meth:`reanchor` moves the anchor to where the fit went, so the fit converges on the
        exact model)."""
        keys = [k for k in state.values if k in self._expensive_keys]
        if not keys:
            return self.exact_features(state)
        anchored = state.copy()
        for key in keys:
            anchored.values[key] = dict(self.anchor.get(key, _effect(self, key).defaults()))
        f = self.exact_features(anchored)
        for key in keys:
            for name, value in state.values[key].items():
                delta = value - anchored.values[key][name]
                if delta != 0.0:
                    f = f + self._derivative(key, name) * delta
        return f

    @property
    def _expensive_keys(self) -> set[str]:
        return {c.key for c in self.candidates if c.name in self.expensive}

    def _derivative(self, key: str, name: str) -> np.ndarray:
        """d(features)/d(parameter) of an expensive effect at the anchor (finite difference of
        the exact features, the other values as they were when the anchor was set; cached)."""
        if (key, name) not in self._derivatives:
            base = self._anchor_state.copy()
            for k in self._expensive_keys:
                base.values.pop(k, None)
            base.values.update({k: dict(v) for k, v in self.anchor.items()})
            column = _columns(self, base, [(key, name)], self.exact_features(base), exact=True)[:, 0]
            self._derivatives[(key, name)] = np.nan_to_num(column)
        return self._derivatives[(key, name)]

    def _departed(self, state: State, keys: set[str], anchor: Values) -> bool:
        """Whether any effect of ``keys`` in ``state`` (or in ``anchor``) is more than half its
        finite-difference step away from its value in ``anchor`` (default: absent)."""
        for key in keys & (set(state.values) | set(anchor)):
            effect = _effect(self, key)
            now, then = state.values.get(key, effect.defaults()), anchor.get(key, effect.defaults())
            if any(abs(now[p.name] - then[p.name]) > 0.5 * p.step for p in effect.parameters):
                return True
        return False

    def reanchor(self, state: State) -> bool:
        """Move the anchors to ``state`` where it has left them by more than half a
        finite-difference step: the expensive effects' linearisation point, and, for a simulator
        that traces its moving effects on request (``trace_at``), the moving effects; whether
        anything moved (then the next evaluations are exact at ``state``)."""
        moved = False
        trace_at = getattr(self.simulator, "trace_at", None)
        if trace_at is not None:
            moving = {c.key for c in self.candidates if c.name not in self.expensive and not _is_image_side(c.key)}
            if self._departed(state, moving, self.simulator.anchor):
                trace_at({k: v for k, v in state.values.items() if k in moving})
                self._rates.clear()
                moved = True
        if moved or self._departed(state, self._expensive_keys, self.anchor):
            self.anchor = {k: dict(state.values[k]) for k in self._expensive_keys & set(state.values)}
            self._anchor_state = state.copy()
            self._derivatives = {}
            moved = True
        return moved

    def pixel_change(self, before: State, after: State) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The data's residual under ``before``, the model's change from ``before`` to ``after``,
        the pixels' noise σ (counts) and their direction from the nearest focus (:data:`SECTORS`),
        over the valid pixels (1-D)."""
        if self._sectors is None:
            self._sectors = _sectors(self.counts.shape[-2:], self.space.centres)[self.valid]
        start = self.model_counts(before)
        change = self.model_counts(after)[self.valid] - start[self.valid]
        sigma = np.sqrt(self.noise.variance(start[self.valid] - np.float32(self.registration.dark_level)))
        return (self.counts - start)[self.valid], change, sigma, self._sectors

    def reweight(self, state: State) -> None:
        """The features' σ propagated from the model under ``state`` (the fit so far) instead of
        the nominal one: a focus that the nominal model makes bright but the data show dim (a
        narrow source, a dusty lenslet) gets the centroid and width σ of its real energy. The
        features that take part stay the same, so criteria stay comparable."""
        signal = self.model_counts(state) - np.float32(self.registration.dark_level)
        sigma = _feature_sigma(self.space, signal, self.noise)
        keep = np.isfinite(sigma) & (sigma > 0)
        self.space.sigma = np.where(keep, sigma, self.space.sigma)

    def chi2(self, f: np.ndarray) -> float:
        r = (self.space.data[self.use] - f[self.use]) / self.space.sigma[self.use]
        return float(np.sum(r[np.isfinite(r)] ** 2))

    @property
    def n_features(self) -> int:
        return int(self.use.sum())


def _sectors(shape: tuple[int, int], centres: np.ndarray) -> np.ndarray:
    """(N, y, x) the direction of every pixel from its frame's nearest focus (``centres`` (N, J, 2)
    (row, col) px): the index into :data:`SECTORS` (quarters about +col, +row, −col, −row)."""
    rows = np.arange(shape[0], dtype=np.float32)[:, None]
    cols = np.arange(shape[1], dtype=np.float32)[None, :]
    out = np.zeros((len(centres), *shape), np.int8)
    for i, frame in enumerate(centres):
        nearest = np.full(shape, np.inf, np.float32)
        d_row, d_col = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        for r0, c0 in frame[np.isfinite(frame).all(axis=1)]:
            d2 = (rows - r0) ** 2 + (cols - c0) ** 2
            closer = d2 < nearest
            nearest = np.where(closer, d2, nearest)
            d_row, d_col = np.where(closer, rows - r0, d_row), np.where(closer, cols - c0, d_col)
        out[i] = np.round(np.arctan2(d_row, d_col) / (np.pi / 2)).astype(np.int8) % 4
    return out


def _is_image_side(key: str) -> bool:
    return key in {"stray_light", "pixel_crosstalk", "leakage_background", FLAT_FIELD.key}


def _columns(
    problem: Problem, state: State, params: list[tuple[str, str]], base: np.ndarray, exact: bool = False
) -> np.ndarray:
    """Finite-difference Jacobian columns (features × params) at ``state``; params are
    (effect key, parameter name) or ("nuisance", index); ``exact``: of the exact features."""
    cols = []
    for key, name in params:
        trial = state.copy()
        if key == "nuisance":
            k = int(name)
            trial.nuisance[k] += NUISANCE_STEPS[k]
            h = NUISANCE_STEPS[k]
        else:
            effect = _effect(problem, key)
            parameter = next(p for p in effect.parameters if p.name == name)
            values = trial.values.setdefault(key, effect.defaults())
            h = parameter.step  # a step across the range's edge goes the other way
            h = -h if not parameter.low <= values[name] + h <= parameter.high else h
            values[name] = values[name] + h
        cols.append(((problem.exact_features if exact else problem.features)(trial) - base) / h)
    return np.stack(cols, axis=1) if cols else np.zeros((len(base), 0))


def _effect(problem: Problem, key: str) -> Effect:
    return next(e for e in problem.candidates if e.key == key)


def _parameters(problem: Problem, keys: list[str]) -> list[tuple[str, str]]:
    out = [("nuisance", str(k)) for k in range(len(NUISANCE))]
    for key in keys:
        out += [(key, p.name) for p in _effect(problem, key).parameters]
    return out


def _solve(problem: Problem, jac: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Weighted linear least squares: step, predicted χ², covariance."""
    use = problem.use & np.all(np.isfinite(jac), axis=1) & np.isfinite(residual)
    w = 1.0 / problem.space.sigma[use]
    a = jac[use] * w[:, None]
    b = residual[use] * w
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    step, *_ = np.linalg.lstsq(a / scale, b, rcond=1e-10)
    step = step / scale
    chi2 = float(np.sum((b - a @ step) ** 2))
    cov = np.linalg.pinv((a / scale).T @ (a / scale)) / np.outer(scale, scale)
    return step, chi2, cov


def _apply(problem: Problem, state: State, params: list[tuple[str, str]], step: np.ndarray) -> State:
    trial = state.copy()
    for (key, name), delta in zip(params, step, strict=True):
        if key == "nuisance":
            trial.nuisance[int(name)] += delta
            continue
        effect = _effect(problem, key)
        parameter = next(p for p in effect.parameters if p.name == name)
        values = trial.values.setdefault(key, effect.defaults())
        values[name] = float(np.clip(values[name] + delta, parameter.low, parameter.high))
    return trial


def _refine(problem: Problem, state: State, keys: list[str], iterations: int = 6) -> tuple[State, float, np.ndarray]:
    """Gauss–Newton on the nuisance and the kept effects, with step halving."""
    params = _parameters(problem, keys)
    base = problem.features(state)
    chi2 = problem.chi2(base)
    cov = np.zeros((len(params), len(params)))
    for _ in range(iterations):
        jac = _columns(problem, state, params, base)
        step, _, cov = _solve(problem, jac, problem.space.data - base)
        for _halving in range(6):
            trial = _apply(problem, state, params, step)
            f = problem.features(trial)
            c = problem.chi2(f)
            if c < chi2:
                break
            step = step / 2
        else:
            break
        improvement = chi2 - c
        state, base, chi2 = trial, f, c
        if improvement < 1e-3 * chi2:
            break
    return state, chi2, cov


#: Diameters (µm beyond the declared one) the ``source_size`` candidate starts from: the foci
#: widen with the square of the diameter, so that its derivative vanishes at the declared size.
SOURCE_SIZE_PROBES_UM = (40.0, 120.0)


def _probe_values(effect: Effect) -> list[dict[str, float]]:
    """Starting points for an effect whose derivative vanishes at its default (a halo of zero
    strength has no width to fit; a source's disc widens the foci by the square of its diameter):
    the default, plus a few widths for the stray-light halo; a few diameters for the source."""
    if effect.name == "stray_light":
        return [dict(effect.defaults(), fraction=0.02, width_um=w) for w in (60.0, 200.0, 600.0)]
    if effect.name == "source_size":
        (size,) = effect.parameters
        return [{size.name: min(size.default + d, size.high)} for d in SOURCE_SIZE_PROBES_UM]
    return [effect.defaults()]


def _criterion(problem: Problem, n: int) -> Callable[[float, int], float]:
    """The Bayesian information criterion of a fit with misfit χ² and k parameters over n features.

    With the camera's gain known the noise is known: BIC = χ² + k·ln n, and the loop may stop at
    the noise floor. With the gain estimated from the data, the noise's scale is not known (a
    misfit inflates the estimate): it is profiled out, BIC = n·ln(χ²/n) + k·ln n, which compares
    fits by their relative misfit whatever the scale.
    """
    if problem.noise_known:
        return lambda chi2, k: chi2 + k * math.log(n)
    return lambda chi2, k: n * math.log(max(chi2, 1e-300) / n) + k * math.log(n)


#: Candidates of a round, best first by their one-step score, that get a few Gauss–Newton steps
#: before the choice (an effect far outside its linear range, a vignetting edge moved by more
#: than its softness, is under-scored by one linear step).
FINALISTS = 3
#: The guard: share of the χ² above the noise floor an effect must remove to be kept …
MIN_EXCESS_SHARE = 0.1
#: … and the most χ² it may add to the foci (and frames' backgrounds) it makes worse, as a share
#: of what it removes from those it makes better: a physical effect explains the residual where
#: it acts; a global or per-lenslet parameter stretched over a localised residual (a scratch that
#: dims one lenslet at some source positions) trades large gains at a few foci for losses at the rest.
MAX_WORSENED_SHARE = 0.25
#: … and, of the groups where the new effect alone moves the model by at least ``ACTS_CHI2`` (3 σ),
#: the most it may make worse, counted group by group, not weighted by their χ²: a per-lenslet
#: transmission predicts the same loss at every source position, and a filter scratch that dims
#: the lenslet's view at two positions out of eight is bought with bright gains there and
#: losses at the other six.
MAX_CONTRADICTED_SHARE = 0.5
ACTS_CHI2 = 9.0


def _finalists(problem: Problem, scored: list, kept: list[str], bic, k_now: int) -> list[tuple[float, str, State]]:
    """The round's candidates for the choice: the :data:`FINALISTS` best one-step candidates
    refined by three Gauss–Newton steps each (probes are refined already), lowest criterion first."""
    out = []
    for score, key, candidate, linear in sorted(scored, key=lambda item: item[0])[:FINALISTS]:
        if linear:
            candidate, c, _ = _refine(problem, candidate, kept + [key], iterations=3)
            score = bic(c, k_now + len(_effect(problem, key).parameters))
        out.append((score, key, candidate))
    return sorted(out, key=lambda item: item[0])


#: … and every observable the fit changes by a χ² of at least ``CONFIRM_CHI2`` (its amplitude there
#: then known to ±1/6, so that ½ lies 3 σ from both 0 and 1) must bear the change out: the data's
#: residual projected on it must hold at least ``CONFIRMED`` of it (a right effect's 1 ± 1/6 lies
#: 4.5 σ above; a second effect not yet fitted may hold a little of one observable against the
#: first: the matrix's narrow source beside partial lenslets has its widths borne out at 0.38,
#: and ½, where the observable's χ² starts to fall, refused it). A physical
#: effect predicts every observable it moves — a tilted array defocuses its outer lenslets, a
#: halo adds light around each focus, not 14 px aside — and a proxy fitted for one of them
#: (a tilt for a shift or an energy pattern, a halo for a ghost) predicts the others wrong.
CONFIRM_CHI2 = 36.0
CONFIRMED = 0.25
#: The observables of the confirmation: the feature kinds in their order; then the pixels, in four
#: quarters by their direction from the nearest focus (a halo acts all round a focus: fitted to a
#: ghost on one side, it is borne out there and not on the others).
OBSERVABLES = ("energy", "centroid", "width", "background")
SECTORS = ("right of", "below", "left of", "above")


def confirmation(residual: np.ndarray, change: np.ndarray, sigma: np.ndarray) -> tuple[float, float]:
    """(a, S): the amplitude a = ⟨r, Δ⟩/⟨Δ, Δ⟩ of the model's change Δ that the data's residual r
    holds, and the change's χ² S = ⟨Δ, Δ⟩ (inner products weighted by 1/σ²; non-finite terms
    dropped). The χ² of the observable falls by S·(2a − 1) when the change is made."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r, d = residual / sigma, change / sigma
    keep = np.isfinite(r) & np.isfinite(d)
    size = float(np.sum(d[keep] ** 2, dtype=np.float64))
    return (float(np.sum(r[keep] * d[keep], dtype=np.float64)) / size if size > 0 else 1.0), size


@dataclass(frozen=True)
class Guard:
    """How a candidate's fit changes the misfit (the guard of :func:`attribute`).

    excess_share: the share of the χ² above the noise floor (1 per feature) it removes; with the
        camera's gain estimated from the data the floor is not known, and the share is of all the χ².
    worsened_share: χ² added to the groups it makes worse (a focus's energy, centroid and
        width; a frame's background blocks) over χ² removed from those it makes better.
    contradicted_share: of the groups the new effect alone moves by ≥ ``ACTS_CHI2`` (its values
        set on ``before``), the share the fit makes worse (0 when it moves none).
    amplitudes: per observable (:data:`OBSERVABLES`, the pixels by :data:`SECTORS`) the fit
        changes by χ² ≥ ``CONFIRM_CHI2``, the share of its change the data bear out
        (:func:`confirmation`; 1 for a right effect), and ``sizes`` that change's χ² S.
    """

    excess_share: float
    worsened_share: float
    contradicted_share: float = 0.0
    amplitudes: dict[str, float] = field(default_factory=dict)
    sizes: dict[str, float] = field(default_factory=dict)

    @property
    def unconfirmed(self) -> list[str]:
        """The observables whose change the data do not bear out (amplitude below :data:`CONFIRMED`)."""
        return [name for name, a in self.amplitudes.items() if a < CONFIRMED]

    @property
    def passed(self) -> bool:
        return (
            self.excess_share >= MIN_EXCESS_SHARE
            and self.worsened_share <= MAX_WORSENED_SHARE
            and self.contradicted_share <= MAX_CONTRADICTED_SHARE
            and not self.unconfirmed
        )


def guard(problem: Problem, before: State, after: State) -> Guard:
    """The guard's figures for the fit going from ``before`` to ``after`` (:class:`Guard`)."""
    use = problem.use
    data, sigma = problem.space.data[use], problem.space.sigma[use]
    f_before = problem.features(before)
    f_after = problem.features(after)
    r_before = (data - f_before[use]) / sigma
    r_after = (data - f_after[use]) / sigma
    gained = np.nan_to_num(r_before**2 - r_after**2)
    group_of = problem.feature_groups[use]
    groups = np.bincount(group_of, weights=gained)
    better, worse = groups[groups > 0].sum(), -groups[groups < 0].sum()
    floor = problem.n_features if problem.noise_known else 0.0  # with the gain estimated, no floor is known
    excess = float(np.nansum(r_before**2)) - floor
    share = float(gained.sum() / excess) if excess > 0 else 0.0
    alone = before.copy()  # the new effect at its fitted values, everything else as before
    alone.values.update({k: dict(v) for k, v in after.values.items() if k not in before.values})
    moved = np.nan_to_num(((problem.features(alone) - f_before)[use] / sigma) ** 2)
    acts = np.bincount(group_of, weights=moved, minlength=len(groups)) >= ACTS_CHI2
    contradicted = float(np.mean(groups[acts] < 0)) if acts.any() else 0.0
    kinds = problem.feature_kinds[use]
    change = (f_after - f_before)[use] / sigma
    checks = {name: confirmation(r_before[kinds == k], change[kinds == k], 1.0) for k, name in enumerate(OBSERVABLES)}
    residual, change, noise, sector = problem.pixel_change(before, after)
    for k, where in enumerate(SECTORS):
        part = sector == k
        checks[f"pixels {where} the foci"] = confirmation(residual[part], change[part], noise[part])
    marked = {name: check for name, check in checks.items() if check[1] >= CONFIRM_CHI2}
    amplitudes, sizes = {k: a for k, (a, _) in marked.items()}, {k: size for k, (_, size) in marked.items()}
    return Guard(share, float(worse / better) if better > 0 else math.inf, contradicted, amplitudes, sizes)


#: Effects that widen every focus alike, as a calibration source larger than declared does: on foci
#: a pixel or two wide (σ ≈ 1.6 px at 8× binning) a 4-neighbour crosstalk of 0.1 and a 30-µm disc
#: differ in χ² by ≈ 5–7 (the disc's blur grows with the magnification, ±3.4 % over z ±0.3 mm).
WIDENING_RIVALS = ("pixel_crosstalk", "stray_light")


def _declared_source_first(
    problem: Problem,
    best: tuple[float, str, State],
    scored: list,
    state: State,
    kept: list[str],
    bic: Callable[[float, int], float],
    k_now: int,
) -> tuple[tuple[float, str, State], str | None]:
    """The round's choice between ``source_size`` and the effects that widen the foci alike
    (:data:`WIDENING_RIVALS`): the scan declares its source's size, so that ``source_size``, which
    contradicts the declaration, is kept only when it beats each rival that is significant and
    passes the guard by ``BIC_THRESHOLD`` (very strong evidence); else the best such rival is kept.
    Returns the choice and, where the two are that close, a sentence saying so (else None)."""
    score, key, _ = best
    size_key = "source_size"
    if key != size_key and key not in WIDENING_RIVALS:
        return best, None
    current = bic(problem.chi2(problem.features(state)), k_now)
    options: dict[str, tuple[float, str, State]] = {key: best}
    for trial_score, trial_key, candidate, linear in sorted(scored, key=lambda item: item[0]):
        if trial_key in options or trial_key in kept or (trial_key != size_key and trial_key not in WIDENING_RIVALS):
            continue
        if linear:
            candidate, c, _ = _refine(problem, candidate, kept + [trial_key], iterations=3)
            trial_score = bic(c, k_now + len(_effect(problem, trial_key).parameters))
        if current - trial_score >= BIC_THRESHOLD and guard(problem, state, candidate).passed:
            options[trial_key] = (trial_score, trial_key, candidate)
    if size_key not in options:
        return best, None
    rivals = [option for k, option in options.items() if k != size_key]
    if not rivals:
        return best, None
    rival = min(rivals, key=lambda option: option[0])
    size = options[size_key]
    margin = rival[0] - size[0]  # > 0: the larger source fits better
    if margin >= BIC_THRESHOLD:
        return size, None
    diameter = size[2].values[size_key]["diameter_um"]
    note = (
        f"{rival[1]} and a calibration source larger than declared (source_size, {diameter:.0f} µm) widen the foci "
        f"alike and fit within ΔBIC {abs(margin):.1f} of each other ({'the larger source' if margin > 0 else rival[1]} "
        f"better): the declared source is kept and {rival[1]} named; check the source's size"
    )
    return rival, note


def attribute(problem: Problem, *, max_effects: int = 6, progress: Progress | None = None) -> Attribution:
    """Run the loop of the module docstring on ``problem``."""
    say = progress or (lambda message: None)
    state = problem.start()
    kept: list[str] = []
    state, chi2, cov = _refine(problem, state, kept, iterations=2)
    n = problem.n_features
    chi2_before = chi2
    bic = _criterion(problem, n)
    steps = [Step(None, chi2, bic(chi2, len(NUISANCE)))]
    ambiguities: list[str] = []
    say(f"nominal design: χ²/n = {chi2 / n:.3f}")
    while len(kept) < max_effects and (chi2 / n > CHI2_FLOOR or not problem.noise_known):
        base = problem.features(state)
        params = _parameters(problem, kept)
        k_now = len(params)
        scored: list[tuple[float, str, State, bool]] = []
        base_jac = _columns(problem, state, params, base)
        for effect in problem.candidates:
            if effect.key in kept:
                continue
            for start in _probe_values(effect):
                trial = state.copy()
                trial.values[effect.key] = dict(start)
                extra = [(effect.key, p.name) for p in effect.parameters]
                if start == effect.defaults():  # the effect is absent: the other columns are the state's
                    trial_base = base
                    jac = np.hstack([base_jac, _columns(problem, trial, extra, trial_base)])
                else:
                    trial_base = problem.features(trial)
                    jac = _columns(problem, trial, params + extra, trial_base)
                step, predicted, _ = _solve(problem, jac, problem.space.data - trial_base)
                candidate = _apply(problem, trial, params + extra, step)
                if start == effect.defaults():
                    c = problem.chi2(problem.features(candidate))
                else:  # a probe starts far from the answer (a halo's width): a few steps, not one
                    candidate, c, _ = _refine(problem, candidate, kept + [effect.key], iterations=3)
                scored.append((bic(c, k_now + len(extra)), effect.key, candidate, start == effect.defaults()))
        current_bic = bic(chi2, k_now)
        best = None
        for score, key, candidate in _finalists(problem, scored, kept, bic, k_now):
            if current_bic - score < BIC_THRESHOLD:
                break
            check = guard(problem, state, candidate)
            if check.passed:
                best = (score, key, candidate)
                break
            unconfirmed = ", ".join(f"{name} {check.amplitudes[name]:.0%}" for name in check.unconfirmed) or "none"
            say(
                f"{key} is significant but does not match the residual (removes {check.excess_share:.0%} of the "
                f"excess χ², adds {check.worsened_share:.0%} of its gain where it makes the fit worse, makes "
                f"{check.contradicted_share:.0%} of the foci it acts on worse; its change borne out by the data "
                f"below a quarter in: {unconfirmed}): left unexplained"
            )
        if best is None:
            say("no further effect is significant and matches the residual")
            break
        best, note = _declared_source_first(problem, best, scored, state, kept, bic, k_now)
        if note is not None:
            say(note)
            ambiguities.append(note)
        kept.append(best[1])
        state, chi2, cov = _refine(problem, best[2], kept)
        for _ in range(4):  # Newton on the exact model: re-linearise the expensive effects where the fit went
            if not problem.reanchor(state):
                break
            state, chi2, cov = _refine(problem, state, kept)
        problem.reweight(state)  # the noise of the features as the fitted model predicts it
        state, chi2, cov = _refine(problem, state, kept, iterations=2)
        steps.append(Step(best[1], chi2, bic(chi2, len(_parameters(problem, kept)))))
        what = (
            " (the sensor's gain pattern, a nuisance: not an effect of the optics)" if best[1] == FLAT_FIELD.key else ""
        )
        say(f"added {best[1]}{what}: χ²/n = {chi2 / n:.3f}")
    params = _parameters(problem, kept)
    inflate = max(1.0, chi2 / max(n - len(params), 1))
    sigma = np.sqrt(np.clip(np.diag(cov), 0, None) * inflate) if cov.size else np.zeros(len(params))
    effects = {key: dict(state.values[key]) for key in kept if key != FLAT_FIELD.key}
    uncertainties: dict[str, dict[str, float]] = {key: {} for key in effects}
    for (key, name), s in zip(params, sigma, strict=False):
        if key in uncertainties:
            uncertainties[key][name] = float(s)
    final = problem.features(state)
    with np.errstate(invalid="ignore", divide="ignore"):
        residual = (problem.space.data - final) / problem.space.sigma
    registration = Registration(
        (float(state.nuisance[0]), float(state.nuisance[1])), float(state.nuisance[2]), float(state.nuisance[3])
    )
    return Attribution(
        effects=effects,
        uncertainties=uncertainties,
        steps=tuple(steps),
        registration=registration,
        noise=problem.noise,
        chi2_before=chi2_before / n,
        chi2_after=chi2 / n,
        feature_residual=residual,
        feature_shape=problem.space.centres.shape[:2],
        flat_field=dict(state.values[FLAT_FIELD.key]) if FLAT_FIELD.key in kept else None,
        ambiguities=tuple(ambiguities),
    )


__all__ = ["FLAT_FIELD", "Attribution", "Guard", "Problem", "attribute", "confirmation", "flat_field_gain", "guard"]

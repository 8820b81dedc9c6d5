"""Statistics for comparing runs: IQM, percentile bootstrap, stratified bootstrap (rliable).

Everything here is pure numpy/scipy (+ rliable) and deterministic given a seed, so two reports
written from the same runs are identical.

rliable's stratified bootstrap (``rliable.library``) needs the ``arch`` package, and arch 7.x
(the newest rliable 1.2.0 allows) does not import under pandas 3. When ``rliable.library``
cannot be imported, the same stratified percentile bootstrap is computed here in numpy;
:func:`bootstrap_backend` says which one ran, and the point estimates always come from
``rliable.metrics``.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import scipy.stats

log = logging.getLogger(__name__)

Interval = tuple[float, float, float]
"""(point estimate, CI low, CI high)."""

DEFAULT_N_BOOT = 2000
"""rliable's own examples use 2,000 reps for probability of improvement; 50,000 (its default)
costs minutes per comparison for no visible change at 2-3 decimals."""

MIN_SEEDS_FOR_VERDICT = 3
"""The fewest finished seeds each compared configuration needs before a report reads a result as a
difference, or a thesis claim as borne out or not. With one seed per configuration every bootstrap
resample is the same pair, so P(X > Y) comes out 0 or 1 with a zero-width interval; with two, the
interval still has only a handful of distinct resamples."""


def _rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    """A Generator from a seed; None means seed 0 (reports must be reproducible)."""
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(0 if rng is None else rng)


def _seed_of(rng: np.random.Generator | int | None) -> int:
    """An int seed for APIs that need one (rliable's global-RNG bootstrap)."""
    if isinstance(rng, np.random.Generator):
        return int(rng.integers(2**31 - 1))
    return 0 if rng is None else int(rng)


def iqm(x: Any, axis: int | None = None) -> Any:
    """Interquartile mean: the mean of the middle 50% (25% trimmed from each end).

    Same definition as rliable (``scipy.stats.trim_mean(x, 0.25)``): ``int(0.25 * n)`` values
    are cut from each end, so for n < 4 it is the plain mean.
    """
    return scipy.stats.trim_mean(np.asarray(x, dtype=float), proportiontocut=0.25, axis=axis)


def bootstrap_ci(
    samples: Any,
    statistic: Callable[..., Any] = np.mean,
    n_boot: int = DEFAULT_N_BOOT,
    conf: float = 0.95,
    rng: np.random.Generator | int | None = None,
) -> tuple[float, float]:
    """Percentile-bootstrap ``conf`` interval of ``statistic(samples)``; returns (low, high).

    ``samples`` is resampled with replacement along axis 0. ``statistic`` is called once on all
    resamples with ``axis=-1`` when it accepts that keyword (numpy reductions, :func:`iqm`),
    otherwise once per resample.
    """
    x = np.asarray(samples, dtype=float).ravel()
    if x.size == 0:
        raise ValueError("bootstrap_ci needs at least one sample")
    idx = _rng(rng).integers(0, x.size, size=(n_boot, x.size))
    try:
        stats = np.asarray(statistic(x[idx], axis=-1), dtype=float)
    except TypeError:  # statistic without an axis keyword
        stats = np.array([statistic(row) for row in x[idx]], dtype=float)
    half = (1.0 - conf) / 2.0
    lo, hi = np.percentile(stats, [100 * half, 100 * (1 - half)])
    return float(lo), float(hi)


def mean_ci_band(
    curves: Any,
    n_boot: int = DEFAULT_N_BOOT,
    conf: float = 0.95,
    rng: np.random.Generator | int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds and a percentile-bootstrap ``conf`` band, for curves (n_seeds, n_points).

    NaN marks a point a seed has no value for (a partial run, a metric not logged yet): each
    point is averaged over the seeds that have it. Resampling is over seeds (whole curves), as
    the seeds are the independent units. With one seed the band collapses onto the curve.
    """
    c = np.atleast_2d(np.asarray(curves, dtype=float))
    n = c.shape[0]
    have = np.isfinite(c)
    vals = np.where(have, c, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = vals.sum(0) / have.sum(0)
        # Multinomial counts are exactly "draw n seeds with replacement", and the weighted
        # means cost (n_boot, n_points) memory instead of (n_boot, n_seeds, n_points).
        counts = _rng(rng).multinomial(n, np.full(n, 1.0 / n), size=n_boot).astype(float)
        boot = (counts @ vals) / (counts @ have)
    half = (1.0 - conf) / 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: no seed has the point
        lo, hi = np.nanpercentile(boot, [100 * half, 100 * (1 - half)], axis=0)
    return mean, lo, hi


def align_curves(
    series: Sequence[tuple[Any, Any]],
) -> tuple[np.ndarray, np.ndarray]:
    """Put (steps, values) series of several runs on one step grid: (grid, curves (n_runs, n_grid)).

    The grid is the union of all steps. Each run is linearly interpolated between its own finite
    points and NaN outside them, so a partial run never contributes beyond its last value.
    """
    cleaned = []
    for steps, values in series:
        s, v = np.asarray(steps, dtype=float), np.asarray(values, dtype=float)
        ok = np.isfinite(s) & np.isfinite(v)
        order = np.argsort(s[ok], kind="stable")
        cleaned.append((s[ok][order], v[ok][order]))
    grid = np.unique(np.concatenate([s for s, _ in cleaned])) if cleaned else np.empty(0)
    out = np.full((len(cleaned), grid.size), np.nan)
    for i, (s, v) in enumerate(cleaned):
        if s.size:
            inside = (grid >= s[0]) & (grid <= s[-1])
            out[i, inside] = np.interp(grid[inside], s, v)
    return grid, out


# --------------------------------------------------------------------------- stratified bootstrap


def _rly_metrics() -> Any:
    """``rliable.metrics``, imported on first use (it is slow to import and plots do not need it)."""
    from mcrl.extras import require  # noqa: PLC0415

    return require("rliable.metrics", None, "the report's statistics")


@functools.cache
def _rliable_library() -> Any | None:
    """``rliable.library`` if it imports here, else None (see the module docstring)."""
    try:
        from rliable import library  # noqa: PLC0415 - optional, heavy (arch, pandas, statsmodels)
    except Exception as e:  # noqa: BLE001 - arch fails with TypeError under pandas 3, not ImportError
        log.warning("rliable.library unavailable (%s: %s); using mcrl's numpy stratified bootstrap",
                    type(e).__name__, e)
        return None
    return library


def bootstrap_backend() -> str:
    """Which stratified bootstrap :func:`stratified_iqm_ci` and :func:`probability_of_improvement` use."""
    if _rliable_library() is not None:
        return "rliable.library.get_interval_estimates"
    return "mcrl.analysis.stats numpy stratified bootstrap (rliable.library unavailable: arch does not import)"


@contextlib.contextmanager
def _seeded_global_numpy(seed: int) -> Iterator[None]:
    """Seed numpy's global RNG for the duration, then restore it.

    rliable's bootstrap classes draw indices from ``np.random.choice`` (the global RNG), not
    from the ``random_state`` they are given, so this is the only way to make them reproducible
    (and passing a RandomState only earns a FutureWarning from arch).
    """
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def _as_runs_by_tasks(x: Any) -> np.ndarray:
    """Scores as rliable wants them: (num_runs, num_tasks); a 1-D array is one task."""
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] == 0:
        raise ValueError(f"scores must be (num_runs,) or (num_runs, num_tasks) with runs > 0, got {a.shape}")
    return a


def _stratified_resample(a: np.ndarray, rng: np.random.Generator, n_boot: int) -> np.ndarray:
    """(n_boot, runs, tasks): runs redrawn with replacement within each task, as rliable does."""
    idx = rng.integers(0, a.shape[0], size=(n_boot, *a.shape))
    return a[idx, np.arange(a.shape[1])[None, None, :]]


def _percentiles(stats: np.ndarray, conf: float) -> tuple[float, float]:
    half = (1.0 - conf) / 2.0
    lo, hi = np.percentile(stats, [100 * half, 100 * (1 - half)])
    return float(lo), float(hi)


def stratified_iqm_ci(
    score_dict: Mapping[str, Any],
    n_boot: int = DEFAULT_N_BOOT,
    conf: float = 0.95,
    seed: int = 0,
) -> dict[str, Interval]:
    """IQM of each entry's scores with a stratified-bootstrap ``conf`` CI (rliable).

    ``score_dict`` maps a name to scores of shape (num_runs,) or (num_runs, num_tasks). Returns
    name -> (IQM, low, high). Runs are resampled within each task (rliable's StratifiedBootstrap).
    Each entry is bootstrapped from its own ``seed``-seeded stream, so its interval does not move when
    another entry is added, removed or gains a run.
    """
    scores = {k: _as_runs_by_tasks(v) for k, v in score_dict.items()}
    rly_metrics = _rly_metrics()
    lib = _rliable_library()
    out: dict[str, Interval] = {}
    for k, a in scores.items():
        if lib is not None:
            with _seeded_global_numpy(seed):
                points, cis = lib.get_interval_estimates(
                    {k: a}, lambda s: np.array([rly_metrics.aggregate_iqm(s)]), method="percentile",
                    reps=n_boot, confidence_interval_size=conf)
            out[k] = (float(np.ravel(points[k])[0]), float(cis[k][0, 0]), float(cis[k][1, 0]))
        else:
            boot = _stratified_resample(a, np.random.default_rng(seed), n_boot).reshape(n_boot, -1)
            out[k] = (float(rly_metrics.aggregate_iqm(a)), *_percentiles(iqm(boot, axis=1), conf))
    return out


def _poi_batch(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) + P(X = Y)/2 per bootstrap rep, averaged over tasks; x (B, n, T), y (B, m, T).

    This is the Mann-Whitney U / (n m) that rliable.metrics.probability_of_improvement computes, and computed as
    it does: U = #(x > y) + #(x = y)/2 is exact in floating point, so U / (n m) is the same number bit for bit.
    """
    d = x[:, :, None, :] - y[:, None, :, :]
    u = (d > 0).sum(axis=(1, 2)) + 0.5 * (d == 0).sum(axis=(1, 2))
    return (u / (x.shape[1] * y.shape[1])).mean(axis=-1)


def _poi(x: np.ndarray, y: np.ndarray) -> float:
    """rliable.metrics.probability_of_improvement of (runs, tasks) scores, without a scipy call per task: the
    bootstrap calls it once per rep, which made scipy's input checks 90% of a report's time."""
    if np.isnan(x).any() or np.isnan(y).any():
        return float(_rly_metrics().probability_of_improvement(x, y))
    return float(_poi_batch(x[None], y[None])[0])


def improvement_point(x: Any, y: Any) -> float:
    """P(X > Y) of two 1-d samples without an interval: the Mann-Whitney U / (n m), ties counting half."""
    a, b = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    return float(_poi_batch(a[None, :, None], b[None, :, None])[0])


def probability_of_improvement(
    x: Any,
    y: Any,
    n_boot: int = DEFAULT_N_BOOT,
    conf: float = 0.95,
    seed: int = 0,
) -> Interval:
    """P(X > Y): the probability that a run of X beats a run of Y, with a ``conf`` CI (rliable).

    ``x``, ``y``: scores (num_runs,) or (num_runs, num_tasks), run counts may differ. Ties count
    one half, so identical samples give 0.5 and fully separated ones 1.0 (or 0.0). The CI
    resamples the runs of X and of Y independently within each task (rliable's
    StratifiedIndependentBootstrap). Returns (P, low, high).
    """
    a, b = _as_runs_by_tasks(x), _as_runs_by_tasks(y)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"x and y need the same number of tasks, got {a.shape[1]} and {b.shape[1]}")
    point = _poi(a, b)
    lib = _rliable_library()
    if lib is not None:
        with _seeded_global_numpy(seed):
            _, cis = lib.get_interval_estimates(
                {"x>y": (a, b)}, _poi, method="percentile",
                reps=n_boot, confidence_interval_size=conf)
        ci = np.ravel(cis["x>y"])
        return point, float(ci[0]), float(ci[1])
    rng = np.random.default_rng(seed)
    stats = np.empty(n_boot)
    chunk = max(1, 2_000_000 // max(1, a.size * b.shape[0]))  # bound the (B, n, m, T) temporary
    for start in range(0, n_boot, chunk):
        k = min(chunk, n_boot - start)
        stats[start:start + k] = _poi_batch(_stratified_resample(a, rng, k), _stratified_resample(b, rng, k))
    return (point, *_percentiles(stats, conf))


# ------------------------------------------------------------------------------------ power


def _z(p: float) -> float:
    return float(scipy.stats.norm.ppf(p))


def _z_sum(alpha: float, power: float, sides: str) -> float:
    """z_{1-alpha/2} + z_power for a two-sided test, z_{1-alpha} + z_power for a one-sided one."""
    if sides not in ("two-sided", "one-sided"):
        raise ValueError(f"sides must be 'two-sided' or 'one-sided', not {sides!r}")
    return _z(1 - alpha / 2 if sides == "two-sided" else 1 - alpha) + _z(power)


def minimum_detectable_difference(x: Any, y: Any, alpha: float = 0.05, power: float = 0.8,
                                  sides: str = "two-sided") -> float:
    """Smallest true difference of means that a two-sample test at level ``alpha`` (``sides``: "two-sided" or
    "one-sided", in the direction of the difference) detects with probability ``power``, given the samples'
    spread and sizes.

    Welch / normal approximation: ``(z_{1-alpha/2} + z_{power}) * sqrt(s_x^2/n_x + s_y^2/n_y)`` with sample
    variances (ddof=1), ``z_{1-alpha}`` one-sided. NaN when either sample has fewer than 2 values (no variance).
    """
    a, b = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    z = _z_sum(alpha, power, sides)
    if a.size < 2 or b.size < 2:
        return float("nan")
    se = np.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
    return float(z * se)


def seeds_to_detect(x: Any, y: Any, difference: float, alpha: float = 0.05, power: float = 0.8,
                    sides: str = "two-sided") -> int | None:
    """Seeds per configuration (the same for both) for :func:`minimum_detectable_difference` (at the same
    ``alpha``, ``power`` and ``sides``) to reach ``|difference|``, if the seeds spread as ``x`` and ``y`` do.

    Solves ``(z_{1-alpha/2} + z_{power})^2 (s_x^2 + s_y^2) / n = difference^2`` for n (``z_{1-alpha}``
    one-sided), at least 2. None when ``difference`` is 0 (no number of seeds suffices) or a sample has fewer
    than 2 values.
    """
    a, b = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    z = _z_sum(alpha, power, sides)
    if a.size < 2 or b.size < 2 or not difference or not np.isfinite(difference):
        return None
    n = z ** 2 * (a.var(ddof=1) + b.var(ddof=1)) / difference ** 2
    return max(2, int(np.ceil(n - 1e-9)))  # the tolerance keeps an exact solution from rounding up


# ------------------------------------------------------------------------------------ effect sizes


def mean_difference_ci(x: Any, y: Any, n_boot: int = DEFAULT_N_BOOT, conf: float = 0.95, seed: int = 0) -> Interval:
    """mean(x) - mean(y) with a percentile-bootstrap ``conf`` CI, resampling each sample independently."""
    a, b = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    rng = np.random.default_rng(seed)
    diffs = (a[rng.integers(a.size, size=(n_boot, a.size))].mean(1)
             - b[rng.integers(b.size, size=(n_boot, b.size))].mean(1))
    return (float(a.mean() - b.mean()), *_percentiles(diffs, conf))

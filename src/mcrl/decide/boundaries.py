"""Group-sequential boundaries by numerical integration (Armitage, McPherson and Rowe 1969), with Lan-DeMets
error spending. Pure numpy/scipy.

The canonical joint distribution (Jennison and Turnbull 2000, ch. 3 and 19): at look k the standardised statistic
``Z_k`` has information ``I_k`` (increasing); ``S_k = Z_k sqrt(I_k)`` has independent increments
``S_k - S_{k-1} ~ N(theta (I_k - I_{k-1}), I_k - I_{k-1})``. So ``E[Z_k] = theta sqrt(I_k)`` and
``Corr(Z_j, Z_k) = sqrt(I_j / I_k)``. A rank-sum statistic with tie-corrected variance follows it asymptotically with
``I = n_x n_y / (n_x + n_y + 1)`` (the inverse of the Mann-Whitney probability's null variance, over 12), which
is what `mcrl.decide.look` uses; the plan's simulation checks the error rate on the bimodal finals themselves.

The recursion carries the sub-density of ``Z_k`` on the continuation interval ``(l_k, u_k)`` on a grid (Simpson's
rule) and gets each look's exit probabilities from the normal tail, so a boundary is found by root-finding on an
exit probability, look by look: no closed form is used.

- :func:`spent`: the Lan-DeMets spending functions (Pocock-type, O'Brien-Fleming-type, power family).
- :func:`exit_probabilities`: P(first exit above / below at look k) for given bounds and drift.
- :func:`upper_bounds`: efficacy bounds that spend ``alpha`` under ``theta = 0``, ignoring any futility bound
  (non-binding futility: stopping for futility can only lower the type-I error).
- :func:`lower_bounds`: futility bounds that spend ``beta`` under the planning drift, given the upper bounds; the
  last look's lower bound equals its upper bound.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.optimize import brentq
from scipy.stats import norm

SPENDING = ("pocock", "obrien-fleming", "power")
GRID = 801  # Simpson points per look (odd); the crossing probabilities of the published tables agree to 1e-5
_WIDTH = 10.0  # integrate each sub-density over its mean +- 10 sd at most: the rest is below 1e-22
_HIGH = 40.0  # a bound that nothing crosses (no error spent at a look)


def spent(kind: str, level: float, t: float | np.ndarray, rho: float = 1.0) -> float | np.ndarray:
    """The error spent by information fraction ``t`` (in [0, 1]) of a total ``level`` (one-sided).

    ``pocock``: level ln(1 + (e - 1) t) (Lan and DeMets 1983's Pocock-type); ``obrien-fleming``:
    2 - 2 Phi(z_{1 - level/2} / sqrt t) (their O'Brien-Fleming-type, as gsDesign's sfLDOF); ``power``: level t^rho
    (Kim and DeMets 1987)."""
    t = np.clip(np.asarray(t, dtype=float), 0.0, 1.0)
    if kind == "pocock":
        out = level * np.log1p((math.e - 1.0) * t)
    elif kind == "obrien-fleming":
        with np.errstate(divide="ignore"):
            out = np.where(t > 0, 2.0 - 2.0 * norm.cdf(norm.ppf(1.0 - level / 2.0) / np.sqrt(np.maximum(t, 1e-300))),
                           0.0)
    elif kind == "power":
        out = level * t ** rho
    else:
        raise ValueError(f"spending {kind!r}: choose one of {', '.join(SPENDING)}")
    return float(out) if out.ndim == 0 else out


def _simpson_weights(a: float, b: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    x = np.linspace(a, b, n)
    w = np.ones(n)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return x, w * (b - a) / (3.0 * (n - 1))


class _Recursion:
    """The continuation sub-density of Z_k on a grid, look after look."""

    def __init__(self, info: Sequence[float], theta: float, grid: int = GRID):
        self.info = np.asarray(info, dtype=float)
        if self.info.ndim != 1 or self.info.size == 0 or np.any(self.info <= 0) or np.any(np.diff(self.info) <= 0):
            raise ValueError(f"information must be positive and increasing, got {list(info)}")
        self.theta, self.grid = float(theta), grid | 1
        self.k = 0  # looks passed
        self.x: np.ndarray | None = None  # grid of z at the last look passed
        self.w: np.ndarray | None = None  # Simpson weight x sub-density there

    def _transition(self, k: int) -> tuple[float, float, float]:
        """Z_k = (a x + m) + s N(0,1) given Z_{k-1} = x: (a, m, s)."""
        i0, i1 = self.info[k - 1], self.info[k]
        d = i1 - i0
        return math.sqrt(i0 / i1), self.theta * d / math.sqrt(i1), math.sqrt(d / i1)

    def exits(self, lo: float, hi: float) -> tuple[float, float]:
        """P(continued to this look and Z_k >= hi), P(... and Z_k <= lo) for the next look k."""
        k = self.k
        if k == 0:
            mean = self.theta * math.sqrt(self.info[0])
            return float(norm.sf(hi - mean)), float(norm.cdf(lo - mean))
        a, m, s = self._transition(k)
        mu = a * self.x + m
        return (float(np.dot(self.w, norm.sf((hi - mu) / s))), float(np.dot(self.w, norm.cdf((lo - mu) / s))))

    def advance(self, lo: float, hi: float) -> None:
        """Continue past the next look with continuation interval (lo, hi)."""
        k = self.k
        mean = self.theta * math.sqrt(self.info[k])
        a_, b_ = max(lo, mean - _WIDTH), min(hi, mean + _WIDTH)
        if b_ <= a_:  # nothing continues
            x, w = np.array([mean, mean + 1.0]), np.zeros(2)
        else:
            x, w = _simpson_weights(a_, b_, self.grid)
            if k == 0:
                dens = norm.pdf(x - mean)
            else:
                a, m, s = self._transition(k)
                dens = (norm.pdf((x[:, None] - (a * self.x[None, :] + m)) / s) / s) @ self.w
            w = w * dens
        self.x, self.w, self.k = x, w, k + 1


def exit_probabilities(info: Sequence[float], upper: Sequence[float], lower: Sequence[float] | None = None,
                       theta: float = 0.0, grid: int = GRID) -> tuple[np.ndarray, np.ndarray]:
    """P(the first exit is above ``upper[k]``) and P(... below ``lower[k]``) at each look k, when the drift is
    ``theta`` (E[Z_k] = theta sqrt(I_k)). ``lower`` None: no lower bound (-inf)."""
    rec = _Recursion(info, theta, grid)
    K = len(rec.info)
    lower = [-np.inf] * K if lower is None else list(lower)
    if len(upper) != K or len(lower) != K:
        raise ValueError(f"{K} looks need {K} upper and lower bounds")
    up, down = np.zeros(K), np.zeros(K)
    for k in range(K):
        lo, hi = lower[k], upper[k]
        up[k], down[k] = rec.exits(lo, hi)
        rec.advance(lo, hi)
    return up, down


def _solve(f, target: float) -> float:
    """The bound b with f(b) = target, f decreasing in b from ~1 (b = -40) to ~0 (b = 40)."""
    if target <= f(_HIGH):
        return _HIGH
    if target >= f(-_HIGH):
        return -_HIGH
    return brentq(lambda b: f(b) - target, -_HIGH, _HIGH, xtol=1e-10, rtol=1e-12)


def upper_bounds(info: Sequence[float], info_max: float, level: float, spending: str = "pocock", rho: float = 1.0,
                 grid: int = GRID) -> tuple[np.ndarray, np.ndarray]:
    """Efficacy bounds for looks at ``info`` that spend ``level`` (one-sided) by ``spending`` over the information
    fraction I_k / ``info_max``, under theta = 0 and with no lower bound; and the cumulative error spent at each
    look. A look at or past ``info_max`` spends all that is left."""
    rec = _Recursion(info, 0.0, grid)
    cum = np.asarray([spent(spending, level, min(1.0, i / info_max), rho) for i in rec.info])
    cum = np.maximum.accumulate(cum)
    bounds = np.empty(len(cum))
    done = 0.0
    for k, c in enumerate(cum):
        bounds[k] = _solve(lambda b: rec.exits(-np.inf, b)[0], c - done)
        done += rec.exits(-np.inf, bounds[k])[0]
        rec.advance(-np.inf, bounds[k])
    return bounds, cum


def lower_bounds(info: Sequence[float], info_max: float, upper: Sequence[float], beta: float, theta: float,
                 spending: str = "pocock", rho: float = 1.0, final: bool | None = None,
                 grid: int = GRID) -> np.ndarray:
    """Futility bounds that spend ``beta`` (the chance of stopping for futility when the drift is the planning
    ``theta``) by ``spending`` over I_k / ``info_max``, given the efficacy bounds ``upper``. A lower bound never
    exceeds its upper bound; at the final look (``final``, default: the last look reaches ``info_max``) they
    are equal, so the last look decides."""
    rec = _Recursion(info, theta, grid)
    K = len(rec.info)
    final = rec.info[-1] >= info_max * (1 - 1e-12) if final is None else final
    cum = np.maximum.accumulate(np.asarray([spent(spending, beta, min(1.0, i / info_max), rho) for i in rec.info]))
    lower = np.empty(K)
    done = 0.0
    for k in range(K):
        hi = upper[k]
        if final and k == K - 1:
            lower[k] = hi
        else:
            target = cum[k] - done
            # exits below rise with the bound: solve on the negated bound to reuse the decreasing solver
            lower[k] = min(hi, -_solve(lambda b: rec.exits(-b, hi)[1], target))
        done += rec.exits(lower[k], hi)[1]
        rec.advance(lower[k], hi)
    return lower

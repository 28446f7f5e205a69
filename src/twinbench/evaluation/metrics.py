"""Evaluation statistics: success-rate intervals, Beta posteriors, sim-vs-real agreement (Pearson, MMRV).

Conventions (DESIGN §8): a policy's success rate is k/n over its episodes with status "ok"; intervals
are two-sided at `confidence` (default 0.95). `pearson` and `mmrv` take keyword-only `sim=` and `real=`
because MMRV is not symmetric in its arguments.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import special, stats


@dataclass(frozen=True)
class Estimate:
    """A point estimate with a two-sided interval."""

    value: float
    low: float
    high: float
    confidence: float = 0.95


def _check_counts(k: int, n: int) -> tuple[int, int]:
    if int(n) != n or int(k) != k:
        raise ValueError(f"successes k={k!r} and episodes n={n!r} must be integers")
    k, n = int(k), int(n)
    if n <= 0:
        raise ValueError(f"episodes n={n} must be >= 1: a success rate over no episodes is undefined")
    if not 0 <= k <= n:
        raise ValueError(f"successes k={k} must lie in [0, n={n}]")
    return k, n


def _check_confidence(confidence: float) -> float:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence={confidence!r} must lie strictly between 0 and 1 (e.g. 0.95)")
    return float(confidence)


def success_rate(k: int, n: int) -> float:
    """k / n (n >= 1)."""
    k, n = _check_counts(k, n)
    return k / n


def clopper_pearson(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) interval, via `scipy.stats.binomtest(k, n).proportion_ci`."""
    k, n = _check_counts(k, n)
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=_check_confidence(confidence), method="exact")
    return float(ci.low), float(ci.high)


def wilson(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval (no continuity correction)."""
    k, n = _check_counts(k, n)
    z = stats.norm.ppf(0.5 + _check_confidence(confidence) / 2)
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z / denom * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def jeffreys(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Jeffreys interval: equal-tailed quantiles of Beta(k + 1/2, n - k + 1/2); the lower end is 0 when
    k = 0 and the upper end is 1 when k = n (Brown, Cai & DasGupta 2001)."""
    k, n = _check_counts(k, n)
    alpha = 1.0 - _check_confidence(confidence)
    a, b = k + 0.5, n - k + 0.5
    low = 0.0 if k == 0 else float(stats.beta.ppf(alpha / 2, a, b))
    high = 1.0 if k == n else float(stats.beta.ppf(1 - alpha / 2, a, b))
    return low, high


INTERVALS = {"clopper-pearson": clopper_pearson, "wilson": wilson, "jeffreys": jeffreys}


def rate_estimate(k: int, n: int, method: str = "clopper-pearson", confidence: float = 0.95) -> Estimate:
    """Success rate k/n with its interval (`method` in INTERVALS)."""
    if method not in INTERVALS:
        raise ValueError(f"interval method {method!r} is not one of {sorted(INTERVALS)}")
    low, high = INTERVALS[method](k, n, confidence)
    return Estimate(success_rate(k, n), low, high, confidence)


def _posterior_params(k: int, n: int, what: str = "") -> tuple[int, int]:
    """(1 + k, 1 + n - k): the Beta posterior's parameters under a uniform prior (n = 0 allowed)."""
    if int(n) != n or int(k) != k or not 0 <= k <= n:
        raise ValueError(f"{what}need integers 0 <= k <= n, got k={k!r}, n={n!r}")
    return 1 + int(k), 1 + int(n) - int(k)


def beta_posterior(k: int, n: int):
    """Posterior of the success probability under a uniform prior: a frozen Beta(1 + k, 1 + n - k).

    n = 0 is allowed here (the posterior is then the uniform prior)."""
    return stats.beta(*_posterior_params(k, n))


def prob_greater(k_a: int, n_a: int, k_b: int, n_b: int) -> float:
    """P(p_A > p_B) for independent posteriors p_A ~ Beta(1+k_a, 1+n_a-k_a), p_B ~ Beta(1+k_b, 1+n_b-k_b).

    Exact: with integer Beta parameters, P(X > Y) for X ~ Beta(a1, b1), Y ~ Beta(a2, b2) is the finite sum
    sum_{i=0}^{a1-1} B(a2+i, b1+b2) / ((b1+i) B(1+i, b1) B(a2, b2)), evaluated in log space."""
    a1, b1 = _posterior_params(k_a, n_a, "policy A: ")
    a2, b2 = _posterior_params(k_b, n_b, "policy B: ")
    i = np.arange(a1, dtype=np.float64)
    log_terms = (special.betaln(a2 + i, b1 + b2) - np.log(b1 + i)
                 - special.betaln(1 + i, b1) - special.betaln(a2, b2))
    return float(np.clip(np.exp(special.logsumexp(log_terms)), 0.0, 1.0))


# ---- sim vs real ---------------------------------------------------------------------------------
def _paired(sim, real) -> tuple[np.ndarray, np.ndarray]:
    s = np.asarray(sim, dtype=np.float64)
    r = np.asarray(real, dtype=np.float64)
    if s.ndim != 1 or r.ndim != 1 or s.shape != r.shape:
        raise ValueError(f"sim and real must be 1-D arrays of the same length (one value per policy), "
                         f"got shapes {s.shape} and {r.shape}")
    if s.size == 0:
        raise ValueError("sim and real are empty: need at least one policy (n = 0 is undefined)")
    if not (np.isfinite(s).all() and np.isfinite(r).all()):
        raise ValueError("sim and real must be finite (no NaN/inf)")
    return s, r


@dataclass(frozen=True)
class PearsonResult:
    """Pearson r over paired success rates with its Fisher-z interval."""

    r: float
    low: float
    high: float
    n: int
    confidence: float = 0.95


def pearson(*, sim: Sequence[float], real: Sequence[float], confidence: float = 0.95,
            controls: int = 0) -> PearsonResult:
    """Pearson correlation of paired (sim, real) success rates with a Fisher-z interval
    tanh(atanh(r) -+ z_{1-alpha/2} / sqrt(n - 3 - controls)).

    `controls`: how many variables were partialled out of both vectors before (a partial correlation, e.g.
    rates centred per group: one fewer than the groups), each costing the interval a degree of freedom.
    Raises ValueError for n - controls < 3 (r is +-1 or undefined, no information) and for a constant
    vector (r is 0/0, undefined: e.g. every policy at 100% in sim). At n - controls = 3 the interval is
    (-1, 1)."""
    s, r = _paired(sim, real)
    conf = _check_confidence(confidence)
    if controls < 0:
        raise ValueError(f"controls={controls} must be >= 0")
    n = s.size - controls
    if n < 3:
        raise ValueError(f"Pearson r needs at least 3 paired policies"
                         f"{f' beyond the {controls} variables partialled out' if controls else ''}, "
                         f"got {s.size}")
    for name, v in (("sim", s), ("real", r)):
        if np.ptp(v) == 0:
            raise ValueError(f"Pearson r is undefined: all {name} values equal {v[0]:g} (zero variance)")
    ds, dr = s - s.mean(), r - r.mean()
    rho = float(np.clip(np.dot(ds, dr) / np.sqrt(np.dot(ds, ds) * np.dot(dr, dr)), -1.0, 1.0))
    if n == 3:
        return PearsonResult(rho, -1.0, 1.0, s.size, conf)
    if abs(rho) == 1.0:
        return PearsonResult(rho, rho, rho, s.size, conf)
    z, half = np.arctanh(rho), stats.norm.ppf(0.5 + conf / 2) / np.sqrt(n - 3)
    return PearsonResult(rho, float(np.tanh(z - half)), float(np.tanh(z + half)), s.size, conf)


def _mmrv_batch(s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """MMRV for a batch: s, r of shape (B, N) -> (B,)."""
    # wrong[b, i, j]: the pair (i, j) is ranked differently by sim and real (strict comparisons)
    wrong = (s[:, :, None] > s[:, None, :]) != (r[:, :, None] > r[:, None, :])
    viol = np.abs(r[:, :, None] - r[:, None, :]) * wrong
    return viol.max(axis=2).mean(axis=1)  # an empty max (no violation) counts 0


def mmrv(*, sim: Sequence[float], real: Sequence[float]) -> float:
    """Mean Maximum Rank Violation (DESIGN §8), S = sim, R = real:
    (1/N) sum_i max_j |R_i - R_j| * 1[(S_i > S_j) != (R_i > R_j)]; 0 means the rankings agree."""
    s, r = _paired(sim, real)
    return float(_mmrv_batch(s[None], r[None])[0])


def _outcome_arrays(outcomes, name: str) -> list[np.ndarray]:
    arrs = []
    for i, o in enumerate(outcomes):
        a = np.asarray(o, dtype=np.float64).ravel()
        if a.size == 0:
            raise ValueError(f"{name}[{i}] has no episodes; every policy needs at least one")
        if not np.isin(a, (0.0, 1.0)).all():
            raise ValueError(f"{name}[{i}] must hold episode outcomes 0/1 (or booleans)")
        arrs.append(a)
    return arrs


def _resampled_rates(arrs: list[np.ndarray], n_boot: int, rng: np.random.Generator) -> np.ndarray:
    out = np.empty((n_boot, len(arrs)))
    for i, a in enumerate(arrs):
        idx = rng.integers(0, a.size, size=(n_boot, a.size))
        out[:, i] = a[idx].mean(axis=1)
    return out


def mmrv_bootstrap(*, sim: Sequence[Sequence[float]], real: Sequence[Sequence[float]],
                   n_boot: int = 2000, confidence: float = 0.95, seed: int = 0) -> Estimate:
    """MMRV of per-policy success rates with a percentile bootstrap interval.

    `sim[i]` / `real[i]` hold policy i's episode outcomes (0/1) in each domain. Each bootstrap replicate
    resamples episodes with replacement within each policy and domain (seeded, reproducible): the
    interval is the range of the MMRV that a second evaluation with as many episodes would measure if the
    measured rates were the true ones (the reports' "re-run range"). Noise only adds rank violations where
    the rankings agree, so it can lie above the value; it is not a confidence interval for the MMRV of the
    true rates."""
    return mean_mmrv_bootstrap([(sim, real)], n_boot=n_boot, confidence=confidence, seed=seed)


def mean_mmrv_bootstrap(groups: Sequence[tuple[Sequence[Sequence[float]], Sequence[Sequence[float]]]], *,
                        n_boot: int = 2000, confidence: float = 0.95, seed: int = 0) -> Estimate:
    """The mean over groups of each group's MMRV (policies ranked only against the others of their group,
    e.g. of one workcell) with a percentile bootstrap interval; `groups[g]` = (sim, real) as
    `mmrv_bootstrap` takes them. Each replicate resamples episodes within each group, policy and domain."""
    if not groups:
        raise ValueError("no groups: need at least one (sim, real) pair of outcome lists")
    arrays = []
    for g, (sim, real) in enumerate(groups):
        where = f" of group {g}" if len(groups) > 1 else ""
        s_arr = _outcome_arrays(sim, f"sim{where}")
        r_arr = _outcome_arrays(real, f"real{where}")
        if len(s_arr) != len(r_arr) or not s_arr:
            raise ValueError(f"sim and real{where} need the same non-zero number of policies, got "
                             f"{len(s_arr)} and {len(r_arr)}")
        arrays.append((s_arr, r_arr))
    if n_boot < 1:
        raise ValueError(f"n_boot={n_boot} must be >= 1")
    conf = _check_confidence(confidence)
    value = float(np.mean([mmrv(sim=[a.mean() for a in s], real=[a.mean() for a in r]) for s, r in arrays]))
    rng = np.random.default_rng(seed)
    boots = []
    for start in range(0, n_boot, 500):  # chunks bound the (B, N, N) temporaries
        b = min(500, n_boot - start)
        boots.append(np.mean([_mmrv_batch(_resampled_rates(s, b, rng), _resampled_rates(r, b, rng))
                              for s, r in arrays], axis=0))
    boot = np.concatenate(boots)
    low, high = np.quantile(boot, [(1 - conf) / 2, (1 + conf) / 2])
    return Estimate(value, float(low), float(high), conf)

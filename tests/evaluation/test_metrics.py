"""Statistics against published values, hand-computed cases and brute-force references."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import integrate, stats

from twinbench.evaluation.metrics import (
    beta_posterior,
    clopper_pearson,
    jeffreys,
    mean_mmrv_bootstrap,
    mmrv,
    mmrv_bootstrap,
    pearson,
    prob_greater,
    rate_estimate,
    success_rate,
    wilson,
)


# ---- binomial intervals: published values ---------------------------------------------------------
def test_clopper_pearson_published():
    # k=3, n=10 -> [0.0667, 0.6525] (value given in the project brief; it is R's `binom.test(3, 10)` interval,
    # Clopper & Pearson 1934, reproduced by scipy to 1e-8)
    assert clopper_pearson(3, 10) == pytest.approx((0.0667, 0.6525), abs=5e-5)
    # R documentation example `binom.test(9, 24, 1/6)` prints "95 percent confidence interval:
    # 0.1879929 0.5940636" (https://rdrr.io/r/stats/binom.test.html example output)
    assert clopper_pearson(9, 24) == pytest.approx((0.1879929, 0.5940636), abs=1e-7)
    # k = 0 and k = n: closed forms (alpha/2)^(1/n) (Clopper & Pearson 1934)
    assert clopper_pearson(0, 10) == pytest.approx((0.0, 1 - 0.025 ** 0.1), abs=1e-9)
    assert clopper_pearson(10, 10) == pytest.approx((0.025 ** 0.1, 1.0), abs=1e-9)


def test_wilson_published():
    # k=3, n=10 -> [0.1078, 0.6032] (Wilson 1927 formula; same as scipy's binomtest(..., method="wilson"))
    assert wilson(3, 10) == pytest.approx((0.1078, 0.6032), abs=5e-5)
    ref = stats.binomtest(3, 10).proportion_ci(method="wilson")
    assert wilson(3, 10) == pytest.approx((ref.low, ref.high), abs=1e-12)
    # Code Golf SE "Compute the Wilson score interval" test cases (computed with z = 1.96 exactly,
    # we use z = 1.959964, hence 1e-4): (nS, nF) = (1, 10), (10, 90), (50, 50), (0, 100)
    cases = {(1, 10): (0.016231752262825982, 0.3773646254862038),
             (10, 90): (0.05522854161313612, 0.1743673043676654),
             (50, 50): (0.40382982859014716, 0.5961701714098528),
             (0, 100): (0.0, 0.03699480747600191)}
    for (ns, nf), want in cases.items():
        assert wilson(ns, ns + nf) == pytest.approx(want, abs=1e-4)


def test_jeffreys_published_and_conventions():
    # R package RSurveillance, `binom.jeffreys(25, 200)` documented output: 0.08462743 0.176126;
    # `binom.jeffreys(10, 200)`: 0.02599340 0.08687509 (https://rdrr.io/cran/RSurveillance/man/binom.jeffreys.html)
    assert jeffreys(25, 200) == pytest.approx((0.08462743, 0.176126), abs=1e-6)
    assert jeffreys(10, 200) == pytest.approx((0.02599340, 0.08687509), abs=1e-7)
    # k=3, n=10: Beta(3.5, 7.5) 2.5%/97.5% quantiles are [0.0927, 0.6058] (checked by integrating the
    # density below). The brief's [0.0873, 0.6066] does not match these quantiles.
    low, high = jeffreys(3, 10)
    assert (low, high) == pytest.approx((0.0927, 0.6058), abs=5e-5)
    pdf = stats.beta(3.5, 7.5).pdf
    assert integrate.quad(pdf, 0, low)[0] == pytest.approx(0.025, abs=1e-9)
    assert integrate.quad(pdf, high, 1)[0] == pytest.approx(0.025, abs=1e-9)
    # endpoint conventions (Brown, Cai & DasGupta 2001): 0 at k = 0, 1 at k = n
    assert jeffreys(0, 10)[0] == 0.0 and jeffreys(0, 10)[1] == pytest.approx(stats.beta.ppf(0.975, 0.5, 10.5))
    assert jeffreys(10, 10)[1] == 1.0


def test_intervals_contain_estimate_and_shrink():
    for k, n in [(0, 5), (1, 5), (5, 5), (7, 20), (50, 100)]:
        p = success_rate(k, n)
        for f in (clopper_pearson, wilson, jeffreys):
            lo, hi = f(k, n)
            assert 0.0 <= lo <= p <= hi <= 1.0
            lo99, hi99 = f(k, n, confidence=0.99)
            assert lo99 <= lo and hi <= hi99
    # Clopper-Pearson is the widest of the three at k=3, n=10 (it is conservative)
    w = {f.__name__: np.diff(f(3, 10))[0] for f in (clopper_pearson, wilson, jeffreys)}
    assert w["clopper_pearson"] > w["wilson"] and w["clopper_pearson"] > w["jeffreys"]
    est = rate_estimate(3, 10, method="wilson")
    assert (est.value, est.low, est.high) == pytest.approx((0.3, 0.1078, 0.6032), abs=5e-5)


def test_intervals_refuse_bad_counts():
    for f in (clopper_pearson, wilson, jeffreys, success_rate):
        with pytest.raises(ValueError, match="n=0"):
            f(0, 0)
        with pytest.raises(ValueError, match="k=11"):
            f(11, 10)
    with pytest.raises(ValueError, match="confidence"):
        wilson(1, 2, confidence=95)
    with pytest.raises(ValueError, match="interval method"):
        rate_estimate(1, 2, method="wald")


# ---- posteriors -------------------------------------------------------------------------------------
def test_beta_posterior():
    post = beta_posterior(3, 10)
    assert post.args == (4, 8)
    assert post.mean() == pytest.approx(4 / 12)
    assert beta_posterior(0, 0).pdf(0.3) == pytest.approx(1.0)  # uniform prior
    with pytest.raises(ValueError, match="k=11, n=10"):
        beta_posterior(11, 10)
    with pytest.raises(ValueError, match="k=1.5"):
        beta_posterior(1.5, 3)
    with pytest.raises(ValueError, match="policy A: .*k=3, n=2"):
        prob_greater(3, 2, 1, 2)
    with pytest.raises(ValueError, match="policy B: .*k=-1"):
        prob_greater(1, 2, -1, 2)


def _prob_greater_quad(k_a, n_a, k_b, n_b):
    a, b = beta_posterior(k_a, n_a), beta_posterior(k_b, n_b)
    return integrate.quad(lambda x: a.pdf(x) * b.cdf(x), 0, 1, limit=200, epsabs=1e-12)[0]


def test_prob_greater_exact():
    # equal counts: 1/2 by symmetry; A=1/1 vs B=0/1: posteriors Beta(2,1) vs Beta(1,2) -> 5/6
    assert prob_greater(3, 10, 3, 10) == pytest.approx(0.5, abs=1e-12)
    assert prob_greater(1, 1, 0, 1) == pytest.approx(5 / 6, abs=1e-12)
    assert prob_greater(0, 0, 0, 0) == pytest.approx(0.5, abs=1e-12)
    for ka, na, kb, nb in [(7, 10, 3, 10), (15, 16, 9, 16), (0, 20, 1, 20), (120, 200, 100, 180)]:
        p = prob_greater(ka, na, kb, nb)
        assert p == pytest.approx(_prob_greater_quad(ka, na, kb, nb), abs=1e-9)
        assert p + prob_greater(kb, nb, ka, na) == pytest.approx(1.0, abs=1e-12)
    # seeded Monte Carlo agrees within 5 standard errors
    rng = np.random.default_rng(0)
    m = 200_000
    mc = np.mean(rng.beta(8, 4, m) > rng.beta(4, 8, m))
    assert abs(prob_greater(7, 10, 3, 10) - mc) < 5 * np.sqrt(mc * (1 - mc) / m)


# ---- Pearson ---------------------------------------------------------------------------------------
def test_pearson_matches_scipy_fisher_interval():
    x = [0.1, 0.4, 0.35, 0.8, 0.7, 0.95]
    y = [0.0, 0.5, 0.2, 0.6, 0.9, 0.85]
    res = pearson(sim=x, real=y)
    ref = stats.pearsonr(x, y)
    ci = ref.confidence_interval(0.95)
    assert res.r == pytest.approx(ref.statistic, abs=1e-12)
    assert (res.low, res.high) == pytest.approx((ci.low, ci.high), abs=1e-12)
    # hand case: x = (1, 2, 3, 4), y = (1, 3, 2, 4): r = 0.8, Fisher interval tanh(atanh(0.8) -+ 1.96)
    res = pearson(sim=[1, 2, 3, 4], real=[1, 3, 2, 4])
    assert res.r == pytest.approx(0.8)
    z = stats.norm.ppf(0.975)
    assert (res.low, res.high) == pytest.approx((np.tanh(np.arctanh(0.8) - z), np.tanh(np.arctanh(0.8) + z)))
    assert pearson(sim=[0, 1, 2, 3], real=[3, 2, 1, 0]).r == pytest.approx(-1.0)
    three = pearson(sim=[0, 1, 2], real=[0, 2, 1])
    assert three.r == pytest.approx(0.5) and (three.low, three.high) == (-1.0, 1.0)


def test_pearson_refuses_undefined():
    with pytest.raises(ValueError, match="at least 3"):
        pearson(sim=[0.1, 0.2], real=[0.3, 0.4])
    with pytest.raises(ValueError, match="all sim values equal 1"):
        pearson(sim=[1.0, 1.0, 1.0, 1.0], real=[0.2, 0.5, 0.4, 0.9])
    with pytest.raises(ValueError, match="all real values"):
        pearson(sim=[0.1, 0.5, 0.4, 0.9], real=[0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="same length"):
        pearson(sim=[0.1, 0.5, 0.4], real=[0.0, 0.1])
    with pytest.raises(TypeError):
        pearson([0.1, 0.5, 0.4], [0.0, 0.1, 0.3])  # keyword-only


# ---- MMRV ------------------------------------------------------------------------------------------
def _mmrv_loops(sim, real):
    n = len(sim)
    total = 0.0
    for i in range(n):
        worst = 0.0
        for j in range(n):
            if (sim[i] > sim[j]) != (real[i] > real[j]):
                worst = max(worst, abs(real[i] - real[j]))
        total += worst
    return total / n


def test_mmrv_hand_cases():
    # identical rankings -> 0
    assert mmrv(sim=[0.1, 0.5, 0.9], real=[0.2, 0.3, 0.8]) == 0.0
    # one swapped pair: S = (0.2, 0.4), R = (0.9, 0.6): both i=0 and i=1 see |0.9-0.6| = 0.3 -> 0.3
    assert mmrv(sim=[0.2, 0.4], real=[0.9, 0.6]) == pytest.approx(0.3)
    # S = (0.1, 0.5, 0.9), R = (0.5, 0.2, 0.8): pair (0,1) violated, |R0-R1| = 0.3;
    # i=0: 0.3, i=1: 0.3, i=2: 0 -> 0.6/3 = 0.2
    assert mmrv(sim=[0.1, 0.5, 0.9], real=[0.5, 0.2, 0.8]) == pytest.approx(0.2)
    # a single policy: empty max counts 0
    assert mmrv(sim=[0.3], real=[0.7]) == 0.0


def test_mmrv_ties_and_constant_vectors():
    # tie in sim, not in real: (S0 > S1) = False, (R0 > R1) = True -> violation for i=0 only
    # (for i=1: S1 > S0 False, R1 > R0 False -> agree). MMRV = (0.4 + 0) / 2 = 0.2
    assert mmrv(sim=[0.5, 0.5], real=[0.8, 0.4]) == pytest.approx(0.2)
    # ties in both: no violation
    assert mmrv(sim=[0.5, 0.5], real=[0.3, 0.3]) == 0.0
    # constant sim against spread real: every i with some R_i > R_j is violated (max |R_i - R_j|
    # over j with R_j < R_i): R = (0.1, 0.4, 0.9) -> (0, 0.3, 0.8) -> mean 11/30
    assert mmrv(sim=[0.7, 0.7, 0.7], real=[0.1, 0.4, 0.9]) == pytest.approx(1.1 / 3)
    # constant real: |R_i - R_j| = 0 everywhere -> 0
    assert mmrv(sim=[0.1, 0.4, 0.9], real=[0.6, 0.6, 0.6]) == 0.0


def test_mmrv_asymmetric():
    # swapping sim and real changes the value: violations are weighted by real differences
    s, r = [0.1, 0.5, 0.9], [0.5, 0.2, 0.8]
    assert mmrv(sim=s, real=r) == pytest.approx(0.2)
    assert mmrv(sim=r, real=s) == pytest.approx((0.4 + 0.4 + 0.0) / 3)  # |S0 - S1| = 0.4 now weights
    # constant sim vs spread real is 11/30, the swap is 0
    assert mmrv(sim=[0.7] * 3, real=[0.1, 0.4, 0.9]) != mmrv(sim=[0.1, 0.4, 0.9], real=[0.7] * 3)


def test_mmrv_matches_brute_force_on_random_cases():
    rng = np.random.default_rng(1)
    for _ in range(50):
        n = int(rng.integers(1, 8))
        s = rng.integers(0, 5, n) / 4  # coarse values produce many ties
        r = rng.integers(0, 5, n) / 4
        assert mmrv(sim=s, real=r) == pytest.approx(_mmrv_loops(s, r), abs=1e-12)


def test_mmrv_refuses_bad_input():
    with pytest.raises(ValueError, match="n = 0"):
        mmrv(sim=[], real=[])
    with pytest.raises(ValueError, match="same length"):
        mmrv(sim=[0.1, 0.2], real=[0.1])
    with pytest.raises(ValueError, match="finite"):
        mmrv(sim=[0.1, np.nan], real=[0.1, 0.2])
    with pytest.raises(TypeError):
        mmrv([0.1], [0.2])


def test_mmrv_bootstrap():
    sim = [[1, 1, 1, 0], [1, 0, 0, 0, 0], [1, 1, 1, 1, 1, 0]]
    real = [[1, 0, 0], [1, 1, 0, 1], [1, 1, 1, 1]]
    est = mmrv_bootstrap(sim=sim, real=real, n_boot=1000, seed=3)
    want = mmrv(sim=[np.mean(a) for a in sim], real=[np.mean(a) for a in real])
    assert est.value == pytest.approx(want)
    assert 0.0 <= est.low <= est.high <= 1.0
    assert est == mmrv_bootstrap(sim=sim, real=real, n_boot=1000, seed=3)  # seeded
    # brute force replicate 0 of the chunked, vectorised bootstrap: same generator draws
    rng = np.random.default_rng(3)
    s0 = [np.asarray(a, float)[rng.integers(0, len(a), size=(1, len(a)))].mean() for a in sim]
    r0 = [np.asarray(a, float)[rng.integers(0, len(a), size=(1, len(a)))].mean() for a in real]
    one = mmrv_bootstrap(sim=sim, real=real, n_boot=1, seed=3)
    assert one.low == pytest.approx(_mmrv_loops(s0, r0)) and one.high == one.low
    # deterministic outcomes (every episode identical within a policy): no resampling spread
    det = mmrv_bootstrap(sim=[[1, 1], [0, 0, 0]], real=[[0, 0], [1]], n_boot=200)
    assert det.value == det.low == det.high == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no episodes"):
        mmrv_bootstrap(sim=[[1], []], real=[[1], [0]])
    with pytest.raises(ValueError, match="0/1"):
        mmrv_bootstrap(sim=[[0.5]], real=[[1]])
    with pytest.raises(ValueError, match="same non-zero number"):
        mmrv_bootstrap(sim=[], real=[])


def test_mmrv_range_is_that_of_a_rerun_with_the_measured_rates_as_truth():
    """What the reports call MMRV's "re-run range": evaluations simulated from scratch, each policy's
    outcomes drawn as Bernoulli trials at its measured rate, give the bootstrap's quantiles (Monte Carlo
    error only). With rankings that agree (MMRV 0) noise can only add violations: the range lies above."""
    sim = [[1] * 7 + [0], [1] * 5 + [0] * 3, [1] * 3 + [0] * 5, [1] + [0] * 7, [0] * 8]
    real = [[1] * 8, [1] * 6 + [0] * 2, [1] * 4 + [0] * 4, [1] * 2 + [0] * 6, [1] + [0] * 7]
    est = mmrv_bootstrap(sim=sim, real=real, n_boot=4000, seed=1)
    rng = np.random.default_rng(7)
    ps, pr = np.mean(sim, axis=1), np.mean(real, axis=1)
    reruns = [_mmrv_loops(rng.binomial(8, ps) / 8, rng.binomial(8, pr) / 8) for _ in range(4000)]
    low, high = np.quantile(reruns, [0.025, 0.975])
    assert est.value == 0.0 and est.low == pytest.approx(low, abs=0.02)
    assert est.high == pytest.approx(high, abs=0.03) and est.high > 0.1


def test_partial_pearson_over_groups():
    # rates centred per group are the residuals of a regression on group indicators: r of those residuals
    # is the partial correlation, its Fisher interval with n - 3 - (groups - 1) degrees of freedom
    rng = np.random.default_rng(5)
    g = np.repeat([0, 1, 2], 6)
    x = rng.random(18) + g
    y = x + rng.normal(0, 0.3, 18) - 2 * g
    dummies = np.eye(3)[g]
    rx = x - dummies @ np.linalg.lstsq(dummies, x, rcond=None)[0]
    ry = y - dummies @ np.linalg.lstsq(dummies, y, rcond=None)[0]
    res = pearson(sim=rx, real=ry, controls=2)
    want = float(np.corrcoef(rx, ry)[0, 1])
    half = stats.norm.ppf(0.975) / np.sqrt(18 - 3 - 2)
    assert res.r == pytest.approx(want) and res.n == 18
    assert (res.low, res.high) == pytest.approx((np.tanh(np.arctanh(want) - half),
                                                 np.tanh(np.arctanh(want) + half)))
    assert pearson(sim=rx, real=ry, controls=2).high > pearson(sim=rx, real=ry).high  # wider
    assert (pearson(sim=[0, 1, 2, 4], real=[0, 2, 1, 4], controls=1).low, ) == (-1.0, )  # 3 left
    with pytest.raises(ValueError, match="beyond the 2 variables"):
        pearson(sim=[0, 1, 2, 4], real=[0, 2, 1, 4], controls=2)
    with pytest.raises(ValueError, match="controls"):
        pearson(sim=[0, 1, 2, 4], real=[0, 2, 1, 4], controls=-1)


def test_mean_mmrv_bootstrap_over_groups():
    a = ([[1, 1, 1, 0], [1, 0, 0, 0, 0], [1, 1, 1, 1, 1, 0]], [[1, 0, 0], [1, 1, 0, 1], [1, 1, 1, 1]])
    b = ([[0, 0], [1, 1]], [[1, 1], [0, 0]])  # ranked backwards, no episode spread: MMRV 1 in every replicate
    one = mean_mmrv_bootstrap([a], n_boot=300, seed=2)
    assert one == mmrv_bootstrap(sim=a[0], real=a[1], n_boot=300, seed=2)  # one group: the same draws
    both = mean_mmrv_bootstrap([a, b], n_boot=300, seed=2)
    assert both.value == pytest.approx((one.value + 1.0) / 2)  # policies ranked within their group only
    # the replicates: (group a's replicate + 1) / 2, so the interval is a's, mapped; a's draws come first in
    # each chunk and b draws the same amount, so chunk 1 (< 500) matches a alone
    assert (both.low, both.high) == pytest.approx(((one.low + 1) / 2, (one.high + 1) / 2))
    det = mean_mmrv_bootstrap([b, ([[1, 1], [0]], [[1], [0, 0]])], n_boot=50)
    assert det.value == det.low == det.high == pytest.approx(0.5)
    with pytest.raises(ValueError, match="no groups"):
        mean_mmrv_bootstrap([])
    with pytest.raises(ValueError, match="sim and real of group 1 need"):
        mean_mmrv_bootstrap([a, ([[1]], [[1], [0]])])


def test_mmrv_zero_iff_rankings_agree_exhaustive():
    # over all small rate vectors: MMRV = 0 exactly when no pair with different real values is
    # ordered differently by sim
    vals = [0.0, 0.5, 1.0]
    for s in itertools.product(vals, repeat=3):
        for r in itertools.product(vals, repeat=3):
            agree = all(not ((s[i] > s[j]) != (r[i] > r[j]) and r[i] != r[j])
                        for i in range(3) for j in range(3))
            assert (mmrv(sim=s, real=r) == 0.0) == agree

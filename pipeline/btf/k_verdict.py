"""Does k change the error? The clustered runs as a blocked design: seeds are blocks.

A seed gives every k the same initialisation, batch order and k-means seed, so runs of one
seed share an effect; a one-way test over k would count it as noise. Here, for the seeds
run at every k (complete blocks):

- two-way ANOVA without interaction, RMSE ~ k + seed (the test of k);
- Friedman's rank test over the same blocks (a sign test with two values of k), the check
  that does not assume normal errors; its p is exact (:func:`friedman_p`) where that is
  cheap, which covers the few-seed designs where the chi-square is conservative (3 seeds
  ranking 3 k alike: exact 1/36 = 0.028, chi-square 0.0498);
- the trend of RMSE against log2 k within seeds (slope per doubling of k, 95 % CI);
- the effect of each step of the k grid, corrected for the steps tested together
  (:class:`Step`);
- the smallest step effect these runs detect with 80 % power, and the seeds needed to
  detect a difference of ``target`` (:data:`PAPER_LARGEST_K_STEP`) of the mean RMSE.

scipy has the distributions and Friedman's chi-square test, but no two-way ANOVA and no
Holm adjustment; statsmodels (which has both) would be a new dependency for a few sums of
squares of a balanced design and a few lines of step-down adjustment, written out here.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from pipeline.btf import paper

POWER = 0.8
# The paper's largest step between two k (fabric02, k = 500 -> 1000: 5.7 % of k = 500's
# RMSE). Not its largest clustering penalty (+4.4 %, k = 500 over the Neural BTF), which is
# no step between k and must not be compared with one (pipeline.btf.paper).
PAPER_LARGEST_K_STEP = round(paper.largest_k_step(), 3)
# Rank-sum states x block orderings over all blocks, above which Friedman's exact p gives
# way to the chi-square (its time at this bound: docs/performance.md).
EXACT_MAX_WORK = 2_000_000


@dataclass(frozen=True)
class Step:
    """The step from ``k_from`` to the next k of the grid, ``k_to``: the difference of means,
    t-tested on the ANOVA's residual variance.

    The family is the m = (number of k) - 1 adjacent steps. ``p_holm`` is the Holm-Bonferroni
    adjusted p (family-wise error <= alpha). The intervals of Holm's step-down procedure
    (the i-th smallest p at level alpha / (m - i + 1)) are not simultaneous confidence
    intervals: their levels depend on the data's ordering of the p-values. So the adjusted
    interval is Bonferroni's, at level 1 - alpha / m for each step, which covers all m
    differences at once with probability >= 1 - alpha. A step can have Holm p < alpha and a
    Bonferroni interval that touches zero (Holm is the more powerful test); the p decides.
    ``ci`` and ``p`` are the unadjusted ones, for a reader who tests one step alone.
    """

    k_from: int
    k_to: int
    diff: float  # mean RMSE at k_to minus mean RMSE at k_from (the unadjusted estimate)
    mean_from: float  # mean RMSE at k_from, the reference of ``relative``
    p: float  # two-sided t test of diff = 0, unadjusted
    p_holm: float
    ci: tuple[float, float]  # 1 - alpha, unadjusted
    ci_bonferroni: tuple[float, float]  # 1 - alpha / m for this step, simultaneous 1 - alpha

    @property
    def relative(self) -> float:
        """The step as a fraction of the mean RMSE at the smaller k (``k_from``)."""
        return self.diff / self.mean_from


@dataclass
class Verdict:
    ks: list[int]
    seeds: int
    p_anova: float
    p_rank: float
    rank_test: str  # "Friedman" or, for two values of k, "sign test"
    rank_method: str  # how p_rank was computed: "exact" or "chi-square"
    slope: float  # RMSE per doubling of k, within seeds
    slope_ci: tuple[float, float]
    p_trend: float
    steps: list[Step]  # adjacent steps of the k grid, ascending k
    k_means: list[float]
    mean_rmse: float
    detectable_step: float  # smallest step difference a single t test detects, 80 % power
    seeds_needed: int  # to detect target x mean RMSE with 80 % power
    alpha: float = 0.05  # the level of every interval above


def blocked_verdict(
    table: pd.DataFrame, alpha: float = 0.05, target: float = PAPER_LARGEST_K_STEP
) -> Verdict:
    """The tests and effects of k on a blocked table of RMSE.

    Parameters
    ----------
    table : DataFrame of shape (seeds, n_k)
        RMSE with one row per seed (block) and one column per k (distinct positive
        integers, any order: the columns are sorted by k), complete (no missing cells), at
        least 2 seeds and 2 values of k.
    alpha : level of the intervals (1 - alpha) and of the family-wise error of the steps.
    target : the relative difference (of the mean RMSE) for ``seeds_needed``.
    """
    if table.shape[0] < 2 or table.shape[1] < 2 or table.isna().to_numpy().any():
        raise ValueError(
            f"need a complete table of >= 2 seeds x >= 2 k values, got "
            f"{table.shape} with {int(table.isna().to_numpy().sum())} missing"
        )
    ks = [int(k) for k in table.columns]
    if min(ks) <= 0 or len(set(ks)) != len(ks):
        raise ValueError(f"k values must be distinct positive integers, got {ks}")
    table = table.sort_index(axis=1)
    ks = sorted(ks)
    y = table.to_numpy(dtype=float)
    s, n_k = y.shape
    grand = y.mean()
    k_means, seed_means = y.mean(0), y.mean(1)
    ss_k = s * np.sum((k_means - grand) ** 2)
    ss_seed = n_k * np.sum((seed_means - grand) ** 2)
    ss_err = max(np.sum((y - grand) ** 2) - ss_k - ss_seed, 0.0)
    df_k, df_err = n_k - 1, (n_k - 1) * (s - 1)
    var_err = ss_err / df_err
    p_anova = _f_test(ss_k / df_k, var_err, df_k, df_err)
    if n_k >= 3:
        (p_rank, rank_method), rank_test = friedman_p(y), "Friedman"
    else:
        wins = int(np.sum(y[:, 1] < y[:, 0]))
        ties = int(np.sum(y[:, 1] == y[:, 0]))
        p_rank = stats.binomtest(wins, s - ties).pvalue if s > ties else 1.0
        rank_test, rank_method = "sign test", "exact"
    # Trend against log2 k within seeds: centre RMSE per seed and log2 k over the grid.
    x = np.log2(np.asarray(ks, dtype=float))
    xc = np.broadcast_to(x - x.mean(), y.shape)
    yc = y - seed_means[:, None]
    sxx = np.sum(xc**2)
    slope = np.sum(xc * yc) / sxx
    df_trend = y.size - s - 1
    resid = yc - slope * xc
    se_slope = np.sqrt(np.sum(resid**2) / df_trend / sxx) if df_trend > 0 else np.nan
    t_trend = stats.t.ppf(1 - alpha / 2, df_trend) if df_trend > 0 else np.nan
    p_trend = (
        2 * stats.t.sf(abs(slope / se_slope), df_trend)
        if df_trend > 0 and se_slope > 0
        else (0.0 if slope != 0 else 1.0)
    )
    steps = _steps(ks, k_means, var_err, s, df_err, alpha)
    t_err = stats.t.ppf(1 - alpha / 2, df_err)
    detectable = (t_err + stats.t.ppf(POWER, df_err)) * np.sqrt(2 * var_err / s)
    return Verdict(
        ks,
        s,
        p_anova,
        float(p_rank),
        rank_test,
        rank_method,
        slope,
        (slope - t_trend * se_slope, slope + t_trend * se_slope),
        p_trend,
        steps,
        list(k_means),
        grand,
        detectable,
        seeds_needed(var_err, target * grand, n_k, alpha),
        alpha,
    )


def _steps(
    ks: list[int], k_means: np.ndarray, var_err: float, s: int, df_err: int, alpha: float
) -> list[Step]:
    """Adjacent steps: t tests on the ANOVA's residual variance, Holm p, Bonferroni CI."""
    m = len(ks) - 1
    diffs = np.diff(k_means)
    se = np.sqrt(2 * var_err / s)  # a balanced design: every step has the same error
    if se > 0:
        p = 2 * stats.t.sf(np.abs(diffs) / se, df_err)
    else:  # no residual noise: any difference is certain
        p = np.where(diffs != 0, 0.0, 1.0)
    p_holm = holm(p)
    half = stats.t.ppf(1 - alpha / 2, df_err) * se
    half_bonferroni = stats.t.ppf(1 - alpha / (2 * m), df_err) * se
    return [
        Step(
            ks[i],
            ks[i + 1],
            float(d),
            float(k_means[i]),
            float(p[i]),
            float(p_holm[i]),
            (float(d - half), float(d + half)),
            (float(d - half_bonferroni), float(d + half_bonferroni)),
        )
        for i, d in enumerate(diffs)
    ]


def holm(p: np.ndarray) -> np.ndarray:
    """Holm-Bonferroni adjusted p-values, in the order given (statsmodels'
    ``multipletests(method="holm")``): the i-th smallest of m p-values becomes max over
    j <= i of min(1, (m - j + 1) p_(j))."""
    p = np.asarray(p, dtype=float)
    order = np.argsort(p, kind="stable")
    scaled = (p.size - np.arange(p.size)) * p[order]
    adjusted = np.empty_like(p)
    adjusted[order] = np.minimum(np.maximum.accumulate(scaled), 1.0)
    return adjusted


def friedman_p(y: np.ndarray, max_work: int = EXACT_MAX_WORK) -> tuple[float, str]:
    """Friedman's p for ``y`` of shape (blocks, treatments): ``(p, "exact")`` when
    :func:`friedman_exact_p` is cheap enough, else ``(p, "chi-square")`` from scipy (its
    statistic with mid-ranks and the tie correction)."""
    exact = friedman_exact_p(y, max_work)
    if exact is not None:
        return exact, "exact"
    p = stats.friedmanchisquare(*np.asarray(y, dtype=float).T).pvalue
    return (1.0 if np.isnan(p) else float(p)), "chi-square"  # nan: every block all tied


def friedman_exact_p(y: np.ndarray, max_work: int = EXACT_MAX_WORK) -> float | None:
    """The exact permutation p of Friedman's test, or None when it would cost more than
    ``max_work`` (rank-sum states x distinct orderings of a block, summed over blocks).

    Parameters
    ----------
    y : array of shape (b, k)
        b blocks (rows) of k treatments, k >= 2.

    Under H0 each block's ranks are a uniformly random ordering of its observed ranks,
    independently across blocks; p is the share of the (k!)^b configurations whose
    statistic is >= the observed one. Ties within a block get mid-ranks and stay tied in
    every ordering, so scipy's tie correction (a factor fixed by the ties) does not change
    the ordering of the statistics: this is the conditional (permutation) test of scipy's
    statistic. Any statistic of the form a + c sum_j R_j^2 orders like sum_j R_j^2 of the
    rank sums R_j, which is what is compared, in doubled ranks (integers: exact).

    The distribution of the rank-sum vector is built block by block (a convolution), each
    vector sorted (the distribution is exchangeable across treatments: k! times fewer
    states). The same p as scipy's ``permutation_test(..., permutation_type="samples",
    n_resamples=np.inf)``, which enumerates all (k!)^b configurations (6^10 = 6e7 for 3 k
    and 10 seeds) where this costs (states x k!) per block.

    >>> round(36 * friedman_exact_p(np.array([[3.0, 2.0, 1.0]] * 3)), 9)  # 6 of 6^3 tie it
    1.0
    """
    ranks = np.rint(2 * stats.rankdata(y, axis=1)).astype(np.int64)  # doubled mid-ranks
    b, k = ranks.shape
    # A state (a sorted vector of doubled rank sums, each <= 2 k b) is keyed by one integer,
    # its digits in base 2 k b + 1, for a fast np.unique.
    base = 2 * k * b + 1
    if math.factorial(k) > max_work or base**k >= 2**63:
        return None
    digits = base ** np.arange(k, dtype=np.int64)
    observed = np.sum(ranks.sum(0) ** 2)
    orderings = np.array(list(itertools.permutations(range(k))))
    states, prob = np.zeros((1, k), dtype=np.int64), np.ones(1)
    work = 0
    for block in ranks:
        perms, counts = np.unique(block[orderings], axis=0, return_counts=True)
        work += len(states) * len(perms)
        if work > max_work:
            return None
        sums = np.sort((states[:, None, :] + perms[None, :, :]).reshape(-1, k), axis=1)
        weights = (prob[:, None] * (counts / len(orderings))[None, :]).ravel()
        _, first, inverse = np.unique(sums @ digits, return_index=True, return_inverse=True)
        states = sums[first]
        prob = np.bincount(inverse, weights=weights, minlength=len(states))
    return float(min(prob[np.sum(states**2, axis=1) >= observed].sum(), 1.0))


def seeds_needed(var_err: float, difference: float, n_k: int, alpha: float = 0.05) -> int:
    """Seeds for a step difference of ``difference`` to be detected with 80 % power (t
    quantiles of the blocked design's residual degrees of freedom)."""
    if difference <= 0:
        return 0
    if var_err == 0:
        return 2
    for s in range(2, 10_000):
        df = (n_k - 1) * (s - 1)
        t_sum = stats.t.ppf(1 - alpha / 2, df) + stats.t.ppf(POWER, df)
        if t_sum * np.sqrt(2 * var_err / s) <= difference:
            return s
    return 10_000


def _f_test(mean_square: float, var_err: float, df: int, df_err: int) -> float:
    if var_err == 0:
        return 0.0 if mean_square > 0 else 1.0
    return float(stats.f.sf(mean_square / var_err, df, df_err))


def describe(
    v: Verdict, alpha: float = 0.05, target: float = PAPER_LARGEST_K_STEP
) -> dict[str, str]:
    """One table row: the tests, the effects with their intervals, and the verdict.

    A column per step, ``"500 → 1000 [95 % CI, Bonferroni]"``: the difference of means, its
    Bonferroni interval, the difference as a percentage of the mean RMSE at the smaller k,
    and the unadjusted and Holm-adjusted p (:class:`Step`).
    """
    level = f"{100 * (1 - v.alpha):g} %"
    row = {
        "k values": ", ".join(map(str, v.ks)),
        "seeds (blocks)": str(v.seeds),
        "two-way ANOVA p (k | seed)": f"{v.p_anova:.3g}",
        f"{v.rank_test} p ({v.rank_method})": f"{v.p_rank:.3g}",
        f"trend per doubling of k [{level} CI]": (
            f"{v.slope:+.5f} [{v.slope_ci[0]:+.5f}, {v.slope_ci[1]:+.5f}], p={v.p_trend:.3g}"
        ),
    }
    for step in v.steps:
        low, high = step.ci_bonferroni
        row[f"{step.k_from} → {step.k_to} [{level} CI, Bonferroni]"] = (
            f"{step.diff:+.5f} [{low:+.5f}, {high:+.5f}] ({100 * step.relative:+.1f} % of "
            f"k = {step.k_from}); p={step.p:.3g}, Holm p={step.p_holm:.3g}"
        )
    if v.p_anova < alpha:
        best = v.ks[int(np.argmin(v.k_means))]
        row["verdict"] = (
            f"k changes the RMSE beyond seed noise (two-way ANOVA p="
            f"{v.p_anova:.3g} < {alpha}); lowest mean at k = {best}"
        )
    else:
        row["verdict"] = (
            f"no evidence that k changes the RMSE (p={v.p_anova:.3g} >= {alpha}); these runs "
            f"detect a step of {v.detectable_step:.5f} ({v.detectable_step * 100 / v.mean_rmse:.1f}"
            f" % of the mean RMSE) with 80 % power; {v.seeds_needed} seeds would detect "
            f"{100 * target:g} %"
        )
    return row

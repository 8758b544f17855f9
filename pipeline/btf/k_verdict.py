"""Does k change the error? The clustered runs as a blocked design: seeds are blocks.

A seed gives every k the same initialisation, batch order and k-means seed, so runs of one
seed share an effect; a one-way test over k would count it as noise. Here, for the seeds
run at every k (complete blocks):

- two-way ANOVA without interaction, RMSE ~ k + seed (the test of k);
- Friedman's rank test over the same blocks (a sign test with two values of k), the check
  that does not assume normal errors;
- the trend of RMSE against log2 k within seeds (slope per doubling of k, 95 % CI);
- the effect of each step of the k grid (difference of means, 95 % CI from the ANOVA's
  residual variance);
- the smallest step effect these runs detect with 80 % power, and the seeds needed to
  detect a difference of ``target`` (4.4 %, the paper's largest) of the mean RMSE.

scipy has the distributions and Friedman's test, but no two-way ANOVA; statsmodels would be
a new dependency for a few sums of squares of a balanced design, written out here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

POWER = 0.8


@dataclass
class Verdict:
    ks: list[int]
    seeds: int
    p_anova: float
    p_rank: float
    rank_test: str
    slope: float  # RMSE per doubling of k, within seeds
    slope_ci: tuple[float, float]
    p_trend: float
    steps: list[tuple[int, int, float, float, float]]  # k_from, k_to, diff, ci_low, ci_high
    k_means: list[float]
    mean_rmse: float
    detectable_step: float  # smallest step difference detected with 80 % power
    seeds_needed: int  # to detect target x mean RMSE with 80 % power


def blocked_verdict(table: pd.DataFrame, alpha: float = 0.05, target: float = 0.044) -> Verdict:
    """``table``: RMSE with one row per seed (block) and one column per k, complete (no
    missing cells), at least 2 seeds and 2 values of k."""
    y = table.to_numpy(dtype=float)
    s, n_k = y.shape
    if s < 2 or n_k < 2 or np.isnan(y).any():
        raise ValueError(f"need a complete table of >= 2 seeds x >= 2 k values, got {y.shape}")
    grand = y.mean()
    k_means, seed_means = y.mean(0), y.mean(1)
    ss_k = s * np.sum((k_means - grand) ** 2)
    ss_seed = n_k * np.sum((seed_means - grand) ** 2)
    ss_err = max(np.sum((y - grand) ** 2) - ss_k - ss_seed, 0.0)
    df_k, df_err = n_k - 1, (n_k - 1) * (s - 1)
    var_err = ss_err / df_err
    p_anova = _f_test(ss_k / df_k, var_err, df_k, df_err)
    if n_k >= 3:
        p_rank, rank_test = stats.friedmanchisquare(*y.T).pvalue, "Friedman"
    else:
        wins = int(np.sum(y[:, 1] < y[:, 0]))
        ties = int(np.sum(y[:, 1] == y[:, 0]))
        p_rank = stats.binomtest(wins, s - ties).pvalue if s > ties else 1.0
        rank_test = "sign test"
    if np.isnan(p_rank):  # every seed ranks the k values alike and tied
        p_rank = 1.0
    # Trend against log2 k within seeds: centre RMSE per seed and log2 k over the grid.
    x = np.log2(np.asarray(table.columns, dtype=float))
    xc = np.broadcast_to(x - x.mean(), y.shape)
    yc = y - seed_means[:, None]
    sxx = np.sum(xc**2)
    slope = np.sum(xc * yc) / sxx
    df_trend = y.size - s - 1
    resid = yc - slope * xc
    se_slope = np.sqrt(np.sum(resid**2) / df_trend / sxx) if df_trend > 0 else np.nan
    t_trend = stats.t.ppf(1 - alpha / 2, df_trend) if df_trend > 0 else np.nan
    p_trend = (2 * stats.t.sf(abs(slope / se_slope), df_trend)
               if df_trend > 0 and se_slope > 0 else (0.0 if slope != 0 else 1.0))
    # Steps of the grid: difference of k means, standard error from the residual variance.
    t_err = stats.t.ppf(1 - alpha / 2, df_err)
    se_step = np.sqrt(2 * var_err / s)
    ks = [int(k) for k in table.columns]
    steps = [(ks[i], ks[i + 1], k_means[i + 1] - k_means[i],
              k_means[i + 1] - k_means[i] - t_err * se_step,
              k_means[i + 1] - k_means[i] + t_err * se_step) for i in range(n_k - 1)]
    detectable = (t_err + stats.t.ppf(POWER, df_err)) * se_step
    return Verdict(ks, s, p_anova, float(p_rank), rank_test, slope,
                   (slope - t_trend * se_slope, slope + t_trend * se_slope), p_trend, steps,
                   list(k_means), grand, detectable,
                   seeds_needed(var_err, target * grand, n_k, alpha))


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


def describe(v: Verdict, alpha: float = 0.05, target: float = 0.044) -> dict[str, str]:
    """One table row: the tests, the effects with their intervals, and the verdict."""
    pct = 100 / v.mean_rmse
    steps = "; ".join(f"{a}→{b}: {d:+.5f} [{lo:+.5f}, {hi:+.5f}] ({d * pct:+.1f} %)"
                      for a, b, d, lo, hi in v.steps)
    row = {
        "k values": ", ".join(map(str, v.ks)),
        "seeds (blocks)": str(v.seeds),
        "two-way ANOVA p (k | seed)": f"{v.p_anova:.3g}",
        f"{v.rank_test} p": f"{v.p_rank:.3g}",
        "trend per doubling of k [95 % CI]": (f"{v.slope:+.5f} [{v.slope_ci[0]:+.5f}, "
                                               f"{v.slope_ci[1]:+.5f}], p={v.p_trend:.3g}"),
        "step effects [95 % CI]": steps,
    }
    if v.p_anova < alpha:
        best = v.ks[int(np.argmin(v.k_means))]
        row["verdict"] = (f"k changes the RMSE beyond seed noise (two-way ANOVA p="
                          f"{v.p_anova:.3g} < {alpha}); lowest mean at k = {best}")
    else:
        row["verdict"] = (
            f"no evidence that k changes the RMSE (p={v.p_anova:.3g} >= {alpha}); these runs "
            f"detect a step of {v.detectable_step:.5f} ({v.detectable_step * pct:.1f} % of the "
            f"mean) with 80 % power; {v.seeds_needed} seeds would detect {100 * target:g} %")
    return row

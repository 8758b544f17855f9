"""The k verdict as a blocked design (pipeline/btf/k_verdict.py), on hand-made RMSE tables."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from pipeline.btf.k_verdict import (
    blocked_verdict,
    describe,
    friedman_exact_p,
    friedman_p,
    holm,
    seeds_needed,
)

KS = [500, 1000, 2000]


def _table(rng, seeds=4, step=0.0, seed_sd=0.003, noise_sd=0.0002, base=0.03):
    """RMSE[seed, k] = base + a shared seed effect + step per k + noise."""
    seed_effect = rng.normal(0, seed_sd, size=(seeds, 1))
    k_effect = step * np.arange(len(KS))
    values = base + seed_effect + k_effect + rng.normal(0, noise_sd, size=(seeds, len(KS)))
    return pd.DataFrame(values, columns=KS)


def test_a_consistent_k_effect_under_a_shared_seed_effect_is_found():
    """A one-way test drowns the effect in the seed spread; the blocked one finds it."""
    table = _table(np.random.default_rng(0), step=-0.0005, seed_sd=0.004, noise_sd=0.0001)
    assert stats.f_oneway(*table.T.to_numpy()).pvalue > 0.3
    verdict = blocked_verdict(table)
    assert verdict.p_anova < 0.001 and verdict.p_rank < 0.05
    assert verdict.slope < 0 and verdict.slope_ci[1] < 0
    assert all(step.ci_bonferroni[1] < 0 and step.p_holm < 0.05 for step in verdict.steps)
    assert describe(verdict)["verdict"].startswith("k changes the RMSE")
    assert "lowest mean at k = 2000" in describe(verdict)["verdict"]


def test_without_an_effect_the_test_rejects_at_about_its_nominal_rate():
    rng = np.random.default_rng(1)
    p = np.array([blocked_verdict(_table(rng)).p_anova for _ in range(400)])
    assert 0.02 <= np.mean(p < 0.05) <= 0.09


def test_the_anova_matches_a_regression_on_k_and_seed_dummies():
    """Cross-check: the F test of the k dummies in a least-squares fit with seed dummies."""
    table = _table(np.random.default_rng(2), step=-0.0002)
    y = table.to_numpy().ravel()
    seeds, n_k = table.shape
    seed_d = np.repeat(np.eye(seeds), n_k, axis=0)
    k_d = np.tile(np.eye(n_k)[:, 1:], (seeds, 1))
    full, reduced = np.hstack([seed_d, k_d]), seed_d
    rss = [np.sum((y - x @ np.linalg.lstsq(x, y, rcond=None)[0]) ** 2) for x in (full, reduced)]
    df_err = y.size - full.shape[1]
    f = ((rss[1] - rss[0]) / (n_k - 1)) / (rss[0] / df_err)
    assert blocked_verdict(table).p_anova == pytest.approx(stats.f.sf(f, n_k - 1, df_err))


def test_no_evidence_reports_the_detectable_step_and_the_seeds_needed():
    verdict = blocked_verdict(_table(np.random.default_rng(3), seeds=2, noise_sd=0.002))
    text = describe(verdict)["verdict"]
    assert text.startswith("no evidence") and "seeds would detect 5.7 %" in text
    assert verdict.detectable_step > 0 and verdict.seeds_needed > 2


def test_more_noise_needs_more_seeds():
    assert seeds_needed(1e-6, 0.001, 3) < seeds_needed(4e-6, 0.001, 3)


def test_two_values_of_k_use_the_sign_test():
    table = pd.DataFrame(
        {
            500: [0.03, 0.031, 0.029, 0.032, 0.030, 0.028],
            1000: [0.029, 0.030, 0.028, 0.031, 0.029, 0.027],
        }
    )
    verdict = blocked_verdict(table)
    assert (verdict.rank_test, verdict.rank_method) == ("sign test", "exact")
    assert verdict.p_rank == pytest.approx(2 * 0.5**6)


def test_an_incomplete_table_is_refused():
    with pytest.raises(ValueError, match="complete table"):
        blocked_verdict(pd.DataFrame({500: [0.03]}))


def test_a_table_with_k_columns_out_of_order_is_sorted_and_bad_k_values_refused():
    table = _table(np.random.default_rng(4), step=-0.0005)
    shuffled = blocked_verdict(table[[2000, 500, 1000]])
    assert shuffled.ks == KS and shuffled.steps == blocked_verdict(table).steps
    with pytest.raises(ValueError, match=r"distinct positive integers, got \[500, 500\]"):
        blocked_verdict(pd.DataFrame([[0.03, 0.02], [0.03, 0.02]], columns=[500, 500]))
    with pytest.raises(ValueError, match="distinct positive"):
        blocked_verdict(pd.DataFrame([[0.03, 0.02], [0.03, 0.02]], columns=[0, 500]))


# Friedman's test: exact p from the permutation distribution, chi-square when too costly.


@pytest.mark.parametrize(
    ("blocks", "p"),
    [
        ([[1, 2, 3]] * 3, 6 / 216),  # the 6 of 6^3 orderings where all blocks agree: 1/36
        ([[1, 2, 3]] * 2, 6 / 36),
        ([[1, 2, 3], [3, 2, 1]], 1.0),  # equal rank sums: the smallest statistic there is
        # Ties, by hand: block 1 has 3 distinct orderings (the 2 at any place) of 6, block 2
        # has 6; the statistic is largest, as observed, when both put their top rank in the
        # same place: 3 x 2 of 18.
        ([[1, 1, 2], [1, 2, 3]], 1 / 3),
    ],
)
def test_the_exact_friedman_p_of_small_tables_worked_by_hand(blocks, p):
    assert friedman_exact_p(np.array(blocks, dtype=float)) == pytest.approx(p, rel=1e-12)


@pytest.mark.parametrize(
    ("blocks", "chi2", "p"),
    [
        ([[1, 2, 3]] * 3, 6.0, 0.028),
        ([[1, 2, 3]] * 2 + [[1, 3, 2]], 4.667, 0.194),
        ([[1, 2, 3]] * 3 + [[2, 1, 3]], 6.5, 0.042),
        ([[1, 2, 3]] * 4, 8.0, 0.0046),
        ([[1, 2, 3, 4]] * 2, 6.0, 0.042),
        ([[1, 2, 3, 4]] * 2 + [[2, 1, 3, 4]], 8.2, 0.017),
        ([[1, 2, 3, 4]] * 3, 9.0, 0.0017),
    ],
)
def test_the_exact_friedman_p_matches_the_published_table(blocks, chi2, p):
    """Friedman (1937) and Siegel's Nonparametric Statistics (1956), Table N: the exact
    probability of a chi-square_r at least this large, three or two decimals."""
    y = np.array(blocks, dtype=float)
    assert stats.friedmanchisquare(*y.T).statistic == pytest.approx(chi2, abs=5e-4)
    assert friedman_exact_p(y) == pytest.approx(p, abs=0.5 * 10 ** -len(f"{p}".split(".")[1]))


@pytest.mark.parametrize(
    ("blocks", "k", "seed"), [(2, 3, 0), (3, 3, 1), (4, 3, 2), (3, 4, 3), (2, 5, 4), (5, 3, 5)]
)
def test_the_exact_friedman_p_matches_a_brute_force_enumeration(blocks, k, seed):
    """scipy's permutation test enumerates all (k!)^b orderings of the values within the
    blocks and computes scipy's statistic (tie correction included) on each; values on a
    coarse grid make ties within blocks."""
    y = np.random.default_rng(seed).integers(0, 4, size=(blocks, k)).astype(float)
    y[0] = np.arange(k)  # no block all tied in every row

    def statistic(*samples, axis):
        return stats.friedmanchisquare(*samples, axis=axis).statistic

    brute = stats.permutation_test(
        tuple(y.T),
        statistic,
        permutation_type="samples",
        n_resamples=np.inf,
        alternative="greater",
        vectorized=True,
    )
    assert brute.null_distribution.size == np.prod(np.arange(1, k + 1)) ** blocks
    assert friedman_exact_p(y) == pytest.approx(brute.pvalue, rel=1e-9)


def test_the_exact_friedman_p_with_two_k_is_the_sign_test():
    """With two treatments Friedman's statistic is (wins - losses)^2 up to a factor, and
    tied blocks add nothing: the exact p is the two-sided binomial p of the untied blocks."""
    rng = np.random.default_rng(6)
    for _ in range(10):
        y = rng.integers(0, 3, size=(9, 2)).astype(float)
        wins, untied = int(np.sum(y[:, 1] < y[:, 0])), int(np.sum(y[:, 1] != y[:, 0]))
        sign = stats.binomtest(wins, untied).pvalue if untied else 1.0
        assert friedman_exact_p(y) == pytest.approx(sign, rel=1e-12)


def test_the_exact_friedman_p_converges_to_the_chi_square_p_with_many_blocks():
    """With 3 blocks the chi-square p is far from the exact one; with 100, close."""

    def largest_gap(blocks):
        rng = np.random.default_rng(blocks)
        gaps = []
        for _ in range(5):
            y = rng.normal(size=(blocks, 3)) + np.arange(3) / np.sqrt(blocks)
            gaps.append(abs(friedman_exact_p(y) - stats.friedmanchisquare(*y.T).pvalue))
        return max(gaps)

    assert largest_gap(4) > 0.1
    assert largest_gap(100) < 0.02


def test_a_costly_exact_friedman_p_falls_back_to_the_chi_square():
    y = np.random.default_rng(7).normal(size=(4, 8))  # (8!)^4 orderings
    assert friedman_exact_p(y) is None
    p, method = friedman_p(y)
    assert method == "chi-square" and p == stats.friedmanchisquare(*y.T).pvalue
    assert friedman_p(y[:, :3]) == (pytest.approx(friedman_exact_p(y[:, :3])), "exact")
    assert friedman_p(y[:, :3], max_work=10)[1] == "chi-square"


def test_the_verdict_reports_the_exact_friedman_p_and_says_so():
    """Three seeds ranking three k alike: exact 1/36, where the chi-square gives 0.0498."""
    table = pd.DataFrame(
        [[0.031, 0.028, 0.026], [0.033, 0.030, 0.029], [0.030, 0.027, 0.025]], columns=KS
    )
    verdict = blocked_verdict(table)
    assert (verdict.rank_test, verdict.rank_method) == ("Friedman", "exact")
    assert verdict.p_rank == pytest.approx(1 / 36)
    assert stats.friedmanchisquare(*table.to_numpy().T).pvalue == pytest.approx(0.0498, abs=1e-4)
    assert describe(verdict)["Friedman p (exact)"] == "0.0278"
    wide = pd.DataFrame(np.random.default_rng(8).normal(size=(4, 8)), columns=range(1, 9))
    assert "Friedman p (chi-square)" in describe(blocked_verdict(wide))


# The steps of the k grid: Holm-adjusted p, Bonferroni intervals, relative to the smaller k.


@pytest.mark.parametrize(
    ("p", "adjusted"),
    [
        ([0.01, 0.04, 0.03], [0.03, 0.06, 0.06]),  # 3 x 0.01; 2 x 0.03; max(0.06, 1 x 0.04)
        ([0.5, 0.6], [1.0, 1.0]),  # 2 x 0.5, capped; then max(1.0, 0.6)
        ([0.02], [0.02]),
    ],
)
def test_holm_adjusts_p_values_worked_by_hand(p, adjusted):
    assert holm(np.array(p)) == pytest.approx(adjusted)


def _hand_table(c=0.0003):
    """k means 0.030, 0.027, 0.0243 (two steps of -10 % of the smaller k), seed effects,
    and residuals c x [[1, -1, 0], [-1, 1, 0], [0, 0, 0]] (rows and columns sum to 0): the
    residual variance is 4 c^2 / 4 degrees of freedom = c^2."""
    means = np.array([0.030, 0.027, 0.0243])
    residual = c * np.array([[1, -1, 0], [-1, 1, 0], [0, 0, 0]])
    seed_effect = np.array([[0.002], [-0.001], [-0.001]])
    return pd.DataFrame(means + seed_effect + residual, columns=KS)


def test_the_steps_worked_by_hand():
    c = 0.0003
    verdict = blocked_verdict(_hand_table(c))
    se = c * np.sqrt(2 / 3)  # sqrt(2 var / seeds)
    t = np.array([-0.003, -0.0027]) / se
    p = 2 * stats.t.sf(np.abs(t), 4)
    for step, d, p_step, p_holm in zip(
        verdict.steps, [-0.003, -0.0027], p, [2 * p[0], max(2 * p[0], p[1])], strict=True
    ):
        assert step.diff == pytest.approx(d) and step.relative == pytest.approx(-0.1)
        assert step.p == pytest.approx(p_step) and step.p_holm == pytest.approx(p_holm)
        half, half_bonferroni = stats.t.ppf(0.975, 4) * se, stats.t.ppf(1 - 0.05 / 4, 4) * se
        assert step.ci == pytest.approx((d - half, d + half))
        assert step.ci_bonferroni == pytest.approx((d - half_bonferroni, d + half_bonferroni))
    assert [(s.k_from, s.k_to, s.mean_from) for s in verdict.steps] == [
        (500, 1000, pytest.approx(0.030)),
        (1000, 2000, pytest.approx(0.027)),
    ]


def test_the_steps_match_a_regression_on_k_and_seed_dummies():
    """Cross-check: each step is a contrast of the k coefficients of a least-squares fit
    with seed dummies; its standard error from the fit's covariance gives the t test, the
    Bonferroni interval, and (over the two steps) Holm's p."""
    table = _table(np.random.default_rng(9), step=-0.0002)
    y = table.to_numpy().ravel()
    seeds, n_k = table.shape
    x = np.hstack([np.repeat(np.eye(seeds), n_k, axis=0), np.tile(np.eye(n_k)[:, 1:], (seeds, 1))])
    beta, rss = np.linalg.lstsq(x, y, rcond=None)[:2]
    df_err = y.size - x.shape[1]
    cov = rss[0] / df_err * np.linalg.inv(x.T @ x)
    contrasts = np.zeros((2, x.shape[1]))
    contrasts[0, seeds] = 1  # k = 1000 - k = 500
    contrasts[1, seeds:] = [-1, 1]  # k = 2000 - k = 1000
    diff = contrasts @ beta
    se = np.sqrt(np.einsum("ij,jk,ik->i", contrasts, cov, contrasts))
    p = 2 * stats.t.sf(np.abs(diff / se), df_err)
    half = stats.t.ppf(1 - 0.05 / 4, df_err) * se
    steps = blocked_verdict(table).steps
    assert [s.diff for s in steps] == pytest.approx(diff)
    assert [s.p for s in steps] == pytest.approx(p)
    assert [s.p_holm for s in steps] == pytest.approx(
        [min(1, 2 * p.min()) if q == p.min() else max(min(1, 2 * p.min()), q) for q in p]
    )
    assert [s.ci_bonferroni for s in steps] == [
        pytest.approx((d - h, d + h)) for d, h in zip(diff, half, strict=True)
    ]


def test_with_two_k_the_bonferroni_interval_is_the_plain_one():
    table = pd.DataFrame({500: [0.030, 0.031, 0.029], 1000: [0.029, 0.0295, 0.028]})
    (step,) = blocked_verdict(table).steps
    assert step.ci_bonferroni == step.ci and step.p_holm == step.p


def test_describe_names_what_each_column_is():
    verdict = blocked_verdict(_hand_table())
    row = describe(verdict)
    assert list(row) == [
        "k values",
        "seeds (blocks)",
        "two-way ANOVA p (k | seed)",
        "Friedman p (exact)",
        "trend per doubling of k [95 % CI]",
        "500 → 1000 [95 % CI, Bonferroni]",
        "1000 → 2000 [95 % CI, Bonferroni]",
        "verdict",
    ]
    first, second = verdict.steps
    assert row["500 → 1000 [95 % CI, Bonferroni]"] == (
        f"-0.00300 [{first.ci_bonferroni[0]:+.5f}, {first.ci_bonferroni[1]:+.5f}] "
        f"(-10.0 % of k = 500); p={first.p:.3g}, Holm p={first.p_holm:.3g}"
    )
    # Relative to the smaller k's mean, not to the grand mean (0.02743: -10.9 %, -9.8 %).
    assert "(-10.0 % of k = 1000)" in row["1000 → 2000 [95 % CI, Bonferroni]"]
    assert "-10.9" not in str(row) and "-9.8" not in str(row)
    assert "[90 % CI, Bonferroni]" in " ".join(describe(blocked_verdict(_hand_table(), alpha=0.1)))

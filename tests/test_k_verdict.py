"""The k verdict as a blocked design (pipeline/btf/k_verdict.py), on hand-made RMSE tables."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from pipeline.btf.k_verdict import blocked_verdict, describe, seeds_needed

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
    assert all(hi < 0 for _, _, _, _, hi in verdict.steps)
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
    assert text.startswith("no evidence") and "seeds would detect 4.4 %" in text
    assert verdict.detectable_step > 0 and verdict.seeds_needed > 2


def test_more_noise_needs_more_seeds():
    assert seeds_needed(1e-6, 0.001, 3) < seeds_needed(4e-6, 0.001, 3)


def test_two_values_of_k_use_the_sign_test():
    table = pd.DataFrame({500: [0.03, 0.031, 0.029, 0.032, 0.030, 0.028],
                          1000: [0.029, 0.030, 0.028, 0.031, 0.029, 0.027]})
    verdict = blocked_verdict(table)
    assert verdict.rank_test == "sign test"
    assert verdict.p_rank == pytest.approx(2 * 0.5**6)


def test_an_incomplete_table_is_refused():
    with pytest.raises(ValueError, match="complete table"):
        blocked_verdict(pd.DataFrame({500: [0.03]}))

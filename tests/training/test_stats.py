import math

import pytest

from training.stats import wilson_interval


@pytest.mark.parametrize(
    ("successes", "trials", "low", "high"),
    [(25, 50, 0.3664, 0.6336), (50, 50, 0.9287, 1.0), (0, 50, 0.0, 0.0713), (14, 20, 0.4810, 0.8545)],
)
def test_wilson_interval_matches_the_score_formula(successes, trials, low, high):
    assert wilson_interval(successes, trials) == pytest.approx((low, high), abs=1e-4)


def test_the_interval_narrows_with_more_trials_and_holds_the_rate():
    for trials in (10, 100, 1000):
        low, high = wilson_interval(trials * 7 // 10, trials)
        assert low < 0.7 < high
    assert wilson_interval(700, 1000)[1] - wilson_interval(700, 1000)[0] < wilson_interval(7, 10)[1] - wilson_interval(7, 10)[0]


def test_no_trials_and_impossible_counts():
    assert all(math.isnan(x) for x in wilson_interval(0, 0))
    with pytest.raises(ValueError, match="successes=3"):
        wilson_interval(3, 2)

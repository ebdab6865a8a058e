"""Wilson intervals and outcome summaries used by demo and evaluation."""

import numpy as np
import pytest

from policy.training.rollout import EpisodeResult, summarize, wilson_interval


@pytest.mark.parametrize(
    ("k", "n", "lo", "hi"),
    [
        (0, 10, 0.0, 0.2775),
        (5, 10, 0.2366, 0.7634),
        (10, 10, 0.7225, 1.0),
        (80, 100, 0.7112, 0.8666),
    ],
)
def test_wilson_interval_known_values(k, n, lo, hi):
    a, b = wilson_interval(k, n)
    assert a == pytest.approx(lo, abs=1e-3) and b == pytest.approx(hi, abs=1e-3)


def test_summarize_counts_each_outcome():
    z = np.zeros((2, 3))
    results = [EpisodeResult(i, o, 10 * (i + 1), 1.0, 5.0, z, z[0], z[0])
               for i, o in enumerate(["success", "success", "collision", "timeout"])]
    s = summarize(results)
    assert s["episodes"] == 4
    assert s["success_rate"] == 0.5 and s["collision_rate"] == 0.25 and s["timeout_rate"] == 0.25
    assert s["mean_steps"] == 25.0
    assert s["success_ci95"][0] < 0.5 < s["success_ci95"][1]

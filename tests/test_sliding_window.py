"""The sliding window: each window's past marginalized into a prior on the next one's first
keys, and the windows before following what the next one moved, give the log solved as one
window (to the linearization's error) — no seams."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from estimator.batch import estimate
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.settings import Settings

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def short_log():
    config = load_config(ROOT / "configs" / "single_joint.toml")
    log = read_log(ROOT / "recordings" / "single_joint.mcap", config)
    t0 = min(int(m.t_ns[0]) for m in log.measurements.values() if len(m))
    cut = {}
    for name, m in log.measurements.items():  # the log's first 0.8 s
        keep = (m.t_ns >= t0) & (m.t_ns <= t0 + 800_000_000)
        cut[name] = replace(
            m, t_ns=m.t_ns[keep], log_time_ns=m.log_time_ns[keep], values=m.values[keep]
        )
    settings = replace(
        Settings.from_config(config), init="measurements", fit_softness="none", tolerance=1e-6
    )
    whole, _ = estimate(config, cut, replace(settings, window_s=10.0))
    return config, cut, settings, whole


def _swept(short_log, backward_s: float):
    config, cut, settings, whole = short_log
    est, summary = estimate(
        config, cut, replace(settings, window_s=0.25, overlap_s=0.05, backward_s=backward_s)
    )
    assert summary.windows >= 4
    near = np.zeros(est.T, bool)
    for k in summary.window_starts[1:]:
        near[k - 3 : k + 4] = True
    gap = np.abs(est.qacc - whole.qacc).max(axis=1)  # rad/s², against the one-window solve
    return est, gap[near].max(), gap[~near][3:-3].max()


def test_the_sweep_is_the_one_window_solve_without_seams(short_log):
    *_, whole = short_log
    est, at_joins, elsewhere = _swept(short_log, backward_s=30.0)
    # the same trajectory to far below the mocap's σ (5e-4 m at a 0.2 m arm: 2.5e-3 rad)
    assert np.abs(est.qpos - whole.qpos).max() < 2e-5
    assert at_joins < 2 * elsewhere  # the joins differ no more than the rest
    _, no_pass, _ = _swept(short_log, backward_s=0.0)
    assert no_pass > 2 * at_joins  # without the backward pass, they do


def test_a_quiet_join_avoids_an_impact():
    """join = "quiet" hands over at the key of least jerk among the candidates: away from a
    jump in acceleration (an impact) by more than the knots the marginal prior summarizes."""
    from estimator.factors.base import Block
    from estimator.solver.window import quietest_join

    K, nv, span = 100, 4, 4
    a = np.zeros((K, nv))
    a[60:, :] = 50.0  # an impact between knots 60 and 61 (row i is knot i + 1)
    prior = Block("prior", a / 200.0, None, np.zeros(K), np.ones((K, nv), bool), dofwise=True)
    join = quietest_join([prior], 200.0, range(50, 80), span)
    assert abs(join - 61) > span + 1 and join == 79  # the latest of the quiet keys
    # every candidate within reach of the impact: no quieter one, the latest
    assert quietest_join([prior], 200.0, range(55, 66), span) == 65


def test_a_slice_of_the_log_is_swept_in_the_logs_windows(short_log):
    """Windows hand over at anchors on the log's knot clock: a slice that starts anywhere (a
    chunk of `estimate --chunk`) joins the whole log's windows at its first hand-over, and
    from there gives its estimate."""
    from estimator.knots import knot_grid

    config, cut, settings, _ = short_log
    settings = replace(settings, window_s=0.25, overlap_s=0.05)
    knots = knot_grid(cut, settings.h or config.load_model().opt.timestep)
    whole, swept = estimate(config, cut, settings, knots=knots)
    lo = 37  # not a hand-over of the whole log's sweep
    assert lo not in swept.window_starts
    part, sliced = estimate(config, cut, settings, knots=knots[lo:])
    starts = [lo + k for k in sliced.window_starts[1:]]
    assert len(starts) >= 3 and set(starts) <= set(swept.window_starts)
    later = slice(starts[1], None)  # a window on from the join: the same past summarized
    assert np.abs(part.qpos[later.start - lo :] - whole.qpos[later]).max() < 2e-5

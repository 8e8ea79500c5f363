"""A whole log estimated by any method: the entry point the CLI, calibration, chunks and a
notebook share.

    config = load_config("configs/go2.toml")
    log = read_log("recordings/go2.mcap", config)
    est, summary = estimate(config, log.measurements, Settings.from_config(config))

physics and kinematic: the sliding-window smoother (`estimator.run.smooth`); ekf and ukf:
the filters (`estimator.baselines.filters`); raw: the measurements interpolated to the knots.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
from threadpoolctl import threadpool_limits

from estimator.baselines.filters import filter_estimate
from estimator.baselines.gtsam_legged import METHODS as LEGGED
from estimator.baselines.gtsam_legged import legged_estimate
from estimator.config import Config
from estimator.estimate import Estimate
from estimator.io.logs.measurements import Measurement
from estimator.run import Summary, raw_estimate, smooth
from estimator.settings import Settings


def estimate(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    progress: Callable[[int, int], None] | None = None,
    knots: np.ndarray | None = None,
) -> tuple[Estimate, Summary]:
    """Estimate the whole log by `settings.method`; `progress(done, total)` is called after
    each window (physics, kinematic) or stretch of the log (filters). knots: the smoothers'
    knot times (default: `knot_grid` over the measurements; a chunk of a longer log takes
    its slice of the log's grid)."""
    # MuJoCo runs on THREADS threads; the small BLAS calls between its passes are fastest on
    # one (measured: a multithreaded OpenBLAS spin-waits 10× slower on a busy machine)
    with threadpool_limits(limits=1, user_api="blas"):
        if settings.method == "raw":
            return raw_estimate(config, measurements, settings)
        if settings.method in LEGGED:
            return legged_estimate(config, measurements, settings)
        if settings.method in ("ekf", "ukf"):
            return filter_estimate(config, measurements, settings, settings.method, progress)
        return smooth(config, measurements, settings, progress, knots)

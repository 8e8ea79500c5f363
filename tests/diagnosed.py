"""A scenario simulated, estimated and diagnosed with the defaults (the diagnostics tests)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from estimator.batch import estimate
from estimator.config import load_config
from estimator.diagnose import diagnose
from estimator.io.logs import read_log
from estimator.settings import Settings
from estimator.simulate import simulate
from estimator.simulate.simulation import scenario_config


def diagnosed(scenario: Any, tmp_path: Path, duration_s: float, seed: int = 0):
    """(config, log path, measurements, estimate, diagnosis) of `scenario`'s log."""
    log, config_path = tmp_path / "d.mcap", tmp_path / "d.toml"
    simulate(scenario, log, seed=seed, duration_s=duration_s)
    config_path.write_text(scenario_config(scenario, config_path))
    config = load_config(config_path)
    measurements = read_log(log, config).measurements
    settings = Settings.from_config(config)
    est, _ = estimate(config, measurements, settings)
    return config, log, measurements, est, diagnose(config, measurements, est, settings)

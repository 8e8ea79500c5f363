"""The diagnostics tests' runs: a scenario simulated, estimated and diagnosed with the
defaults; a log streamed through the node's online detectors."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from estimator.batch import estimate
from estimator.config import load_config
from estimator.diagnose import DetectorSettings, diagnose
from estimator.io.logs import read_log
from estimator.io.logs.source import open_log
from estimator.settings import Settings
from estimator.simulate import simulate
from estimator.simulate.simulation import scenario_config
from estimator.stream import Stream


def diagnosed(scenario: Any, tmp_path: Path, duration_s: float, seed: int = 0, estimator: str = ""):
    """(config, log path, measurements, estimate, diagnosis) of `scenario`'s log; `estimator`:
    lines of the config's [estimator] table."""
    log, config_path = tmp_path / "d.mcap", tmp_path / "d.toml"
    simulate(scenario, log, seed=seed, duration_s=duration_s)
    table = f"\n[estimator]\n{estimator}\n" if estimator else ""
    config_path.write_text(scenario_config(scenario, config_path) + table)
    config = load_config(config_path)
    measurements = read_log(log, config).measurements
    settings = Settings.from_config(config)
    est, _ = estimate(config, measurements, settings)
    return config, log, measurements, est, diagnose(config, measurements, est, settings)


def streamed(config: Any, log: Path, min_knots: int) -> tuple[Any, list[Any]]:
    """(the stream, every event it reported) of `log` through `Stream(diagnose=...)` with the
    node's settings (two iterations per update, no softness fit), `min_knots` per update."""
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5, diagnose=DetectorSettings())
    events = []
    for raw in open_log(log):
        stream.push(raw)
        for update in stream.update(min_knots=min_knots):
            events += update.events
    for update in stream.close():
        events += update.events
    return stream, events

"""Calibration of the model's contact softness to a log (paper Section V: ε, κ).

A robot softer or stiffer than its model sinks into the floor by another depth, and the
physics prior holds the estimate at the model's depth, off the mocap. Encoders and IMUs do
not see that depth; the mocap does. The criterion is therefore the mocap part of the
estimate's robust cost (its pose, tf, rigid-body and marker streams), profiled over one
setting: each point is a whole estimate with that value (`init = "measurements"`, one solve
per window, so the profile does not switch between starts).

Search: a geometric grid around the config's value (×1.15 steps) or over a given range,
extended by the same steps past an end while the lowest point is there (up to as many values
again; κ not below 2h); then the vertex of the parabola, in log(value), through the grid's
lowest point and its two neighbours. The value kept is the evaluated one with the lowest
mocap cost; its σ is where that parabola rises by ½ (the cost is ½ Σ r² of whitened
residuals). Where the mocap cost varies by less than ½ over the whole grid the log does not
identify the setting (no floor contact, say) and the config's value stays.
"""

from __future__ import annotations

import math
import os
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from estimator.batch import estimate
from estimator.config import MOCAP_KINDS, Config, load_config
from estimator.errors import ConfigError, PhysfuseError
from estimator.io.logs.measurements import Measurement
from estimator.settings import Settings
from physics.errors import UnsupportedModelError
from physics.softness import Softness

# the model's softness as one value for every element, or a factor on its own per-geom values
CALIBRATED = ("softness_eps", "softness_kappa", "softness_eps_scale", "softness_kappa_scale")
GRID_RATIO = 1.15  # between neighbouring grid values
GRID_POINTS = 7
IDENTIFIED_COST = 0.5  # Δ(½ Σ r²) of one σ in one parameter


@dataclass
class Point:
    value: float
    mocap_cost: float  # the criterion
    cost: float  # the whole estimate's robust cost
    wall_time_s: float
    worker: str = ""  # where the estimate ran: "host pid N"


@dataclass
class Calibration:
    setting: str
    initial: float  # the config's value
    best: float
    points: list[Point]  # in evaluation order: the grid, then the parabola's vertex
    at_edge: bool  # the lowest point is an end of the extended grid: the minimum may lie beyond
    identified: bool = True  # False: the mocap cost varies < IDENTIFIED_COST; best = initial
    # σ of log(best): where the parabola rises IDENTIFIED_COST, the 1σ of a cost that is a
    # negative log-likelihood (½ Σ r², Huber's kernel aside); None without a parabola
    sigma_log: float | None = None

    def point(self, value: float) -> Point:
        return next(p for p in self.points if p.value == value)


def default_grid(initial: float, lower: float) -> np.ndarray:
    """GRID_POINTS values around `initial`, ×GRID_RATIO apart, none below `lower`."""
    grid = initial * GRID_RATIO ** (np.arange(GRID_POINTS) - GRID_POINTS // 2)
    if grid[0] < lower:
        grid = lower * GRID_RATIO ** np.arange(GRID_POINTS)
    return grid


def lower_bound(setting: str, config: Config, settings: Settings) -> float:
    """The smallest valid value: κ ≥ 2h (eq. 28; h the knot step), ε > 0."""
    if setting == "softness_kappa":
        return 2 * (settings.h or float(config.load_model().opt.timestep))
    return 0.0


def calibrate(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    setting: str = "softness_eps",
    grid: Sequence[float] | None = None,
    progress: Callable[[Point], None] | None = None,
    on_ray: bool = False,
) -> Calibration:
    """The value of `setting` (one of CALIBRATED) whose physics estimate of the log has the
    lowest mocap cost; `grid` defaults to `default_grid` around the settings' value.

    on_ray: the grid's estimates are Ray tasks, in parallel (inside `fleet.ray_session`)."""
    if setting not in CALIBRATED:
        raise ConfigError(f"calibrate: {setting!r} is not calibrated; expected one of {CALIBRATED}")
    mocap = [name for name, s in config.streams.items() if s.kind in MOCAP_KINDS]
    if not mocap:
        raise ConfigError(
            f"{config.path}: calibration needs a mocap stream ({', '.join(MOCAP_KINDS)}), "
            "which sees how deep the robot sits; the config has none"
        )
    initial = _current_value(config, settings, setting)
    lower = lower_bound(setting, config, settings)
    values = list(default_grid(initial, lower) if grid is None else grid)
    if len(values) < 3 or min(values) < lower or min(values) <= 0:
        raise ConfigError(
            f"calibrate: {setting} needs 3 or more grid values, each > 0 and ≥ {lower:g}; got "
            + ", ".join(f"{v:.4g}" for v in values)
        )
    # (the grid is the fit here: the estimator's own softness fit stays off)
    base = replace(settings, method="physics", init="measurements", fit_softness="none")
    points: list[Point] = []
    shared = _put(measurements) if on_ray else None  # the log, once, in Ray's object store

    def evaluate_all(new: Sequence[float]) -> list[Point]:
        """Points at `new` values, in their order: on Ray's workers when `on_ray`."""
        args = [(setting, v, mocap) for v in new]
        if shared is not None:
            done = _on_ray(config, shared, base, args, progress)
        else:
            done = [
                _progressed(profile_point(config, measurements, base, *a), progress) for a in args
            ]
        points.extend(done)
        return done

    def evaluate(value: float) -> Point:
        return evaluate_all([value])[0]

    on_grid = evaluate_all(sorted(values))
    costs = [p.mocap_cost for p in on_grid]
    if max(costs) - min(costs) < IDENTIFIED_COST:  # the mocap does not see the setting
        return Calibration(setting, initial, initial, points, at_edge=False, identified=False)
    for _ in range(GRID_POINTS):  # a minimum at an end: step past it, as far as the grid spans
        i = int(np.argmin(costs))
        if i == len(on_grid) - 1:
            on_grid.append(evaluate(on_grid[-1].value ** 2 / on_grid[-2].value))
        elif i == 0 and on_grid[0].value > lower:
            on_grid.insert(0, evaluate(max(on_grid[0].value ** 2 / on_grid[1].value, lower)))
        else:
            break
        costs = [p.mocap_cost for p in on_grid]
    i = int(np.argmin(costs))
    at_edge = i in (0, len(on_grid) - 1)
    sigma_log = None
    if not at_edge:
        fit = parabola([math.log(p.value) for p in on_grid[i - 1 : i + 2]], costs[i - 1 : i + 2])
        if fit is not None:
            vertex, curvature = fit
            sigma_log = math.sqrt(IDENTIFIED_COST / curvature)
            evaluate(math.exp(vertex))
    best = min(points, key=lambda p: p.mocap_cost)
    return Calibration(setting, initial, best.value, points, at_edge, sigma_log=sigma_log)


def profile_point(
    config: Config, measurements: Mapping[str, Measurement], settings: Settings,
    setting: str, value: float, mocap: Sequence[str],
) -> Point:  # fmt: skip
    """One point of the profile: the physics estimate with `setting` = value."""
    start = time.perf_counter()
    changed: dict[str, Any] = {setting: value}
    _, summary = estimate(config, measurements, replace(settings, **changed))
    costs = summary.cost_by_type
    return Point(
        value=value,
        mocap_cost=sum(costs.get(name, 0.0) for name in mocap),
        cost=sum(costs.values()),
        wall_time_s=time.perf_counter() - start,
        worker=f"{socket.gethostname()} pid {os.getpid()}",
    )


def _point_task(config_path: str, measurements: Any, settings: Settings, *args: Any) -> Point:
    """`profile_point` in a Ray worker (the config by its path: it holds the loaded model)."""
    return profile_point(load_config(config_path), measurements, settings, *args)


def _put(measurements: Mapping[str, Measurement]) -> Any:
    import ray

    return ray.put(dict(measurements))


def _on_ray(
    config: Config,
    shared: Any,
    settings: Settings,
    args: Sequence[tuple[str, float, Sequence[str]]],
    progress: Callable[[Point], None] | None,
) -> list[Point]:
    """`profile_point` of each of `args` as a Ray task; progress as each one finishes."""
    import ray

    from estimator.fleet import as_task

    task = as_task(_point_task)
    refs = [task.remote(str(config.path), shared, settings, *a) for a in args]
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        try:
            _progressed(ray.get(ready[0]), progress)
        except ray.exceptions.RayError as err:  # the estimate's error, or its workers died
            cause = getattr(err, "cause", None) or err
            line = (str(cause).strip().splitlines() or [type(cause).__name__])[-1]
            raise PhysfuseError(f"calibrate: {line}") from None
    return list(ray.get(refs))


def _progressed(point: Point, progress: Callable[[Point], None] | None) -> Point:
    if progress:
        progress(point)
    return point


def _current_value(config: Config, settings: Settings, setting: str) -> float:
    """The setting's value, or the model's own where it is unset (one for the whole model;
    a scale's is 1)."""
    value = getattr(settings, setting)
    if value is not None:
        return float(value)
    try:
        own = Softness.of_model(config.load_model())
    except UnsupportedModelError as err:
        raise ConfigError(
            f"{config.model_path}: the model's own softness differs between elements ({err}); "
            f"set estimator.{setting} in {config.path} to the value to calibrate around"
        ) from None
    return own.eps if setting == "softness_eps" else own.kappa


def parabola(x: Sequence[float], y: Sequence[float]) -> tuple[float, float] | None:
    """(vertex, a) of the parabola y = a x² + b x + c through three points (x ascending, the
    middle one lowest), the vertex clipped to [x0, x2]; None where they do not curve upward."""
    a, b, _ = np.polyfit(x, y, 2)
    if a <= 0:
        return None
    return float(np.clip(-b / (2 * a), x[0], x[2])), float(a)


def config_with(source: Path, target: Path, setting: str, value: float) -> None:
    """`source` with [estimator] `setting` = value, its comments kept; a relative model path
    is rewritten relative to `target`'s folder."""
    document = tomlkit.parse(source.read_text())
    model = document.get("model")
    if isinstance(model, str) and model.endswith(".xml") and not os.path.isabs(model):
        moved = os.path.relpath(source.parent / model, target.parent)
        document["model"] = moved
    if "estimator" not in document:
        document.add("estimator", tomlkit.table())
    document["estimator"][setting] = float(f"{value:.4g}")
    text = tomlkit.dumps(document)
    if target.is_file() and target.read_text() == text:
        return  # as it is (its time stamp too: the suite reuses runs newer than their config)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
    except OSError as err:
        raise PhysfuseError(f"{target}: cannot write the config ({err.strerror})") from err

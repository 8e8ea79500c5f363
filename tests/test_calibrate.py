"""`physfuse calibrate`: the contact softness fitted to a log by the mocap cost."""

from __future__ import annotations

import json
import os
import socket

import numpy as np
import pytest
import tomlkit
from mcap.reader import make_reader

from estimator.calibrate import calibrate, default_grid, parabola
from estimator.cli import main
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.settings import Settings
from physics.softness import Softness


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A 2 s humanoid_push log whose robot is softer than the model: (log, config, true ε)."""
    folder = tmp_path_factory.mktemp("calibrate")
    log, config = folder / "push.mcap", folder / "push.toml"
    argv = ["simulate", "humanoid_push", "--condition", "nominal", "--seed", "0"]
    argv += ["--duration", "2", "--out", str(log), "--config-out", str(config), "--quiet"]
    assert main(argv) == 0
    with log.open("rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    true_eps = json.loads(meta["physfuse.mismatch"]["true_softness"])["eps"]
    return log, config, true_eps


def test_calibrate_finds_the_robots_softness_and_writes_a_config_that_uses_it(
    simulated, tmp_path, capsys
):
    log, config, true_eps = simulated
    model_eps = Softness.of_model(load_config(config).load_model()).eps  # the model's own
    assert true_eps > 1.15 * model_eps  # the robot is softer than the model by a grid step
    out, calibrated = tmp_path / "out", tmp_path / "elsewhere" / "calibrated.toml"
    argv = ["calibrate", str(log), "--config", str(config), "--out", str(out)]
    assert main([*argv, "--config-out", str(calibrated)]) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "calibration.json").read_text())
    assert (out / "calibration.png").stat().st_size > 0
    best = report["best"]
    assert abs(best - true_eps) < 0.05 * true_eps, (best, true_eps)
    costs = {p["value"]: p["mocap_cost"] for p in report["points"]}
    assert len(costs) == 8 and costs[best] == min(costs.values()) < costs[model_eps]
    assert f"best: softness_eps = {best:.4g}" in printed
    assert not report["at_edge"] and report["identified"]
    assert 0.01 < report["sigma_log"] < 0.1  # a few percent
    assert abs(np.log(best / true_eps)) < 2 * report["sigma_log"]
    # the written config: the original's comments and streams, the fitted ε in [estimator]
    text = calibrated.read_text()
    assert text.startswith(config.read_text().splitlines()[0])
    sections = {"extra_sections": ("estimator", "simulate")}
    assert load_config(calibrated, **sections).streams.keys() == load_config(config).streams.keys()
    settings = Settings.from_config(load_config(calibrated, **sections))
    assert settings.softness_eps == float(f"{best:.4g}")


def test_a_grid_that_stops_short_of_the_minimum_is_extended_past_its_end(simulated, tmp_path):
    """In this process, and on a local Ray of 2 workers: the same profile, its grid's
    estimates in the workers."""
    log, config, true_eps = simulated
    reports = []
    for workers in ([], ["--workers", "2"]):
        out = tmp_path / f"out{len(workers)}"
        argv = ["calibrate", str(log), "--config", str(config), "--out", str(out), "--quiet"]
        assert main([*argv, "--range", "0.03", "0.045", "--points", "3", *workers]) == 0
        reports.append(json.loads((out / "calibration.json").read_text()))
    here, on_ray = (sorted(r["points"], key=lambda p: p["value"]) for r in reports)
    assert here[-1]["value"] > true_eps and not reports[0]["at_edge"]  # stepped ×1.22 past 0.045
    assert abs(reports[0]["best"] - true_eps) < 0.05 * true_eps
    # (MuJoCo on 1 thread in a worker, 2 here: the same to rounding)
    assert reports[1]["best"] == pytest.approx(reports[0]["best"], rel=1e-9)
    for a, b in zip(here, on_ray, strict=True):
        assert b["value"] == pytest.approx(a["value"], rel=1e-9)
        assert b["mocap_cost"] == pytest.approx(a["mocap_cost"], rel=1e-9)
    assert {p["worker"] for p in here} == {f"{socket.gethostname()} pid {os.getpid()}"}
    grid = [p["worker"] for p in on_ray[:3]]  # the grid's three, in parallel
    assert len(set(grid)) >= 2 and os.getpid() not in [int(w.split()[-1]) for w in grid]


def test_the_grid_and_the_parabola():
    grid = default_grid(0.05, 0.0)
    assert len(grid) == 7 and grid[3] == 0.05
    np.testing.assert_allclose(grid[1:] / grid[:-1], 1.15)
    assert default_grid(0.02, 0.02)[0] == 0.02  # κ ≥ 2h: the grid starts at the floor
    assert parabola([0.0, 1.0, 2.0], [1.0, 0.0, 1.0]) == pytest.approx((1.0, 1.0))
    assert parabola([0.0, 1.0, 2.0], [4.0, 1.0, 0.0])[0] == pytest.approx(2.0)  # clipped
    assert parabola([0.0, 1.0, 2.0], [0.0, 1.0, 0.0]) is None  # no minimum


def test_a_log_that_does_not_show_the_softness_keeps_the_configs_value(tmp_path):
    """The single-joint mechanism has no floor: its mocap cost does not move with ε."""
    log, config_path = tmp_path / "sj.mcap", tmp_path / "sj.toml"
    argv = ["simulate", "single_joint", "--condition", "nominal", "--seed", "0"]
    assert (
        main([*argv, "--duration", "1", "--out", str(log), "--config-out", str(config_path)]) == 0
    )
    config = load_config(config_path)
    result = calibrate(config, read_log(log, config).measurements, Settings())
    costs = [p.mocap_cost for p in result.points]
    assert not result.identified and result.sigma_log is None
    assert result.best == result.initial == pytest.approx(0.05)  # the model's own
    assert len(costs) == 7 and max(costs) - min(costs) < 0.5


def test_bad_calibration_input_is_a_one_line_error(simulated, tmp_path, capsys):
    log, config, _ = simulated
    blind = tmp_path / "blind.toml"
    document = tomlkit.parse(config.read_text())
    for name in [n for n, s in document["streams"].items() if s["type"] == "pose"]:
        del document["streams"][name]
    blind.write_text(tomlkit.dumps(document))
    base = ["calibrate", str(log), "--out", str(tmp_path / "out")]
    for extra, expected in [
        (["--config", str(blind)], "calibration needs a mocap stream"),
        (["--config", str(config), "--range", "0.08", "0.04"], "expected 0 < LO < HI"),
        (["--config", str(config), "--points", "2"], "--points 2: expected 3 or more"),
        (
            ["--config", str(config), "--setting", "softness_kappa", "--range", "0.01", "0.04"],
            "softness_kappa needs 3 or more grid values, each > 0 and ≥ 0.02",
        ),
    ]:
        capsys.readouterr()
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and expected in err, err

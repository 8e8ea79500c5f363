"""benchmarks/suite.py: the targets checklist, the table, and its subprocess steps."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("suite", ROOT / "benchmarks" / "suite.py")
assert _spec is not None and _spec.loader is not None
suite = importlib.util.module_from_spec(_spec)
sys.modules["suite"] = suite  # dataclasses resolve their module
_spec.loader.exec_module(suite)


def _run(
    method: str,
    condition: str = "nominal",
    error: str | None = None,
    motion: float = 1.0,
    **metrics: float | None,
):
    """A humanoid_push run with error `motion` on every metric of BEATS_BASELINES, or failed."""
    values = {**dict.fromkeys(suite.BEATS_BASELINES, motion), **metrics} if error is None else {}
    return suite.Run("humanoid_push", condition, method, metrics=values, error=error)


def test_physics_must_beat_every_baseline_on_each_metric():
    runs = [
        _run("physics", joint_deg=0.5, position_mm=0.2),
        _run("kinematic", joint_deg=0.8),
        _run("raw", joint_deg=0.4, position_mm=7.0),
    ]
    (check,) = suite.check_beats_baselines(runs)
    assert check.status == "MISS"  # joint_deg 0.5 against raw's 0.4; orientation ties at 1.0
    assert "joint_deg 0.5 vs raw 0.4 (1.25×)" in check.detail
    assert "orientation_deg 1 vs kinematic 1 (1.00×)" in check.detail
    assert "position_mm" not in check.detail
    better = [_run("physics", motion=0.5), _run("raw")]
    better[0].metrics["joint_deg"] = 0.9
    (check,) = suite.check_beats_baselines(better)
    assert check.status == "PASS" and check.detail == "joint_deg 0.9 vs raw 1 (0.90×)"


def test_a_failed_baseline_leaves_the_target_unmeasured_not_passed():
    runs = [
        _run("physics", motion=0.5),
        _run("raw"),
        _run("ekf", error="timed out after 600 s: physfuse estimate"),
    ]
    (check,) = suite.check_beats_baselines(runs)
    assert check.status == "N/A" and check.detail.endswith(": ekf failed")
    runs[1].metrics["joint_deg"] = 0.1  # a miss outweighs the missing baseline
    assert suite.check_beats_baselines(runs)[0].status == "MISS"


def test_occluded_error_must_be_at_most_a_third_of_the_kinematic_smoothers():
    def runs(physics_mm: float, occluded_s: float = 1.2):
        return [
            _run("physics", "occlusion", occluded_position_mm=physics_mm, occluded_s=occluded_s),
            _run("kinematic", "occlusion", occluded_position_mm=3.0, occluded_s=occluded_s),
        ]

    (check,) = suite.check_occlusion(runs(0.9))
    assert check.status == "PASS" and "(0.30×, target ≤ 0.33×)" in check.detail
    assert suite.check_occlusion(runs(1.2))[0].status == "MISS"
    assert suite.check_occlusion(runs(0.9, occluded_s=0.0)) == []  # nothing was occluded


def test_contact_force_target_applies_to_the_nominal_condition():
    runs = [
        _run("physics", "nominal", contact_force_pct_weight=4.0),
        _run("physics", "outliers", contact_force_pct_weight=40.0),
    ]
    (check,) = suite.check_contact_force(runs)
    assert (check.condition, check.status) == ("nominal", "PASS")
    runs[0].metrics["contact_force_pct_weight"] = 12.5
    assert "12.5% of m·g (1.25× the limit)" in suite.check_contact_force(runs)[0].detail


def test_table_has_a_row_per_run_failures_in_one_line_and_no_empty_columns():
    runs = [
        _run("physics", wall_over_duration=0.7),
        _run("ukf", error="physfuse estimate: error: boom"),
    ]
    text = suite.table(runs)
    head, _, physics, ukf = text.splitlines()
    assert "pos mm" in head and "wall/T" in head and "occ mm" not in head
    assert physics.split()[:3] == ["humanoid_push", "nominal", "physics"]
    assert physics.split()[-1] == "0.7"
    assert ukf.endswith("failed: physfuse estimate: error: boom")


def test_occlusion_table_lists_the_runs_with_occlusions_over_them():
    runs = [
        _run("physics", "nominal", position_mm=0.1),
        _run("physics", "occlusion", position_mm=0.1, occluded_position_mm=0.3, occluded_s=1.2),
        _run("kinematic", "occlusion", occluded_position_mm=0.9, occluded_s=1.2),
    ]
    text = suite.occlusion_table(runs)
    title, head, _, physics, kinematic = text.strip().splitlines()
    assert title == "over the mocap occlusions:"
    assert head.split()[3:] == ["pos", "mm", "occ", "s"]  # only the occluded columns
    assert physics.split() == ["humanoid_push", "occlusion", "physics", "0.3", "1.2"]
    assert kinematic.split()[2:] == ["kinematic", "0.9", "1.2"]
    assert suite.occlusion_table(runs[:1]) == ""  # no occlusions: no table


def test_markdown_tables_have_the_same_cells_and_physics_in_bold():
    runs = [
        _run("physics", "occlusion", position_mm=0.1, occluded_position_mm=0.3, occluded_s=1.2),
        _run("ukf", "occlusion", error="physfuse estimate: error: boom"),
    ]
    main, title, occluded = suite.markdown(runs).strip().split("\n\n")
    head, rule, physics, ukf = main.splitlines()
    assert head.startswith("| scenario | condition | method | pos mm |")
    assert rule.count("|---") == head.count("|") - 1
    assert physics.startswith("| humanoid_push | occlusion | **physics** | 0.1 |")
    assert "| failed: physfuse estimate: error: boom |" in ukf
    assert ukf.count("|") == head.count("|")
    assert title == "Over the mocap occlusions:"
    assert occluded.splitlines()[2].endswith("| 0.3 | 1.2 |")


def test_a_failing_step_becomes_one_line_and_a_log_is_simulated_once(tmp_path):
    error = suite.call(["simulate", "nope", "--out", str(tmp_path / "x.mcap")], 120, tmp_path / "t")
    assert error is not None and error.startswith("physfuse simulate: error: unknown scenario")
    logs = tmp_path / "logs"
    logs.mkdir()
    log, config, error = suite.simulate_log("single_joint", "nominal", 0, 0.3, logs, 120)
    assert error is None and log.exists() and "[streams.command]" in config.read_text()
    mtime = log.stat().st_mtime_ns
    assert suite.simulate_log("single_joint", "nominal", 0, 0.3, logs, 120)[2] is None
    assert log.stat().st_mtime_ns == mtime  # the cache answered
    run = suite.Run("single_joint", "nominal", "physics")
    folder = tmp_path / "run"
    suite.estimate_and_evaluate(run, log, tmp_path / "missing.toml", folder, 120, False)
    assert run.error is not None and "missing.toml" in run.error and "\n" not in run.error
    assert run.metrics == {}


def test_no_mismatch_simulates_the_model_exactly_into_its_own_cache(tmp_path):
    def body_masses(log: Path) -> dict:
        with log.open("rb") as f:
            meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
        return json.loads(meta["physfuse.mismatch"]["body_mass"])

    logs = tmp_path / "logs"
    logs.mkdir()
    drawn, _, error = suite.simulate_log("single_joint", "nominal", 0, 0.1, logs, 120)
    exact, _, exact_error = suite.simulate_log("single_joint", "nominal", 0, 0.1, logs, 120, False)
    assert error is None and exact_error is None and exact != drawn
    assert exact.name == "single_joint-nominal-seed0-0.1s-exact-model.mcap"
    assert body_masses(drawn) != {} and body_masses(exact) == {}
    with pytest.raises(SystemExit):  # argparse's one-line error
        suite.main(["--no-mismatch", "--out", str(tmp_path / "out")])


def test_a_baseline_without_the_method_option_is_reported_not_run(tmp_path):
    run = suite.Run("single_joint", "nominal", "ekf")
    log = tmp_path / "x.mcap"
    log.write_bytes(b"")
    suite.estimate_and_evaluate(run, log, tmp_path / "x.toml", tmp_path / "run", 60, False)
    assert run.error == "physfuse estimate has no --method option (only the physics smoother)"


def test_each_robot_is_calibrated_on_its_own_log_and_every_method_takes_that_config(tmp_path):
    """nominal, occlusion, outliers and no_commands simulate one robot, calibrated on the
    nominal log (simulated for it if not in the suite); `mismatch` another, on its own."""
    said: list[str] = []
    runs, calibrations = suite.run_suite(
        ["single_joint"], ["no_commands", "mismatch"], ["raw"], 0.3, 0, 2, 300, tmp_path,
        say=said.append, calibrate="softness_eps",
    )  # fmt: skip
    assert [(c.condition, c.error) for c in calibrations] == [("nominal", None), ("mismatch", None)]
    for c in calibrations:
        assert c.initial == pytest.approx(0.05)  # the model's own
        assert c.value is not None and Path(c.config).is_file()
        assert f"softness_eps = {c.value:.4g}" in Path(c.config).read_text()
    for run, c in zip(runs, calibrations, strict=True):  # the log's config, the robot's value
        assert run.error is None
        config = Path(run.folder).parent / "calibrated.toml"
        assert f"{config} --out" in (Path(run.folder) / "transcript.txt").read_text()
        text = config.read_text()
        assert f"--condition {run.condition}" in text and f"softness_eps = {c.value:.4g}" in text
    text = suite.calibration_text(calibrations)  # single_joint has no floor: ε is not seen
    assert all(not c.identified for c in calibrations) and "not identified" in text
    again, _ = suite.run_suite(
        ["single_joint"], ["no_commands", "mismatch"], ["raw"], 0.3, 0, 2, 300, tmp_path,
        reuse=True, say=said.append, calibrate="softness_eps",
    )  # fmt: skip
    assert all(r.reused for r in again)  # the calibrated configs were left as they were


def test_a_failed_calibration_is_one_line_and_leaves_the_logs_config(tmp_path):
    log = tmp_path / "empty.mcap"
    log.write_bytes(b"")
    result = suite.calibrate_robot(
        "single_joint", "nominal", "softness_eps", log, tmp_path / "x.toml", tmp_path / "cal", 60
    )
    assert result.config == "" and result.error and "\n" not in result.error
    assert "failed, the log's config used" in suite.calibration_text([result])

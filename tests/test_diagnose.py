"""Contact diagnostics: a push found, isolated and sized on a public robot model's log; the
`disturbances` condition's truth; sensor faults grouped; `physfuse diagnose` end to end; the
online detector inside the streaming estimator."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from diagnosed import diagnosed, streamed
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from estimator.batch import estimate
from estimator.cli import main
from estimator.config import load_config
from estimator.diagnose import Event, diagnose
from estimator.diagnose.detect import DetectorSettings, detect, outliers, unexplained
from estimator.diagnose.diagnosis import explained
from estimator.diagnose.online import CALIBRATE_S
from estimator.diagnose.report import message
from estimator.diagnose.score import score, true_events
from estimator.diagnose.sensor_faults import isolated
from estimator.diagnose.unmodeled import UnmodeledForces
from estimator.io.logs import read_log
from estimator.io.rerun import write_recording
from estimator.settings import Settings
from estimator.simulate import simulate
from estimator.simulate.disturbances import PUSH_FORCE_N, PUSH_S, fall_time
from estimator.simulate.model_scenario import model_scenario
from estimator.simulate.obstacle import Collision
from estimator.simulate.patch import Patch
from estimator.simulate.simulation import T0_NS
from physics.dynamics import make_dynamics
from physics.model import weight

ROOT = Path(__file__).resolve().parents[1]
NS = 1_000_000_000


def test_a_push_on_the_go2_base_is_found_on_its_body_and_sized_within_20_percent(tmp_path):
    """recordings/go2.mcap: Menagerie's Go2 pushed once on the base (1.0–1.1 s, 26 N) in 3 s,
    estimated and diagnosed with the defaults: the push stands out (anything else scores
    under 2, i.e. within twice the threshold); drawn in the Rerun recording, read back."""
    config = load_config(ROOT / "configs" / "go2.toml")
    log = read_log(ROOT / "recordings" / "go2.mcap", config)
    with open(ROOT / "recordings" / "go2.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    (push,) = json.loads(meta["physfuse.simulation"]["pushes"])
    settings = Settings.from_config(config)
    est, _ = estimate(config, log.measurements, settings)
    diagnosis = diagnose(config, log.measurements, est, settings)
    events = [e for e in diagnosis.events if not e.explained_by and e.score > 2.0]
    contacts = [e for e in events if e.kind == "unmodeled contact"]
    assert len(events) == len(contacts) == 1, events
    (e,) = contacts
    assert e.target == push["body"] == "base"
    start, end = (e.start_ns - T0_NS) / NS, (e.end_ns - T0_NS) / NS
    assert abs(start - 1.0) < 0.02 and abs(end - 1.1) < 0.02
    true = np.linalg.norm(push["force_n"])
    assert abs(e.magnitude - true) < 0.2 * true
    assert np.degrees(np.arccos(e.force @ push["force_n"] / e.magnitude / true)) < 15
    # scored as the benchmark scores it: found, isolated, no false alarm
    truth = [{"kind": "push", "start_s": 1.0, "end_s": 1.1, "body": "base", **push}]
    result = score(events, truth, T0_NS, 3.0)
    assert result.matched[0].isolated and not result.false_alarms
    _the_push_is_drawn(config, log, est, diagnosis, e, tmp_path / "diagnostics.rrd")


def _the_push_is_drawn(config, log, est, diagnosis, e, path) -> None:
    """The event on the timeline at its start; its force an arrow onto its contact point (or
    from the base's centre of mass) over its interval's knots and no other; the statistic
    over its threshold per knot."""
    from test_visualize import read_recording

    model = config.load_model()
    entities = read_recording(write_recording(est, model, log, path=path, diagnosis=diagnosis))
    t0 = min(int(est.t_ns[0]), *(int(m.t_ns[0]) for m in log.measurements.values()))
    text = entities["/diagnostics/events"]
    assert text.rows["TextLog:text"] == [[f"{x.kind}: {message(x)}"] for x in diagnosis.events]
    assert text.time_ns == [x.start_ns - t0 for x in diagnosis.events]
    arrows = entities["/world/diagnostics/base"]
    drawn = [k for k, v in enumerate(arrows.rows["Arrows3D:vectors"]) if v]
    inside = np.flatnonzero((est.t_ns >= e.start_ns) & (est.t_ns <= e.end_ns))
    assert drawn == inside.tolist()
    vector = np.array(arrows.rows["Arrows3D:vectors"][inside[0]][0])
    if e.point is None:  # from the base's centre of mass
        d = mujoco.MjData(model)
        d.qpos[:] = est.qpos[inside[0]]
        mujoco.mj_kinematics(model, d)
        origin = arrows.rows["Arrows3D:origins"][inside[0]]
        np.testing.assert_allclose(origin, [d.xipos[1]], atol=1e-6)
    else:  # onto its contact point, at the event's middle knot where it was fitted
        middle = inside[len(inside) // 2]
        tip = np.add(
            arrows.rows["Arrows3D:origins"][middle], arrows.rows["Arrows3D:vectors"][middle]
        )
        np.testing.assert_allclose(tip, [e.point], atol=1e-5)
    np.testing.assert_allclose(vector * weight(model), e.force, rtol=1e-5)  # 1 m per weight
    det = diagnosis.detection
    statistic = entities["/plots/diagnostics/base"]
    b = det.forces.bodies.index("base")
    finite = np.flatnonzero(np.isfinite(det.d2[:, b]))
    assert statistic.time_ns == (est.t_ns[finite] - t0).tolist()
    shown = np.ravel(statistic.rows["Scalars:scalars"])
    np.testing.assert_allclose(shown, det.d2[finite, b] / det.threshold, rtol=1e-6)
    assert shown.max() > 1 and shown[np.searchsorted(finite, inside)].max() == shown.max()


def test_disturbances_write_their_truth_and_leave_out_pushes_the_robot_cannot_take(tmp_path):
    scenario = model_scenario(ROOT / "physics" / "models" / "menagerie" / "go2.xml")
    result = simulate(
        scenario, tmp_path / "d.mcap", seed=3, duration_s=4.0, condition="disturbances"
    )
    events = true_events(tmp_path / "d.mcap")
    kinds = [e["kind"] for e in events]
    assert kinds.count("imu bias step") == 1 and kinds.count("encoder offset") == 1
    pushes = [e for e in events if e["kind"] == "push"]
    collisions = [e for e in events if e["kind"] == "collision"]
    drawn = [p for p in result.pushes if isinstance(p, Collision)]
    patches = [p for p in result.pushes if isinstance(p, Patch)]
    assert len(patches) == 1 and patches[0].body.endswith("_calf")  # one of Go2's feet
    assert len(pushes) == len(result.pushes) - len(drawn) - len(patches) >= 1
    assert len(collisions) == len(drawn) >= 1  # seed 3 brings the obstacle against a hip
    for c in collisions:
        assert sum(c["touched"].values()) == pytest.approx(1.0, abs=2e-3)
        assert c["end_s"] <= 0.7 * 4.0 + 1e-6
    for p in pushes:
        assert PUSH_FORCE_N[0] <= np.linalg.norm(p["force_n"]) <= PUSH_FORCE_N[1]
        assert PUSH_S[0] - 1e-6 <= p["end_s"] - p["start_s"] <= PUSH_S[1] + 1e-6
        assert p["end_s"] <= 0.7 * 4.0 + 1e-6  # pushes first, the sensor faults after
    assert fall_time(result.trajectory) is None  # the robot stays up


def test_a_collision_is_the_force_the_obstacle_made_and_what_the_truth_leaves_unexplained(
    tmp_path,
):
    """Go2 standing, an obstacle not in the model pressed on its base for 0.2 s with 50 N
    along +x: the truth is a collision on the base of about that force (friction of the
    sliding contact adds a part across), and it is what the ground truth's inverse dynamics,
    where the obstacle is parked, leave unexplained on the free joint (J_bᵀF's translational
    rows are F on any body of the tree) — to the newton, and nothing before it."""
    go2 = model_scenario(ROOT / "physics" / "models" / "menagerie" / "go2.xml")
    press = Collision("base", 1.0, 0.2, (50.0, 0.0, 0.0))
    scenario = replace(go2, pushes=lambda rng, duration: (press,), condition="disturbances")
    result = simulate(scenario, tmp_path / "c.mcap", seed=0, duration_s=1.5)
    (event,) = [e for e in true_events(tmp_path / "c.mcap") if e["kind"] == "collision"]
    assert event["body"] == "base" and event["touched"] == {"base": 1.0}
    assert event["start_s"] == pytest.approx(1.0, abs=0.005)
    assert event["end_s"] == pytest.approx(1.2, abs=0.005)
    force = np.array(event["force_n"])
    assert np.linalg.norm(force) == pytest.approx(50.0, rel=0.1)
    assert np.degrees(np.arccos(force[0] / np.linalg.norm(force))) < 25.0
    traj = result.trajectory
    dyn = make_dynamics(traj.model, "native", softness=result.true_softness)

    def unexplained(k: int) -> np.ndarray:
        qacc = (traj.qvel[k + 1] - traj.qvel[k]) / traj.h
        return dyn.inverse(traj.qpos[k], traj.qvel[k], qacc).qfrc_inverse[:3]

    during = range(round(event["start_s"] / traj.h), round(event["end_s"] / traj.h))
    np.testing.assert_allclose(np.mean([unexplained(k) for k in during], axis=0), force, atol=1.0)
    before = range(round(0.8 / traj.h), round(0.95 / traj.h))
    assert max(np.linalg.norm(unexplained(k)) for k in before) < 1.0


def test_a_collision_is_located_on_the_surface_where_the_obstacle_touched(tmp_path):
    """Go2 standing, an obstacle not in the model pressed on the right side of its base for
    0.2 s (about 50 N): estimated and diagnosed with the defaults, the one unmodeled contact
    is on the base, at a point of its surface within 5 cm of where the obstacle touched."""
    go2 = model_scenario(ROOT / "physics" / "models" / "menagerie" / "go2.xml")
    press = Collision("base", 1.0, 0.2, (0.0, 50.0, 0.0))
    scenario = replace(go2, pushes=lambda rng, duration: (press,), condition="disturbances")
    config, log, _, est, diagnosis = diagnosed(scenario, tmp_path, 2.5)
    (truth,) = [e for e in true_events(log) if e["kind"] == "collision"]
    (e,) = [e for e in diagnosis.events if e.kind == "unmodeled contact"]
    assert e.target == truth["body"] == "base"
    assert e.point is not None and np.linalg.norm(e.point - truth["point_m"]) < 0.05
    assert abs(e.magnitude - np.linalg.norm(truth["force_n"])) < 0.3 * e.magnitude
    # Rerun draws the force onto that point, the point moving with the base
    from test_visualize import read_recording

    drawn = write_recording(
        est,
        config.load_model(),
        read_log(log, config),
        path=tmp_path / "d.rrd",
        diagnosis=diagnosis,
    )
    arrows = read_recording(drawn)["/world/diagnostics/base"]
    inside = np.flatnonzero((est.t_ns >= e.start_ns) & (est.t_ns <= e.end_ns))
    middle = inside[len(inside) // 2]
    tip = np.add(arrows.rows["Arrows3D:origins"][middle], arrows.rows["Arrows3D:vectors"][middle])
    np.testing.assert_allclose(tip, [e.point], atol=1e-5)


def _event(kind: str, start_s: float, target: str, score_: float, component: str = "") -> Event:
    t = T0_NS + int(start_s * NS)
    return Event(kind, t, t, t, target, np.zeros(3), np.eye(3), score_, component)


def test_a_sensor_fault_is_the_best_scoring_row_and_explains_what_is_around_it():
    faults = isolated(
        [
            _event("sensor fault", 5.00, "imu", 3.0, "accel y"),
            _event("sensor fault", 5.10, "imu", 9.0, "gyro x"),
            _event("sensor fault", 7.00, "joints", 2.0, "knee position"),
        ]
    )
    causes = [f for f in faults if not f.explained_by]
    assert [(f.target, f.component) for f in causes] == [
        ("imu", "gyro x"),
        ("joints", "knee position"),
    ]
    assert [f.explained_by for f in faults if f.explained_by] == ["imu gyro x"]
    events = explained(
        [
            _event("unmodeled contact", 4.8, "base", 4.0),  # the smoother spreads it back
            _event("unmodeled contact", 5.2, "base", 4.0),
            _event("unmodeled contact", 6.0, "base", 4.0),
        ],
        faults,
    )
    contacts = [e for e in events if e.kind == "unmodeled contact"]
    assert [e.explained_by for e in contacts] == ["imu gyro x", "imu gyro x", ""]


def test_a_pushed_body_is_found_beside_one_the_residual_never_sees():
    """Two bodies, 4 s at 2 ms of unit-information noise: a 5 N push on the first for 0.2 s
    is one event on it; the second, moved only through a joint whose force is free (no
    information, its force 0 at every knot), has nothing to diagnose — not a singular
    covariance."""
    rng = np.random.default_rng(1)
    T = 2000
    info = np.zeros((T, 2, 3, 3))
    info[:, 0] = np.eye(3)
    info[:, 1] = 1e-8 * np.eye(3)  # the force prior alone
    grad = np.zeros((T, 2, 3))
    grad[:, 0] = rng.standard_normal((T, 3))
    grad[1000:1100, 0, 0] += 5.0
    t_ns = 1_000_000_000 + 2_000_000 * np.arange(T)
    # the residual's misfit: what a force on the first body explains, and rows none does
    misfit = np.sum(grad[:, 0] ** 2, axis=1) + rng.chisquare(6, T)
    forces = UnmodeledForces(t_ns, ("pushed", "unseen"), np.array([1, 2]), info, grad, misfit)
    events = detect(forces).events
    assert [e.target for e in events] == ["pushed"]
    assert events[0].force[0] == pytest.approx(5.0, rel=0.2)
    assert abs(events[0].start_ns - t_ns[1000]) <= 20_000_000


def test_diagnose_command_writes_events_and_diagnostics_topics(tmp_path, capsys):
    """The nominal single hinge pressing its tip on the floor: what the physics does not
    explain is the tip contact's normal force (the simulated robot is not its model) —
    model errors of that contact, sized, and no unmodeled contact."""
    out = tmp_path / "diag"
    log, config = ROOT / "recordings" / "single_joint.mcap", ROOT / "configs" / "single_joint.toml"
    assert main(["diagnose", str(log), "--config", str(config), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "events.json").read_text())
    assert report["bodies"] == ["arm"] and report["settings"]["false_alarms_per_min"] == 1.0
    kinds = (" unmodeled contact ", " sensor fault ", " model error ")
    assert len(report["events"]) == sum(
        any(k in line for k in kinds) for line in printed.splitlines()
    )
    contact_errors = [e for e in report["events"] if e["kind"] == "model error"]
    assert contact_errors and all(e["target"] == "contact arm–floor" for e in contact_errors)
    assert all(
        abs(e["normal_force_error_n"]) > 3 * e["normal_force_error_std_n"] for e in contact_errors
    )
    assert not [e for e in report["events"] if e["kind"] == "unmodeled contact"]
    with open(out / "diagnostics.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = {c.topic for c in reader.get_summary().channels.values()}
        assert {"/diagnostics/unmodeled_force/arm", "/estimate/joint_states"} <= topics
        statuses = [
            m.status[0] for _, _, _, m in reader.iter_decoded_messages(topics=["/diagnostics"])
        ]
        typed = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/diagnostics/events"])]
    assert len(statuses) == len(typed) == len(report["events"])
    assert all(s.name.startswith("physfuse/") for s in statuses)
    for m, e in zip(typed, report["events"], strict=True):  # MODEL_ERROR = 1
        assert (m.kind, m.target, m.component) == (1, e["target"], e["component"])
        assert m.size[0] == pytest.approx(e["normal_force_error_n"], rel=1e-12)
        assert m.size_covariance[0] == pytest.approx(e["normal_force_error_std_n"] ** 2)
        span_ns = (m.end.sec - m.header.stamp.sec) * NS + m.end.nanosec - m.header.stamp.nanosec
        assert span_ns / NS == pytest.approx(e["end_s"] - e["start_s"], abs=1e-9)
    assert (out / "diagnostics.rrd").stat().st_size > 0


@pytest.mark.parametrize("option", ["--window", "--false-alarms-per-min"])
def test_diagnose_rejects_a_non_positive_setting_in_one_line(option, tmp_path, capsys):
    log, config = ROOT / "recordings" / "single_joint.mcap", ROOT / "configs" / "single_joint.toml"
    code = main(
        ["diagnose", str(log), "--config", str(config), "--out", str(tmp_path), option, "0"]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and option in err


def test_the_stream_reports_a_push_online_while_it_lasts_and_again_when_it_ends():
    """recordings/humanoid_push.mcap through `Stream(diagnose=...)` with the node's settings:
    the push at 3.26 s (33 N on the torso for 0.1 s; the one at 1.0 s falls in the detector's
    calibration) is reported within a window and a half of its start while it lasts, then
    final: on the torso, sized within 20%, and nothing else is."""
    log, config = (
        ROOT / "recordings" / "humanoid_push.mcap",
        load_config(ROOT / "configs" / "humanoid_push.toml"),
    )
    with open(log, "rb") as f:
        meta = next(r for r in make_reader(f).iter_metadata() if r.name == "physfuse.simulation")
    pushes = json.loads(meta.metadata["pushes"])
    push = next(p for p in pushes if p["start_s"] > CALIBRATE_S)
    stream, events = streamed(config, log, min_knots=10)
    assert stream.lag is not None
    start_ns = stream.lag.t0_ns + round(push["start_s"] * NS)
    assert [e.ongoing for e in events] == [True, False]
    first, final = events
    assert first.target == final.target == "torso"
    assert 0 <= first.detected_ns - start_ns <= 1.5 * DetectorSettings().window_s * NS
    assert final.detected_ns == first.detected_ns
    assert abs(final.start_ns - start_ns) <= 0.05 * NS
    true = float(np.linalg.norm(push["force_n"]))
    assert abs(final.magnitude - true) <= 0.2 * true, (final.magnitude, true)


def test_knots_no_force_on_one_body_explains_are_left_out_of_the_median(monkeypatch):
    """One body at 5 ms of unit-information noise: two knots in three over 0.11 s asking for
    200 N in every direction, their residual explained by no force on the body (a foot
    chattering on touchdown), hold the windowed median up for an event; left out
    (`detect.outliers`), nothing is found there. A 6 N push of 0.2 s is found either way."""
    rng = np.random.default_rng(2)
    T = 2000
    info = np.tile(np.eye(3), (T, 1, 1, 1))
    grad = rng.standard_normal((T, 1, 3))
    misfit = np.sum(grad[:, 0] ** 2, axis=1) + rng.chisquare(6, T)
    spikes = [k for k in range(1000, 1022) if k % 3]
    grad[spikes, 0] = 200.0
    misfit[spikes] = 3 * 200.0**2 + 2000.0  # the force explains its part, not the rest
    grad[1500:1540, 0, 1] += 6.0
    misfit[1500:1540] = np.sum(grad[1500:1540, 0] ** 2, axis=1) + rng.chisquare(6, 40)
    t_ns = 5_000_000 * np.arange(T)
    forces = UnmodeledForces(t_ns, ("foot",), np.array([1]), info, grad, misfit)
    assert set(np.flatnonzero(outliers(unexplained(forces)))) >= set(spikes)
    found = detect(forces).events
    assert [round(e.start_ns / 1e9, 1) for e in found] == [7.5]
    detect_module = sys.modules["estimator.diagnose.detect"]  # (the package exports `detect`)
    monkeypatch.setattr(detect_module, "OUTLIER_QUANTILE", 1.0)  # none left out
    assert sorted(round(e.start_ns / 1e9, 1) for e in detect(forces).events) == [5.0, 7.5]

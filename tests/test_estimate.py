"""The smoother: factor Jacobians on the manifold, and `physfuse estimate` end to end."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from factor_checks import jacobian_error
from mcap_ros2.reader import read_ros2_messages

from estimator.cli import main
from estimator.config import load_config
from estimator.io.logs import Measurement, read_log
from estimator.io.state_topics import at_times, read_ground_truth
from estimator.knots import knot_grid
from estimator.problem import build_problem
from estimator.run import collect_estimate, initial_trajectory
from estimator.settings import Settings
from estimator.solver.banded import BandedSystem
from estimator.solver.linearize import Linearizer

ROOT = Path(__file__).resolve().parent.parent


def _window(
    name: str, first: int, knots: int, method: str = "physics", model_error_std: float = 0.0
) -> tuple:
    """(problem, qpos, bias) of a short window of a sample recording, away from its start."""
    config = load_config(ROOT / "configs" / f"{name}.toml")
    log = read_log(ROOT / "recordings" / f"{name}.mcap", config)
    # no robust reweighting: J is the residual's derivative
    settings = Settings(huber_k=1e12, method=method, model_error_std=model_error_std)
    h = float(config.load_model().opt.timestep)
    t_ns = knot_grid(log.measurements, h)[first : first + knots]
    problem = build_problem(config, log.measurements, settings, t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    bias = np.random.default_rng(0).normal(0.0, 0.01, (problem.T, problem.nb))
    return problem, qpos, bias


@pytest.mark.parametrize(
    ("name", "first", "method"),
    [
        ("humanoid_push", 100, "physics"),
        ("arm_box", 1200, "physics"),
        ("quadruped_trot", 200, "physics"),
        ("quadruped_trot", 200, "kinematic"),
        ("humanoid_push", 100, "physics+model_error"),
    ],
)
def test_factor_jacobians_match_numerical_differentiation_on_the_manifold(name, first, method):
    """Every row of knot k (physics, also with the model-error offset; prior; each sensor:
    vectors, quaternions, IMU with bias, force/torque; the kinematic method's jerk prior,
    reaching z_{k+2}) against central differences of q ⊕ x and b + δ."""
    method, _, error = method.partition("+")  # + the generalized force offset
    problem, qpos, bias = _window(name, first, 12, method, 50.0 if error else 0.0)
    error, rows = jacobian_error(problem, qpos, bias)
    assert error.max() < 2e-3, f"worst row {np.unravel_index(error.argmax(), error.shape)}"
    assert rows > 2 * problem.model.nv + 6  # sensor rows beyond physics (nv) and prior (nv)


def test_banded_normal_equations_and_marginals_match_the_dense_system():
    """BandedSystem (JᵀJ by key blocks, bias prior and walk, LAPACK band storage, damped step
    and its predicted decrease, GTSAM marginals) against the dense normal equations of the
    same rows."""
    for method, error in (("physics", 0.0), ("kinematic", 0.0), ("physics", 50.0)):
        # bandwidth 2 and 3 keys; with the model-error offset
        problem, qpos, bias = _window("humanoid_push", 100, 10, method, error)
        lin = Linearizer(problem)
        try:
            r, J = lin.jacobian(qpos, bias)  # the dense rows
            system = BandedSystem.of(lin.linearize(qpos, bias), lin, bias)
            T, nz, nv = problem.T, problem.nz, problem.model.nv
            A = np.zeros((0, T * nz))
            b = np.zeros(0)
            for i in range(T - 2):  # knot rows, reaching keys i … i + span − 1
                rows = np.zeros((r.shape[1], T * nz))
                width = min(lin.span, T - i) * nz
                rows[:, i * nz : i * nz + width] = J[i, :, :width]
                A, b = np.vstack([A, rows]), np.r_[b, r[i]]
            for key_a, key_b, res, sigma in lin.bias_rows(bias):
                rows = np.zeros((problem.nb, T * nz))
                rows[:, key_a * nz + nv : (key_a + 1) * nz] = np.diag(-1.0 / sigma)
                if key_b is None:
                    rows *= -1
                else:
                    rows[:, key_b * nz + nv : (key_b + 1) * nz] = np.diag(1.0 / sigma)
                A, b = np.vstack([A, rows]), np.r_[b, res / sigma]
            H, g = A.T @ A, A.T @ b
            s, ab = system.scaled_band()
            lam = 1e-3
            dx = system.damped_step(s, ab, lam)
            # (H + λ D) dx = −g with D = diag H + 1e-12 max(diag H) (the scaling's floor:
            # contacts put diag H near 1e14), solved in the scaled form
            D = np.diag(H) + 1e-12 * max(np.diag(H).max(), 1.0)
            c = 1.0 / np.sqrt(D)
            expected = c * np.linalg.solve(c[:, None] * H * c + lam * np.eye(len(c)), -c * g)
            scale = np.abs(expected).max()  # contacts make H stiff (≈1e12): compare to scale
            np.testing.assert_allclose(dx.reshape(-1), expected, rtol=0, atol=1e-5 * scale)
            # the quadratic model's decrease at that step, −gᵀdx − ½dxᵀH dx
            step = dx.reshape(-1)
            model = -g @ step - 0.5 * step @ H @ step
            assert system.predicted_decrease(s, lam, dx) == pytest.approx(model, rel=1e-6)
            std = system.marginal_std(nv, [])
            expected_std = np.sqrt(np.diag(np.linalg.inv(H))).reshape(T, nz)[:, :nv]
            np.testing.assert_allclose(std, expected_std, rtol=1e-4)
        finally:
            lin.close()


def test_the_normal_equations_do_not_depend_on_the_number_of_threads(monkeypatch):
    """Each thread sums its own keys' blocks, row by row in one order: 1, 2 or 3 threads give
    the same bits (split by rows, the blocks at the seams were summed in another order, and
    an estimate moved in the ninth digit with PHYSFUSE_THREADS)."""
    import estimator.solver.banded as banded

    problem, qpos, bias = _window("quadruped_trot", 200, 40)
    lin = Linearizer(problem)
    try:
        blocks = lin.linearize(qpos, bias)
        systems = []
        for threads in (1, 2, 3):
            monkeypatch.setattr(banded, "THREADS", threads)
            systems.append(BandedSystem.of(blocks, lin, bias))
    finally:
        lin.close()
    for other in systems[1:]:
        assert np.array_equal(other.diag, systems[0].diag)
        assert np.array_equal(other.g, systems[0].g)
        assert all(np.array_equal(a, b) for a, b in zip(other.lower, systems[0].lower, strict=True))


def test_marginal_std_is_the_inverse_of_a_stiff_system():
    """A position measured by mocap (120 Hz, σ 0.5 mm) and an accelerometer at every knot
    (500 Hz, σ 0.03 m/s²): the accelerometer's rows put ≈4e14 on H's diagonal, the mocap's
    knowledge of the position as a whole ≈1e6 — an eigenvalue ≈2e-9 of the Jacobi-scaled
    system. A regularizer of that size on the unit diagonal once halved the reported σ."""
    h, T = 0.002, 2000
    H = np.zeros((T, T))
    for k in range(1, T - 1):  # (x_{k−1} − 2 x_k + x_{k+1}) / (h² σ_a)
        a = np.zeros(T)
        a[k - 1 : k + 2] = np.array([1.0, -2.0, 1.0]) / (h**2 * 0.03)
        H += np.outer(a, a)
    mocap = np.flatnonzero(np.diff(np.floor(np.arange(T + 1) * h * 120.0)) > 0)
    H[mocap, mocap] += 1.0 / 0.0005**2
    system = BandedSystem(
        H.diagonal().reshape(T, 1, 1).copy(),
        [H.diagonal(-d).reshape(-1, 1, 1).copy() for d in (1, 2)],
        np.zeros((T, 1)),
    )
    std = system.marginal_std(1, [])[:, 0]
    expected = np.sqrt(np.diag(np.linalg.inv(H)))
    np.testing.assert_allclose(std, expected, rtol=1e-3)
    assert 50e-6 < std[T // 2] < 80e-6  # ≈ 63 µm: mocap averaged over ≈ 0.25 s


def test_model_error_offset_is_on_the_unactuated_dofs_and_reported_by_name():
    """model_error_std adds one offset per unactuated dof (the humanoid's free joint) after the
    IMU bias; collect_estimate reports each under its dof's name."""
    problem, qpos, bias = _window("humanoid_push", 100, 10, "physics", 50.0)
    assert problem.error_dofs.tolist() == [0, 1, 2, 3, 4, 5]
    assert problem.bias_of["model error"] == slice(6, 12) and problem.nb == 12
    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    std = np.full((problem.T, problem.model.nv), np.nan)
    est = collect_estimate(problem, qpos, bias, std, config)
    assert list(est.model_error) == ["root_x", "root_y", "root_z", "root_rx", "root_ry", "root_rz"]
    np.testing.assert_array_equal(est.model_error["root_z"], bias[:, 8])
    off, _, _ = _window("humanoid_push", 100, 10, "physics")
    assert off.nb == 6 and not off.error_dofs.size


def test_difference_jacobians_of_rotations():
    """∂(q2 ⊖ q1)/∂x on a free joint's rotation, against differences of mj_differentiatePos;
    by dof group (row d on the columns of d's group; zero elsewhere)."""
    from estimator.problem import RotationDofs, difference_jacobians

    model = load_config(ROOT / "configs" / "humanoid_push.toml").load_model()
    rng = np.random.default_rng(3)
    q1 = model.qpos0.copy()
    q2 = model.qpos0.copy()
    mujoco.mj_integratePos(model, q1, rng.normal(0, 0.5, model.nv), 1.0)
    mujoco.mj_integratePos(model, q2, rng.normal(0, 0.5, model.nv), 1.0)
    rotations = RotationDofs.of(model)
    d1, d2 = difference_jacobians(model, rotations, q1[None], q2[None])
    group = {d: [d] for d in range(model.nv)}  # the columns of each row's group
    for _, r in rotations.quat_dofs:
        group.update({r + i: [r, r + 1, r + 2] for i in range(3)})
    assert len(rotations.quat_dofs) == 1  # the free joint: vector dofs and one rotation

    def dense(by_group: np.ndarray) -> np.ndarray:
        out = np.zeros((model.nv, model.nv))
        for d, cols in group.items():
            out[d, cols] = by_group[d, : len(cols)]
        return out

    d1, d2 = dense(d1[0]), dense(d2[0])

    def diff(a, b):
        v = np.zeros(model.nv)
        mujoco.mj_differentiatePos(model, v, 1.0, a, b)
        return v

    eps = 1e-7
    for which, analytic in ((0, d1), (1, d2)):
        numeric = np.zeros((model.nv, model.nv))
        for c in range(model.nv):
            dx = np.zeros(model.nv)
            dx[c] = eps
            plus, minus = [q.copy() for q in (q1, q2)], [q.copy() for q in (q1, q2)]
            mujoco.mj_integratePos(model, plus[which], dx, 1.0)
            mujoco.mj_integratePos(model, minus[which], -dx, 1.0)
            numeric[:, c] = (diff(*plus) - diff(*minus)) / (2 * eps)
        np.testing.assert_allclose(analytic, numeric, atol=1e-7)


@pytest.fixture(scope="module")
def estimated(tmp_path_factory):
    """`physfuse estimate` on a fresh 1.5 s humanoid_push simulation: (out dir, log path)."""
    folder = tmp_path_factory.mktemp("estimate")
    log = folder / "push.mcap"
    config = folder / "push.toml"
    assert (
        main(
            [
                "simulate",
                "humanoid_push",
                "--seed",
                "3",
                "--duration",
                "1.5",
                "--out",
                str(log),
                "--config-out",
                str(config),
                "--quiet",
            ]
        )
        == 0
    )
    out = folder / "out"
    assert main(["estimate", str(log), "--config", str(config), "--out", str(out), "--quiet"]) == 0
    return out, log, config


def _estimate_with(estimated, folder: Path, settings: str) -> tuple[Path, dict]:
    """`physfuse estimate` on the fixture's log with `settings` (TOML lines) added to its
    config's [estimator]: (out dir, summary.json)."""
    _, log, config = estimated
    changed = folder / "changed.toml"
    changed.write_text(f"{config.read_text()}\n[estimator]\n{settings}\n")
    out = folder / "out"
    argv = ["estimate", str(log), "--config", str(changed), "--out", str(out), "--quiet"]
    assert main(argv) == 0
    return out, json.loads((out / "summary.json").read_text())


def test_estimate_writes_the_shared_topic_layout_and_beats_the_measurements(estimated, capsys):
    out, log, config = estimated
    model = load_config(config).load_model()
    summary = json.loads((out / "summary.json").read_text())
    knots = summary["knots"]
    assert all(summary["converged"])
    accuracy = summary["accuracy_vs_ground_truth"]
    for metric in ("joint_deg", "torso_pos_mm", "torso_rot_deg"):
        assert accuracy["estimate"][metric] < accuracy["raw"][metric], metric
    # estimate.mcap: the /estimate layout, one message per knot and topic
    counts: dict[str, int] = {}
    odometry = {}
    for msg in read_ros2_messages(str(out / "estimate.mcap")):
        counts[msg.channel.topic] = counts.get(msg.channel.topic, 0) + 1
        if msg.channel.topic == "/estimate/odometry/torso":
            m = msg.ros_msg
            t = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            p = m.pose.pose.position
            odometry[t] = (p.x, p.y, p.z, m.pose.covariance[0])
    expected = {"/estimate/odometry/torso", "/estimate/joint_states", "/estimate/contacts"}
    assert expected <= set(counts)
    assert any(t.startswith("/estimate/contact_wrench/") for t in counts)
    assert counts["/estimate/joint_states"] == knots
    # the odometry is the estimate: within millimetres of the true torso, with a covariance
    times = np.array(sorted(odometry))
    truth = at_times(*read_ground_truth(log, model), times)
    position = np.array([odometry[t][:3] for t in times])
    assert np.sqrt(np.mean(np.sum((position - truth[:, :3]) ** 2, axis=1))) < 2e-3
    assert all(odometry[t][3] > 0 for t in times[2:-2])
    # the Rerun recording has the moving model and the contact arrows
    import rerun as rr

    chunks = rr.chunk.RrdReader(out / "estimate.rrd").stream().collect().stream().to_chunks()
    paths = {c.entity_path for c in chunks}
    assert "/world/model/torso" in paths and "/world/contacts" in paths


def test_estimate_reports_a_model_that_does_not_explain_the_motion(estimated, tmp_path, capsys):
    """A floor 5 cm too high: the estimate is still written, with a warning naming residuals."""
    _, log, config = estimated
    spec = mujoco.MjSpec.from_file(str(ROOT / "physics" / "models" / "humanoid.xml"))
    floor = spec.geom("floor")
    floor.pos = [floor.pos[0], floor.pos[1], floor.pos[2] + 0.05]
    wrong_model = tmp_path / "high_floor.xml"
    wrong_model.write_text(spec.to_xml())
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(config.read_text().replace('model = "humanoid"', f'model = "{wrong_model}"'))
    out = tmp_path / "out"
    assert main(["estimate", str(log), "--config", str(wrong), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    # the physics factors give up on what the model cannot explain (a redescending kernel)
    # rather than bend the measured motion, and say so
    assert "the model does not explain the motion (physics factors)" in err
    # the torso's vertical dof, and what most likely sets it: the contacts or the masses
    assert "on root_z" in err and "the contact softness or the masses" in err
    assert (out / "estimate.mcap").exists()
    assert json.loads((out / "summary.json").read_text())["warnings"]
    # the right model raises no such warning
    summary = json.loads((estimated[0] / "summary.json").read_text())
    assert not any("does not explain" in w for w in summary["warnings"])


def test_init_kinematic_starts_the_physics_from_the_kinematic_smoother(estimated, tmp_path, capsys):
    """init = "kinematic": each window is first solved without physics; the physics solve that
    follows still converges and beats the measurements. A misspelt choice is a one-line error."""
    _, log, config = estimated
    _, summary = _estimate_with(estimated, tmp_path, 'init = "kinematic"')
    assert summary["settings"]["init"] == "kinematic" and all(summary["converged"])
    accuracy = summary["accuracy_vs_ground_truth"]
    for metric in ("joint_deg", "torso_pos_mm", "torso_rot_deg"):
        assert accuracy["estimate"][metric] < accuracy["raw"][metric], metric
    assert accuracy["estimate"]["torso_pos_mm"] < 2.0
    typo = tmp_path / "typo.toml"
    typo.write_text(config.read_text() + '\n[estimator]\ninit = "kinematc"\n')
    capsys.readouterr()
    assert main(["estimate", str(log), "--config", str(typo), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "estimator.init = 'kinematc'" in err


def test_init_best_keeps_the_lower_cost_of_both_starts(estimated, tmp_path):
    """init = "best": the window (the whole 1.5 s log) solved from the measurements and from
    the kinematic smoother's solution; the estimate is the solution of lower cost. Each start
    alone: `init` in the config, or `--init` on the command line."""
    _, log, config = estimated
    (tmp_path / "best").mkdir()
    _, best = _estimate_with(estimated, tmp_path / "best", 'init = "best"')
    assert best["settings"]["init"] == "best"
    costs = {}
    for init in ("measurements", "kinematic"):
        folder = tmp_path / init / "out"
        if init == "kinematic":
            (tmp_path / init).mkdir()
            _estimate_with(estimated, tmp_path / init, f'init = "{init}"')
        else:
            argv = ["estimate", str(log), "--config", str(config), "--init", init]
            assert main([*argv, "--out", str(folder), "--quiet"]) == 0
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["settings"]["init"] == init and summary["kept_starts"] == [init]
        costs[init] = sum(summary["cost_by_type"].values())
    assert sum(best["cost_by_type"].values()) == pytest.approx(min(costs.values()), rel=1e-12)
    assert best["kept_starts"] == [min(costs, key=costs.__getitem__)]  # one window
    assert best["iterations"][0] > max(  # every stage counted: kinematic + both physics solves
        json.loads((tmp_path / init / "out" / "summary.json").read_text())["iterations"][0]
        for init in costs
    )


def test_init_best_across_gaps_solves_once_where_every_coordinate_is_measured(estimated, tmp_path):
    """init = "best_across_gaps": one solve, from the measurements, where every
    coordinate of the start is measured — the `estimated` log's torso mocap stops 0.5 s before
    its end, and the pelvis' mocap carries the torso's start through the joints; both starts,
    as "best", where the start has a gap (the torso alone tracked) or where the solve from
    the measurements does not converge (two iterations)."""
    _, log, config = estimated
    argv = ["estimate", str(log), "--config", str(config), "--init", "best_across_gaps"]
    assert main([*argv, "--out", str(tmp_path / "filled"), "--quiet"]) == 0
    filled = json.loads((tmp_path / "filled" / "summary.json").read_text())
    assert filled["settings"]["init"] == "best_across_gaps"
    assert filled["starts_tried"] == [["measurements"]]

    torso_alone = tmp_path / "torso_alone.toml"
    text = config.read_text()
    for name in ("mocap_pelvis", "mocap_left_foot", "mocap_right_foot"):  # whole sections
        text = re.sub(rf"\[streams\.{name}\]\n(?:[^\[\n].*\n|\n)*", "", text)
    torso_alone.write_text(text)
    summaries = {}
    for init in ("best_across_gaps", "best"):
        argv = ["estimate", str(log), "--config", str(torso_alone), "--init", init]
        assert main([*argv, "--out", str(tmp_path / init), "--quiet"]) == 0
        summaries[init] = json.loads((tmp_path / init / "summary.json").read_text())
    with_gap, best = summaries["best_across_gaps"], summaries["best"]
    assert "mocap_pelvis" not in with_gap["cost_by_type"]
    assert with_gap["starts_tried"] == best["starts_tried"] == [["kinematic", "measurements"]]
    assert with_gap["cost_by_type"] == best["cost_by_type"]

    argv = ["estimate", str(log), "--config", str(config), "--init", "best_across_gaps"]
    argv += ["--iterations", "2"]
    assert main([*argv, "--out", str(tmp_path / "unconverged"), "--quiet"]) == 0
    unconverged = json.loads((tmp_path / "unconverged" / "summary.json").read_text())
    assert unconverged["starts_tried"] == [["measurements", "kinematic"]]

    log, config = tmp_path / "log.mcap", tmp_path / "log.toml"
    simulated = ["simulate", "humanoid_push", "--seed", "3", "--duration", "1.5"]
    argv = [*simulated, "--condition", "nominal", "--out", str(log), "--config-out", str(config)]
    assert main([*argv, "--quiet"]) == 0
    summaries = {}
    for init in ("best_across_gaps", "measurements"):
        argv = ["estimate", str(log), "--config", str(config), "--init", init]
        assert main([*argv, "--out", str(tmp_path / f"nominal_{init}"), "--quiet"]) == 0
        summaries[init] = json.loads((tmp_path / f"nominal_{init}" / "summary.json").read_text())
    once, measurements = summaries["best_across_gaps"], summaries["measurements"]
    assert once["starts_tried"] == [["measurements"]]
    assert once["iterations"] == measurements["iterations"]
    assert once["cost_by_type"] == measurements["cost_by_type"]


def test_the_gaps_of_the_measurements_start():
    """initial_trajectory's filled knots: a measured coordinate interpolated across a gap, or
    held at an end for longer than 2.5 of its stream's sample periods."""
    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    model = config.load_model()
    measurements = dict(read_log(ROOT / "recordings" / "humanoid_push.mcap", config).measurements)
    t_ns = knot_grid(measurements, model.opt.timestep)
    # the torso's mocap alone: the bodies below it would fill its gaps through the joints
    for name in ("mocap_pelvis", "mocap_left_foot", "mocap_right_foot"):
        del measurements[name]

    def gaps() -> np.ndarray:
        filled = np.zeros(len(t_ns), dtype=bool)
        initial_trajectory(model, measurements, t_ns, filled=filled)
        return filled

    assert not gaps().any()  # every frame of the root's mocap: its start knot held, no gap
    torso = measurements["mocap_torso"]

    def kept(keep: np.ndarray) -> Measurement:
        return replace(
            torso,
            t_ns=torso.t_ns[keep],
            values=torso.values[keep],
            log_time_ns=torso.log_time_ns[keep],
        )

    k0, k1 = 40, 90  # the torso's mocap lost between the knots k0 and k1
    lost = (torso.t_ns > t_ns[k0]) & (torso.t_ns < t_ns[k1])
    measurements["mocap_torso"] = kept(~lost)
    kept_times = torso.t_ns[~lost]
    last, first = kept_times[kept_times <= t_ns[k0]][-1], kept_times[kept_times >= t_ns[k1]][0]
    expected = (t_ns > last) & (t_ns < first)  # between the samples that bracket the gap
    assert np.array_equal(gaps(), expected) and k0 <= np.flatnonzero(expected)[0] <= k0 + 1
    late = torso.t_ns > t_ns[k1 + 20]  # and it starts late
    measurements["mocap_torso"] = kept(late)
    assert np.array_equal(gaps(), t_ns < torso.t_ns[late][0])


def test_a_free_joint_occluded_is_started_through_a_tracked_body_below_it():
    """The torso's mocap lost for 0.5 s: its start comes from the pelvis' mocap through the
    encoders (forward kinematics), close to the truth, not interpolated across the gap; no
    knot is then a gap."""
    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    model = config.load_model()
    log = ROOT / "recordings" / "humanoid_push.mcap"
    measurements = dict(read_log(log, config).measurements)
    t_ns = knot_grid(measurements, model.opt.timestep)
    torso = measurements["mocap_torso"]
    lost = (torso.t_ns > t_ns[100]) & (torso.t_ns < t_ns[150])
    measurements["mocap_torso"] = replace(
        torso,
        t_ns=torso.t_ns[~lost],
        values=torso.values[~lost],
        log_time_ns=torso.log_time_ns[~lost],
    )
    filled = np.zeros(len(t_ns), dtype=bool)
    qpos = initial_trajectory(model, measurements, t_ns, filled=filled)
    assert not filled.any()
    t_truth, q_truth = read_ground_truth(log, model)
    truth = at_times(t_truth, q_truth, t_ns)
    gap = slice(105, 145)
    through_joints = rms(qpos[gap, :3] - truth[gap, :3])
    # interpolating across the gap, even between the true ends (the torso sways in it)
    w = np.linspace(0.0, 1.0, 51)[5:45, None]
    interpolated = rms((1 - w) * truth[100, :3] + w * truth[150, :3] - truth[gap, :3])
    assert through_joints < 0.6 * interpolated  # (measured: 2.8 against 5.8 mm)


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def test_short_windows_stitch_the_motion_and_its_covariance(estimated, tmp_path):
    """Windows of 0.6 s overlapping by 0.2 s: the stitched estimate still beats the
    measurements, and every knot has its covariance (each window computes the marginals only
    at the knots it keeps)."""
    out, summary = _estimate_with(estimated, tmp_path, "window_s = 0.6\noverlap_s = 0.2")
    assert len(summary["converged"]) >= 3 and all(summary["converged"])
    accuracy = summary["accuracy_vs_ground_truth"]
    for metric in ("joint_deg", "torso_pos_mm", "torso_rot_deg"):
        assert accuracy["estimate"][metric] < accuracy["raw"][metric], metric
    variances = [
        msg.ros_msg.pose.covariance[0]
        for msg in read_ros2_messages(str(out / "estimate.mcap"))
        if msg.channel.topic == "/estimate/odometry/torso"
    ]
    assert len(variances) == summary["knots"]
    assert all(np.isfinite(v) and v > 0 for v in variances[1:-1])


def test_bad_settings_and_missing_logs_are_one_line_errors(estimated, tmp_path, capsys):
    _, log, config = estimated
    bad = tmp_path / "bad.toml"
    bad.write_text(config.read_text() + "\n[estimator]\nwindow_s = -1\n")
    assert main(["estimate", str(log), "--config", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "estimator.window_s = -1" in err
    typo = tmp_path / "typo.toml"
    typo.write_text(config.read_text() + "\n[estimator]\nwindow = 2\n")
    assert main(["estimate", str(log), "--config", str(typo), "--out", str(tmp_path)]) == 2
    assert "estimator.window is not a setting" in capsys.readouterr().err
    assert main(["estimate", str(tmp_path / "none.mcap"), "--config", str(config)]) == 2
    assert "none.mcap" in capsys.readouterr().err


def test_softness_settings_reach_the_residuals_and_the_reported_forces(estimated, tmp_path, capsys):
    """softness_eps and softness_kappa set the model of the physics residuals and of the
    reported forces alike; a value MuJoCo would clamp is a one-line error naming the setting."""
    _, log, config_path = estimated
    softer = tmp_path / "softer.toml"
    softer.write_text(
        config_path.read_text() + "\n[estimator]\nsoftness_eps = 0.06\nsoftness_kappa = 0.03\n"
    )
    forces = {}
    for path in (config_path, softer):
        config = load_config(path)
        measurements = read_log(log, config).measurements
        t_ns = knot_grid(measurements, float(config.load_model().opt.timestep))[:30]
        problem = build_problem(config, measurements, Settings.from_config(config), t_ns)
        qpos = initial_trajectory(problem.model, measurements, t_ns)
        lin = Linearizer(problem)
        u = lin.terms(qpos, False).u
        lin.close()
        std = np.full((problem.T, problem.model.nv), np.nan)
        estimate = collect_estimate(problem, qpos, np.zeros((problem.T, problem.nb)), std, config)
        np.testing.assert_allclose(estimate.qfrc_inverse[1:-1], u, rtol=1e-9, atol=1e-9)
        forces[path] = u
    np.testing.assert_allclose(problem.model.geom_solimp[:, :2], 1 / 1.06)
    assert np.all(problem.model.geom_solref[:, 0] == 0.03)
    assert np.abs(forces[softer] - forces[config_path]).max() > 1.0  # N: the feet are in contact
    clamped = tmp_path / "clamped.toml"
    clamped.write_text(config_path.read_text() + "\n[estimator]\nsoftness_kappa = 0.001\n")
    capsys.readouterr()
    assert main(["estimate", str(log), "--config", str(clamped), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "estimator.softness_kappa=0.001 s is below" in err


def test_initialization_survives_a_dropped_first_frame():
    """Without the first mocap frames, the first knots hold the first seen pose (no NaN) and
    the measured knots are the measurements."""
    from dataclasses import replace

    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    measurements = dict(read_log(ROOT / "recordings" / "humanoid_push.mcap", config).measurements)
    torso = measurements["mocap_torso"]
    dropped = 6
    measurements["mocap_torso"] = replace(
        torso,
        t_ns=torso.t_ns[dropped:],
        log_time_ns=torso.log_time_ns[dropped:],
        values=torso.values[dropped:],
    )
    model = config.load_model()
    t_ns = knot_grid(measurements, float(model.opt.timestep))
    qpos = initial_trajectory(model, measurements, t_ns)
    assert np.all(np.isfinite(qpos))
    first = int(np.searchsorted(t_ns, measurements["mocap_torso"].t_ns[0]))
    assert first > 0
    np.testing.assert_allclose(
        qpos[:first, :3], np.tile(qpos[first + 1, :3], (first, 1)), atol=0.02
    )
    np.testing.assert_allclose(np.linalg.norm(qpos[:, 3:7], axis=1), 1.0, atol=1e-12)


def test_constant_acceleration_prior_defaults_by_method():
    """Both smoothers get σ_j = 1000 m/s³; its kernel is Cauchy per dof with the physics
    factors (impacts get through) and none in the kinematic baseline, unless set; 0 turns the
    prior off (factors reach three knots again)."""
    assert Settings().jerk_prior_std == Settings(method="kinematic").jerk_prior_std == 1000.0
    assert Settings().jerk_robust_kernel == "cauchy"
    assert Settings(method="kinematic").jerk_robust_kernel == "none"
    assert Settings(method="kinematic", jerk_kernel="huber").jerk_robust_kernel == "huber"
    problem, _, _ = _window("humanoid_push", 100, 10, "physics", 0.0)
    spans = []
    for std in (1000.0, 0.0):
        lin = Linearizer(replace(problem, settings=replace(problem.settings, jerk_prior_std=std)))
        spans.append(lin.span)
        lin.close()
    assert spans == [4, 3]


def test_the_readme_python_example_runs(monkeypatch, capsys):
    """The README's Python API example, as a notebook user pastes it (on the single-joint
    recording, for time): the same objects the CLI uses, no private names."""
    readme = (ROOT / "README.md").read_text()
    code = readme.split("```python\n")[1].split("```")[0]
    assert "from estimator.batch import estimate" in code
    monkeypatch.chdir(ROOT)
    exec(code.replace("go2", "single_joint"), {})
    shapes = capsys.readouterr().out
    assert shapes.startswith("(") and "True" in shapes.splitlines()[-1]

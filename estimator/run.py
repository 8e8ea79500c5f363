"""Estimation of a whole log: initialize from the measurements, sweep a sliding window over it
(each window's past marginalized into a prior on the next one's first keys, and the windows
before following what the next one moved), and collect the forces, contacts, uncertainty and
residuals of the result."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import mujoco
import numpy as np

from estimator import heap
from estimator.actuation import moment_dense
from estimator.config import Config
from estimator.contact_forces import balanced_constraints
from estimator.estimate import Estimate
from estimator.factors.marginal_prior import MarginalPrior
from estimator.io.logs.measurements import Measurement
from estimator.knots import interpolated_at_knots, knot_grid
from estimator.leg_odometry import (
    START_POSITION_STD_M,
    START_YAW_STD_RAD,
    base_from_legs,
    start_source,
    unanchored,
    unobserved_line,
)
from estimator.problem import (
    MODEL_ERROR,
    Problem,
    accelerations,
    build_problem,
    dof_names,
    model_with_sensors,
    u_known_along,
    velocities,
)
from estimator.settings import Settings
from estimator.solver.covariance import with_covariance
from estimator.solver.linearize import Linearizer, row_span
from estimator.solver.softness_fit import fit_softness
from estimator.solver.window import WindowResult, follow, solve_window
from physics.dynamics import Dynamics, make_dynamics
from physics.model import weight as model_weight
from physics.result import Constraints, Contacts

_OBJ = mujoco.mjtObj
# a knot whose forces were not computed (`collect_estimate(knots=...)`)
_NO_CONSTRAINTS = Constraints(
    np.zeros(0),
    np.zeros(0, int),
    np.zeros(0, int),
    np.zeros(0, int),
    Contacts(
        np.zeros((0, 3)),
        np.zeros((0, 3, 3)),
        np.zeros(0, int),
        np.zeros((0, 2), int),
        np.zeros(0, int),
        np.zeros((0, 5)),
    ),
    0.0,
)


@dataclass
class Summary:
    """What the terminal and summary.json report about one estimation."""

    duration_s: float
    knots: int
    h: float
    windows: int
    iterations: list[int]
    converged: list[bool]
    cost_by_type: dict[str, float]
    largest_residuals: list[dict]
    wall_time_s: float
    warnings: list[str] = field(default_factory=list)
    linearizations: int = 0  # MuJoCo passes with Jacobians over a window's knots
    evaluations: int = 0  # passes without
    knots_linearized: int = 0  # Σ knots over those passes
    knots_evaluated: int = 0
    # unactuated dof → mean generalized force offset the model needed (N or N·m)
    model_error_mean: dict[str, float] = field(default_factory=dict)
    # per window, where the kept physics solution started: "kinematic" | "measurements"
    kept_starts: list[str] = field(default_factory=list)
    # per window, the starts its physics was solved from ("best": both; "best_across_gaps":
    # both only where the measurements have a gap)
    starts_tried: list[list[str]] = field(default_factory=list)
    # fit_softness: the factors on the model's own ε and κ the first window gave, their σ
    softness_fit: dict[str, float] = field(default_factory=dict)
    # the knot where each window's kept estimate begins (a join between windows: the next)
    window_starts: list[int] = field(default_factory=list)


PASS_COUNTS = ("linearizations", "evaluations", "knots_linearized", "knots_evaluated")


def smooth(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    progress: Callable[[int, int], None] | None,
    knots: np.ndarray | None = None,
) -> tuple[Estimate, Summary]:
    start = time.perf_counter()
    compiled = model_with_sensors(config)
    model = compiled[0]
    h = settings.h or float(model.opt.timestep)
    t_ns = knot_grid(measurements, h) if knots is None else knots
    T = len(t_ns)
    filled = np.zeros(T, dtype=bool)  # knots the measurements' start interpolates in a gap
    qpos0 = initial_trajectory(model, measurements, t_ns, filled=filled)
    # the physics without mocap: short windows, the heading the gyro's (docs/no_mocap.md)
    no_mocap = unanchored(model, measurements)  # x, y, yaw relative to the start pose
    short = settings.method == "physics" and no_mocap
    window_s = settings.window_s_no_mocap if short else settings.window_s
    W = max(8, round(window_s / h))
    overlap = min(W // 2, max(4, round(settings.overlap_s / h)))
    qpos = qpos0.copy()
    nb = None
    bias: np.ndarray | None = None
    std = np.full((T, model.nv), np.nan)
    iterations, converged = [], []
    warnings: list[str] = []
    passes = dict.fromkeys(PASS_COUNTS, 0)
    kept_starts: list[str] = []
    starts_tried: list[list[str]] = []
    settings, fitted = softness_fitted(config, measurements, settings, t_ns, qpos0, compiled)
    # The sweep: window i solves keys [s, e) with the marginal prior of the knots before s,
    # keeps [s, s + a) and hands keys s + a … on to the next window (with its past
    # marginalized onto them): its last `overlap` knots only look ahead for the kept ones.
    n_shared = row_span(settings) - 1  # keys two windows' rows share
    # Windows hand over at anchors every `step` knots of the log's clock (t // h), so that a
    # slice of a log (a chunk) is swept in the windows the whole log is: the next window
    # starts at the next anchor, or (join = "quiet") at the quietest key of the `early` knots
    # before it, never later than `overlap` look-ahead allows (a0 knots on). `step` keeps the
    # mean hand-over where the quiet range's middle was: a0 − early / 2.
    early = overlap // 2 if settings.join == "quiet" else 0
    step = max(1, W - overlap - n_shared - early // 2)
    clock = int(t_ns[0]) // round(h * 1e9)  # the first knot's index on the log's clock
    total = max(1, -(-(T - W) // step) + 1)
    prior = None
    s, i = 0, 0
    window_starts = []
    history: list[_Joined] = []  # the last windows: where each starts, the prior it received
    solved_until = 0  # the knots before come from a window's solution
    while True:
        window_starts.append(s)
        e = min(T, s + W)
        last = e == T
        # the next window's start: the next anchor's key, or (below) a key of its quiet range
        a0 = max(1, e - s - overlap - n_shared)  # the most this window can keep
        anchor = _next_anchor(clock + s + early, step) - clock - s
        a = e - s if last else min(anchor, a0)
        window = {name: samples_within(m, t_ns[s], t_ns[e - 1]) for name, m in measurements.items()}
        problem = build_problem(config, window, settings, t_ns[s:e], compiled)
        if nb is None:
            nb = problem.nb
            bias = np.zeros((T, nb))
            if no_mocap:  # the estimate is relative to its start pose
                prior = MarginalPrior.start_pose(
                    model, qpos, bias, problem.bias_prior, START_POSITION_STD_M, START_YAW_STD_RAD
                )
        assert bias is not None
        init_q = qpos[s:e].copy()
        init_b = bias[s:e].copy()
        stages = []
        shared = (init_q[:n_shared], init_b[:n_shared])  # as the previous window left them
        history.append(_Joined(s, prior))
        reach = s - round(settings.backward_s / h)  # the oldest window the pass still moves
        while len(history) > 1 and history[1].start <= reach:
            del history[0]
        starts_at = {"measurements": (init_q, init_b)}  # where the physics solve starts
        # "best_across_gaps": both starts only where the measurements' start is interpolated
        # across a gap (an occlusion, a dropout; not on the knots the previous window solved)
        fill = filled[s:e].copy()
        fill[: max(0, solved_until - s)] = False
        kinematic_start = settings.init in ("kinematic", "best") or (
            settings.init == "best_across_gaps" and bool(fill.any())
        )
        physics = settings.method == "physics"
        if kinematic_start and physics:
            stage, kinematic = _kinematic_start(
                config, window, settings, t_ns[s:e], compiled, init_q, init_b
            )
            stages.append(stage)
            if settings.init == "kinematic":
                starts_at = {"kinematic": kinematic}
            else:
                starts_at = {"kinematic": kinematic, **starts_at}
        # the next window's start: the anchor, or (join = "quiet") the quietest key of the
        # `early` knots before it
        joins: int | range | None = None if last else a
        if not last and early:
            joins = range(max(1, anchor - early), a + 1)
        solved = {
            name: solve_window(problem, q0, b0, False, prior=prior, marginalize=joins)
            for name, (q0, b0) in starts_at.items()
        }
        # "best_across_gaps": a solve from the measurements that did not converge (a start
        # the redescending kernels hold, as the Panda's box at 2 kHz) from both starts too
        if (
            settings.init == "best_across_gaps"
            and physics
            and "kinematic" not in solved
            and not solved["measurements"].converged
        ):
            stage, kinematic = _kinematic_start(
                config, window, settings, t_ns[s:e], compiled, init_q, init_b
            )
            stages.append(stage)
            solved["kinematic"] = solve_window(
                problem, *kinematic, False, prior=prior, marginalize=joins
            )
        stages += solved.values()
        # "best": the solution of lower cost; its covariance alone
        kept = min(solved, key=lambda name: solved[name].cost_final)
        kept_starts.append(kept)
        next_start = solved[kept].next_start
        if not last and next_start is not None:
            a = next_start
        starts_tried.append(list(solved))
        result = with_covariance(solved[kept], range(0, a), problem)
        # the windows before follow the keys this one moved (a backward pass, linearized)
        moved, now = shared, (result.qpos[:n_shared], result.bias[:n_shared])
        for later, earlier in zip(reversed(history), reversed(history[:-1]), strict=False):
            assert later.prior is not None
            kept_keys = slice(earlier.start, later.start)
            its_first = slice(earlier.start, earlier.start + n_shared)
            before = (qpos[its_first].copy(), bias[its_first].copy())
            qpos[kept_keys], bias[kept_keys] = follow(
                model, later.prior, moved, now, (qpos[kept_keys], bias[kept_keys])
            )
            moved, now = before, (qpos[its_first], bias[its_first])
        qpos[s : s + a] = result.qpos[:a]
        bias[s : s + a] = result.bias[:a]
        std[s : s + a] = result.qpos_std[:a]
        qpos[s + a : e] = result.qpos[a:]  # the next window starts from this one's solution
        bias[s + a : e] = result.bias[a:]
        prior = result.next_prior
        solved_until = e
        warnings.extend(f"window {i + 1}: {w}" for w in result.warnings)
        iterations.append(sum(r.iterations for r in stages))  # every solve's count
        for r in stages:
            passes["linearizations"] += r.linearizations
            passes["evaluations"] += r.evaluations
            passes["knots_linearized"] += r.linearizations * (e - s - 2)
            passes["knots_evaluated"] += r.evaluations * (e - s - 2)
        converged.append(result.converged)
        heap.trim()  # the window's freed arrays: the sweep's memory stays what it holds
        i += 1
        if progress:
            progress(i, max(total, i))
        if last:
            break
        s += a
    assert bias is not None
    if no_mocap:
        warnings.append(unobserved_line(model, qpos, std, start_source(config)))
    full = build_problem(config, measurements, settings, t_ns, compiled)
    est, summary = finish(
        config, full, qpos, bias, std, start, iterations, converged, warnings, passes, kept_starts
    )
    return est, replace(
        summary, softness_fit=fitted, window_starts=window_starts, starts_tried=starts_tried
    )


def _next_anchor(k: int, step: int) -> int:
    """The first anchor (a multiple of `step` on the log's knot clock) after knot k."""
    return k - k % step + step


def _kinematic_start(
    config: Config,
    window: Mapping[str, Measurement],
    settings: Settings,
    t_ns: np.ndarray,
    compiled: tuple[mujoco.MjModel, dict[str, list[str]]],
    init_q: np.ndarray,
    init_b: np.ndarray,
) -> tuple[WindowResult, tuple[np.ndarray, np.ndarray]]:
    """The kinematic smoother's solution of a window, the physics solve's second start (its
    bias dims are the physics problem's first: no model-error offset)."""
    first = build_problem(config, window, replace(settings, method="kinematic"), t_ns, compiled)
    stage = solve_window(first, init_q, init_b[:, : first.nb], covariance=False)
    bias = init_b.copy()
    bias[:, : first.nb] = stage.bias
    return stage, (stage.qpos, bias)


@dataclass(frozen=True)
class _Joined:
    """A window of the sweep, for the backward pass: its first key, and the marginal prior
    it received (whose gain moves the previous window's kept keys)."""

    start: int
    prior: MarginalPrior | None


def softness_fitted(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    t_ns: np.ndarray,
    qpos0: np.ndarray | None = None,
    compiled: tuple[mujoco.MjModel, dict[str, list[str]]] | None = None,
) -> tuple[Settings, dict[str, float]]:
    """The settings every window of a physics estimate on the knots t_ns takes, and the fit
    (empty without one): with fit_softness = "first_window" and a config that does not give
    the softness (one that does is taken as calibrated), `_fit_softness` on the log's first
    fit_softness_s. qpos0: the initial trajectory on t_ns (default: from the measurements)."""
    if (
        settings.fit_softness != "first_window"
        or settings.method != "physics"
        or settings.sets_softness
    ):
        return settings, {}
    compiled = compiled or model_with_sensors(config)
    h = settings.h or float(compiled[0].opt.timestep)
    span = min(len(t_ns), round(settings.fit_softness_s / h))
    if qpos0 is None:
        qpos0 = initial_trajectory(compiled[0], measurements, t_ns[:span])
    return _fit_softness(config, measurements, settings, t_ns[:span], qpos0, compiled)


def _fit_softness(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    t_ns: np.ndarray,
    qpos0: np.ndarray,
    compiled: tuple[mujoco.MjModel, dict[str, list[str]]],
) -> tuple[Settings, dict[str, float]]:
    """fit_softness = "first_window": the factors on the model's own ε and κ that the physics
    and the mocap agree on over the knots t_ns (the log's first fit_softness_s:
    `solver.softness_fit.fit_softness`), folded into the settings every window then takes;
    the covariances consider their posterior σ."""
    window = {name: samples_within(m, t_ns[0], t_ns[-1]) for name, m in measurements.items()}
    problem = build_problem(config, window, settings, t_ns, compiled)
    fit, _ = fit_softness(problem, qpos0[: len(t_ns)], np.zeros((problem.T, problem.nb)))
    fitted = replace(
        settings,
        softness_eps_scale=settings.softness_eps_scale * fit.eps_scale,
        softness_kappa_scale=settings.softness_kappa_scale * fit.kappa_scale,
        model_softness_std=max(fit.sigma),
    )
    return fitted, {
        "eps_scale": fit.eps_scale,
        "kappa_scale": fit.kappa_scale,
        "eps_scale_sigma": fit.sigma[0],
        "kappa_scale_sigma": fit.sigma[1],
        "rounds": float(fit.rounds),
        "settled": float(fit.settled),
    }


def raw_estimate(
    config: Config, measurements: Mapping[str, Measurement], settings: Settings
) -> tuple[Estimate, Summary]:
    """The measurements alone (the `raw` method): mocap poses, markers fitted by Kabsch, and
    encoders, interpolated onto the knots (`initial_trajectory`); no bias, no covariance."""
    start = time.perf_counter()
    compiled = model_with_sensors(config)
    h = settings.h or float(compiled[0].opt.timestep)
    problem = build_problem(config, measurements, settings, knot_grid(measurements, h), compiled)
    qpos = initial_trajectory(problem.model, measurements, problem.t_ns)
    bias = np.zeros((problem.T, problem.nb))
    std = np.full((problem.T, problem.model.nv), np.nan)
    return finish(config, problem, qpos, bias, std, start, [], [], [], {})


def finish(
    config: Config,
    problem: Problem,
    qpos: np.ndarray,
    bias: np.ndarray,
    std: np.ndarray,
    start: float,
    iterations: list[int],
    converged: list[bool],
    warnings: list[str],
    passes: Mapping[str, int],
    kept_starts: Sequence[str] = (),
    qvel: np.ndarray | None = None,
) -> tuple[Estimate, Summary]:
    """The Estimate of a whole-log trajectory and its Summary (any method; qvel: a method's
    own velocity states, see `collect_estimate`)."""
    est = collect_estimate(problem, qpos, bias, std, config, qvel=qvel)
    if problem.settings.method == "physics":  # (a baseline's misfit is no news about the model)
        warnings = warnings + consistency_warnings(est, problem)
    summary = Summary(
        duration_s=(problem.t_ns[-1] - problem.t_ns[0]) / 1e9,
        knots=problem.T,
        h=problem.h,
        windows=len(iterations),
        iterations=iterations,
        converged=converged,
        cost_by_type=est.cost_by_type,
        largest_residuals=largest_residuals(est),
        wall_time_s=time.perf_counter() - start,
        warnings=warnings,
        model_error_mean={dof: float(np.mean(e)) for dof, e in est.model_error.items()},
        kept_starts=list(kept_starts),
        linearizations=passes.get("linearizations", 0),
        evaluations=passes.get("evaluations", 0),
        knots_linearized=passes.get("knots_linearized", 0),
        knots_evaluated=passes.get("knots_evaluated", 0),
    )
    return est, summary


WINDOW_MARGIN_NS = 1_000_000_000  # samples kept around a window: interpolation, held commands


def samples_within(m: Measurement, t0_ns: int, t1_ns: int) -> Measurement:
    """The samples of m within [t0, t1] ± WINDOW_MARGIN_NS (a window's problem needs no more)."""
    return m.between(t0_ns - WINDOW_MARGIN_NS, t1_ns + WINDOW_MARGIN_NS + 1)


# ---------------------------------------------------------------------------------------------
# initialization from the measurements


def initial_trajectory(
    model: mujoco.MjModel,
    measurements: Mapping[str, Measurement],
    t_ns: np.ndarray,
    filled: np.ndarray | None = None,
    measured_out: np.ndarray | None = None,
) -> np.ndarray:
    """(T, nq) q_k from mocap (poses, or markers fitted by Kabsch) and joint encoders.

    Knots without a measurement (a dropped first frame, occlusions) are interpolated between
    measured knots and held at the ends; unmeasured coordinates keep the model's home pose.
    filled (T,): set True at the knots where a measured coordinate was interpolated across a
    gap (an occlusion, a dropout), or held at an end for more than 2.5 of its stream's sample
    periods (a stream that starts late, or stops early).
    measured_out (T, nq): set True where a coordinate comes from a measurement at that knot.
    """
    T = len(t_ns)
    home = model.qpos0.copy()
    key = mujoco.mj_name2id(model, _OBJ.mjOBJ_KEY, "home")
    if key >= 0:
        home = model.key_qpos[key].copy()
    qpos = np.tile(home, (T, 1))
    measured = np.zeros((T, model.nq), dtype=bool)
    held_ns = np.zeros(model.nq)  # the longest hold at an end that is no gap, by coordinate
    tracked = []  # poses of bodies below a free joint: (element type, name, (T, 7) pose)
    for m in measurements.values():
        if not len(m):
            continue
        before = measured.any(axis=0)
        if m.kind in ("pose", "tf", "rigid_bodies"):
            values = interpolated_at_knots(m, t_ns)
            for e, name in enumerate(m.elements):
                _set_free_pose(model, qpos, measured, m.element_type, name, values[:, e])
                tracked.append((m.element_type, name, values[:, e]))
        elif m.kind == "markers":
            _fit_markers(model, qpos, measured, m, interpolated_at_knots(m, t_ns))
        elif m.kind == "joint_state":
            values = interpolated_at_knots(m, t_ns)
            for e, name in enumerate(m.elements):
                j = mujoco.mj_name2id(model, _OBJ.mjOBJ_JOINT, name)
                adr = model.jnt_qposadr[j]
                ok = np.isfinite(values[:, e, 0])
                qpos[ok, adr] = values[ok, e, 0]
                measured[ok, adr] = True
        period = np.median(np.diff(m.t_ns)) if len(m) > 1 else 0.0
        held_ns[measured.any(axis=0) & ~before] = 2.5 * period
    _free_poses_through_joints(model, qpos, measured, tracked)
    if measured_out is not None:
        measured_out[:] = measured
    _fill_gaps(model, qpos, measured)
    if unanchored(model, measurements):  # no mocap: the base from proprioception
        base_from_legs(model, qpos, measurements, t_ns)
    if filled is not None:
        filled[:] = _gap_knots(measured, t_ns, held_ns)
    return qpos


def _gap_knots(measured: np.ndarray, t_ns: np.ndarray, held_ns: np.ndarray) -> np.ndarray:
    """(T,) knots where a measured coordinate (a column of measured (T, nq)) is not measured:
    inside its measured span, or at an end held for longer than its held_ns."""
    after_first = np.maximum.accumulate(measured, axis=0)
    before_last = np.maximum.accumulate(measured[::-1], axis=0)[::-1]
    gap = ~measured & after_first & before_last
    for col in np.flatnonzero(measured.any(axis=0)):
        k0, k1 = np.flatnonzero(measured[:, col])[[0, -1]]
        if t_ns[k0] - t_ns[0] > held_ns[col]:
            gap[:k0, col] = True
        if t_ns[-1] - t_ns[k1] > held_ns[col]:
            gap[k1 + 1 :, col] = True
    return np.asarray(gap.any(axis=1))


def _free_joint_of(model: mujoco.MjModel, body: int) -> int:
    """qpos address of the free joint that moves `body` directly, or −1."""
    if model.body_jntnum[body] >= 1:
        j = model.body_jntadr[body]
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            return int(model.jnt_qposadr[j])
    return -1


def _set_free_pose(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    measured: np.ndarray,
    element_type: str,
    name: str,
    pose: np.ndarray,
) -> None:
    """Write a measured world pose (T, 7) of a body or site into its free joint's qpos."""
    if element_type == "site":
        site = mujoco.mj_name2id(model, _OBJ.mjOBJ_SITE, name)
        body = int(model.site_bodyid[site])
        local_pos, local_quat = model.site_pos[site], model.site_quat[site]
    else:
        body = mujoco.mj_name2id(model, _OBJ.mjOBJ_BODY, name)
        local_pos, local_quat = np.zeros(3), np.array([1.0, 0, 0, 0])
    adr = _free_joint_of(model, body)
    if adr < 0:
        return
    inv_local = np.zeros(4)
    mujoco.mju_negQuat(inv_local, local_quat)
    for k in np.flatnonzero(np.all(np.isfinite(pose), axis=1)):
        quat = np.zeros(4)
        mujoco.mju_mulQuat(quat, pose[k, 3:7], inv_local)  # R_body = R_site R_localᵀ
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, quat)
        qpos[k, adr : adr + 3] = pose[k, :3] - rot.reshape(3, 3) @ local_pos
        qpos[k, adr + 3 : adr + 7] = quat
        measured[k, adr : adr + 7] = True


def _free_poses_through_joints(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    measured: np.ndarray,
    tracked: list[tuple[str, str, np.ndarray]],
) -> None:
    """A free joint's pose where its own body is not measured (an occlusion, a dropout) from a
    tracked body below it whose joints up to it are measured (encoders): T_root =
    T_tracked · T_root→tracked⁻¹, the second by forward kinematics with the root at the
    origin — a humanoid's torso through its pelvis, not interpolated across the gap."""
    data = None
    for element_type, name, pose in tracked:
        if element_type == "site":
            site = mujoco.mj_name2id(model, _OBJ.mjOBJ_SITE, name)
            body = int(model.site_bodyid[site])
        else:
            site, body = -1, mujoco.mj_name2id(model, _OBJ.mjOBJ_BODY, name)
        chain, root = [], body  # the joints between the body and its free joint's body
        while root > 0 and _free_joint_of(model, root) < 0:
            chain += [int(model.jnt_qposadr[j]) for j in _joints_of(model, root)]
            root = int(model.body_parentid[root])
        adr = _free_joint_of(model, root) if root > 0 else -1
        if adr < 0 or root == body:
            continue
        knots = ~measured[:, adr] & np.all(np.isfinite(pose), axis=1)
        knots &= measured[:, chain].all(axis=1) if chain else True
        if not knots.any():
            continue
        if data is None:
            data = mujoco.MjData(model)
        for k in np.flatnonzero(knots):
            data.qpos[:] = qpos[k]
            data.qpos[adr : adr + 7] = [0, 0, 0, 1, 0, 0, 0]
            mujoco.mj_kinematics(model, data)
            if site >= 0:
                p_rel, R_rel = data.site_xpos[site], data.site_xmat[site].reshape(3, 3)
            else:
                p_rel, R_rel = data.xpos[body], data.xmat[body].reshape(3, 3)
            R_world = np.zeros(9)
            mujoco.mju_quat2Mat(R_world, pose[k, 3:7])
            R_root = R_world.reshape(3, 3) @ R_rel.T
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, R_root.reshape(-1))
            qpos[k, adr : adr + 3] = pose[k, :3] - R_root @ p_rel
            qpos[k, adr + 3 : adr + 7] = quat
            measured[k, adr : adr + 7] = True


def _joints_of(model: mujoco.MjModel, body: int) -> range:
    start = int(model.body_jntadr[body])
    return range(start, start + int(model.body_jntnum[body])) if start >= 0 else range(0)


def _fit_markers(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    measured: np.ndarray,
    m: Measurement,
    values: np.ndarray,
) -> None:
    """Kabsch fit of each free body's pose to its markers (≥ 3 visible) at every knot."""
    sites = [mujoco.mj_name2id(model, _OBJ.mjOBJ_SITE, n) for n in m.elements]
    bodies = {int(model.site_bodyid[s]) for s in sites}
    for body in bodies:
        adr = _free_joint_of(model, body)
        if adr < 0:
            continue
        cols = [i for i, s in enumerate(sites) if model.site_bodyid[s] == body]
        local = np.array([model.site_pos[sites[i]] for i in cols])  # (n, 3) in body frame
        for k in range(len(values)):
            world = values[k, cols, :3]
            ok = np.all(np.isfinite(world), axis=1)
            if ok.sum() < 3:
                continue
            R, p = _kabsch(local[ok], world[ok])
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, R.reshape(-1))
            qpos[k, adr : adr + 3] = p
            qpos[k, adr + 3 : adr + 7] = quat
            measured[k, adr : adr + 7] = True


def _kabsch(local: np.ndarray, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, p minimizing Σ‖R local_i + p − world_i‖²."""
    cl, cw = local.mean(axis=0), world.mean(axis=0)
    U, _, Vt = np.linalg.svd((local - cl).T @ (world - cw))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cw - R @ cl


def _fill_gaps(model: mujoco.MjModel, qpos: np.ndarray, measured: np.ndarray) -> None:
    """Interpolate unmeasured knots of measured coordinates; renormalize quaternions."""
    T = len(qpos)
    knots = np.arange(T)
    quat_adr = [
        model.jnt_qposadr[j] + (3 if model.jnt_type[j] == 0 else 0)
        for j in range(model.njnt)
        if model.jnt_type[j] in (0, 1)
    ]
    for adr in quat_adr:  # one sign along time, so that interpolation is on the short arc
        for k in range(1, T):
            if np.dot(qpos[k, adr : adr + 4], qpos[k - 1, adr : adr + 4]) < 0:
                qpos[k, adr : adr + 4] *= -1
    for col in range(model.nq):
        ok = measured[:, col]
        if ok.any() and not ok.all():
            qpos[~ok, col] = np.interp(knots[~ok], knots[ok], qpos[ok, col])
    for adr in quat_adr:
        qpos[:, adr : adr + 4] /= np.linalg.norm(qpos[:, adr : adr + 4], axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# the result


def collect_estimate(
    problem: Problem,
    qpos: np.ndarray,
    bias: np.ndarray,
    std: np.ndarray,
    config: Config,
    knots: Sequence[int] | None = None,
    residuals: bool = True,
    qvel: np.ndarray | None = None,
    dynamics: Dynamics | None = None,
) -> Estimate:
    """The Estimate of a trajectory qpos (T, nq) with IMU biases (T, nb) on problem's knots:
    v, a by finite differences, forces and impulses by the native analytic inverse (contact
    impulses balanced unless settings.contact_forces = "model": estimator.contact_forces),
    residuals of every factor. std: (T, nv) marginal standard deviations (NaN where unknown).

    knots: the knots whose forces and contacts are wanted (default: all; the others NaN, no
    contacts); residuals=False leaves the residuals out (a streaming update publishes knots,
    not a report); qvel: (T, nv) the knots' velocities where the method has its own (a filter's
    velocity state), NaN where it has none; else finite differences. dynamics: the native
    dynamics of a model equal to the problem's (a stream's updates: made once)."""
    model, h = problem.model, problem.h
    v = velocities(model, qpos, h)
    if qvel is not None:
        v = np.where(np.isnan(qvel), v, qvel)
    a = accelerations(v, h)
    dyn = dynamics or make_dynamics(model, "native")  # the problem's model, its softness applied
    qfrc = np.full((problem.T, model.nv), np.nan)
    constraints = []
    balance = (
        problem.settings.contact_forces == "balanced" and problem.settings.contact_force_std > 0
    )
    force_std = problem.settings.contact_force_std * model_weight(model)
    wanted = set(range(problem.T) if knots is None else knots)
    qfrc_known = u_known_along(problem, qpos, sorted(wanted))
    data = mujoco.MjData(model)
    for k in range(problem.T):
        if k not in wanted:
            constraints.append(_NO_CONSTRAINTS)
            continue
        inv = dyn.inverse(qpos[k], v[k], a[k])
        qfrc[k] = inv.qfrc_inverse
        c = inv.constraints
        if balance and 0 < k < problem.T - 1:  # (v, a at the end knots are not the motion's)
            data.qpos[:] = qpos[k]
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            residual = qfrc[k] - qfrc_known[k]
            c = balanced_constraints(model, data, c, residual, problem.known_sigma[k], force_std)
        constraints.append(c)
    imu_bias = {name: bias[:, problem.bias_of[name]] for name in problem.imu_streams}
    model_error = {}
    if problem.error_dofs.size:
        names = dof_names(model)
        offsets = bias[:, problem.bias_of[MODEL_ERROR]].T
        model_error = {names[dof]: e for dof, e in zip(problem.error_dofs, offsets, strict=True)}
    rows, cost_by_type = residuals_by_type(problem, qpos, bias) if residuals else ({}, {})
    return Estimate(
        t_ns=problem.t_ns,
        h=h,
        qpos=qpos,
        qvel=v,
        qacc=a,
        qfrc_inverse=qfrc,
        qfrc_known=qfrc_known,
        qpos_std=std,
        constraints=tuple(constraints),
        model_name=config.model_ref,
        imu_bias=imu_bias,
        model_error=model_error,
        residuals=rows,
        residual_labels=residual_labels(problem, rows),
        cost_by_type=cost_by_type,
    )


def residual_labels(problem: Problem, residuals: dict[str, np.ndarray]) -> dict[str, list[str]]:
    """What each row of `residuals_by_type` is: a sensor's element and component (its first
    slot's blocks, in order), the dof for physics and priors; "row j" where unknown."""
    dofs = dof_names(problem.model)
    labels: dict[str, list[str]] = {}
    for block in problem.blocks:
        if block.slot == 0:
            labels.setdefault(block.stream, []).extend(block.labels)
    out = {}
    for name, r in residuals.items():
        rows = dofs if r.shape[1] == len(dofs) and name not in labels else labels.get(name, [])
        out[name] = (
            list(rows) if len(rows) == r.shape[1] else [f"row {j}" for j in range(r.shape[1])]
        )
    return out


def row_label(est: Estimate, factor: str, j: int) -> str:
    """`"<factor> <row>"`: "mocap_torso torso_site position z", "physics root_z"."""
    labels = est.residual_labels.get(factor, [])
    return f"{factor} {labels[j] if j < len(labels) else f'row {j}'}"


def residuals_by_type(
    problem: Problem, qpos: np.ndarray, bias: np.ndarray
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Whitened residuals per knot, unweighted: "physics" (T, nv), "prior" (T, nv) and one
    (T, rows) array per stream, NaN where a knot has no such factor (and at both end knots);
    and the robust cost per factor type. A knot with several samples of a stream (slots)
    shows its first sample's residual on a row, the next one's where the first has none."""
    lin = Linearizer(problem)
    try:
        blocks = lin.blocks(lin.terms(qpos, False), bias, robust=False)
        cost = lin.bias_cost(bias)
    finally:
        lin.close()
    parts: dict[str, dict[int, list[np.ndarray]]] = {}
    for block in blocks:  # a pose stream's position and rotation rows together
        rows = parts.setdefault(block.name, {}).setdefault(block.slot, [])
        rows.append(np.where(block.valid, block.r, np.nan))
        cost[block.name] = cost.get(block.name, 0.0) + float(block.cost.sum())
    out = {}
    for name, slots in parts.items():
        # a later slot's j-th block is the first slot's j-th (a stream's position rows come
        # first; the rows only its first slot has, velocities, after them)
        (_, first), *more = sorted(slots.items())
        for _, rows in more:
            first = [
                np.where(np.isnan(f), r, f) if j < len(rows) else f
                for j, (f, r) in enumerate(zip(first, rows + first[len(rows) :], strict=True))
            ]
        out[name] = np.full((problem.T, sum(f.shape[1] for f in first)), np.nan)
        out[name][1:-1] = np.concatenate(first, axis=1)
    return out, cost


UNEXPLAINED_MEDIAN_SIGMA = 3.0  # median |whitened residual| of a factor type; Gaussian: 0.67


def consistency_warnings(est: Estimate, problem: Problem | None = None) -> list[str]:
    """Warnings when the model and the measurements do not fit each other.

    A residual row (of a factor type) whose median |whitened value| over time exceeds 3σ
    (0.67σ when the model and the noise settings are right; a median ignores occasional
    outliers) means a wrong model, an unmodeled contact or force, or a faulty sensor or noise
    setting. Names the factor, the row and the time of its largest residual, and for a physics
    row (with the problem) its dof and the setting most likely behind it (`likely_cause`).
    """
    out = []
    for name, r in est.residuals.items():
        magnitude = np.abs(r)
        rows = np.flatnonzero(np.isfinite(magnitude).any(axis=0))
        if not rows.size:
            continue
        medians = np.nanmedian(magnitude[:, rows], axis=0)  # per residual row, over time
        j = int(rows[np.argmax(medians)])
        median = float(medians.max())
        if median <= UNEXPLAINED_MEDIAN_SIGMA:
            continue
        k = int(np.nanargmax(magnitude[:, j]))
        t = (est.t_ns[k] - est.t_ns[0]) / 1e9
        what = "the motion (physics factors)" if name == "physics" else f"the {name} measurements"
        row = row_label(est, name, j).removeprefix(f"{name} ")
        cause = "wrong model, unmodeled contact or force, or a faulty sensor or noise setting?"
        if name == "physics" and problem is not None:
            cause = likely_cause(problem, j)
        out.append(
            f"the model does not explain {what}: median residual "
            f"{median:.1f}σ on {row} (largest {r[k, j]:+.0f}σ at {t:.2f} s) — {cause}"
        )
    return out


def likely_cause(problem: Problem, dof: int) -> str:
    """What most likely leaves a physics row unexplained over the whole log, by its dof: an
    actuated one the commands' force (actuator type, gains, units or mapping); a floating
    base's vertical or tilting dofs the contacts' softness or the masses; its horizontal and
    yaw dofs a mounting (a mocap marker or IMU placed other than the model says) or an
    unmodeled push; another unactuated dof the model's friction, damping or masses."""
    model = problem.model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    actuated = bool(np.any(moment_dense(model, data)[:, dof] != 0))
    joint = int(model.dof_jntid[dof])
    if actuated:
        return (
            "the commands' force through the actuators: check the actuator type and gains, "
            "the command units and the mapping (physfuse inspect --config: commands against "
            "efforts)"
        )
    if model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE:
        axis = dof - int(model.jnt_dofadr[joint])
        if axis in (2, 3, 4):  # z, roll, pitch: carried by the contacts
            return (
                "the contact softness or the masses: the robot rests at another depth than "
                "the model says (physfuse inspect --config: resting penetration; calibrate "
                "softness_eps_scale)"
            )
        return (
            "a mounting (a mocap marker or IMU placed other than the model says: the "
            "stream's mount) or an unmodeled push"
        )
    return "the model's friction, damping or masses on this joint, or an unmodeled force"


def largest_residuals(est: Estimate, n: int = 5) -> list[dict]:
    """The n largest whitened residuals: factor type, which row (labelled), when, value."""
    entries: list[dict[str, Any]] = []
    for name, r in est.residuals.items():
        mag = np.abs(np.nan_to_num(r, nan=0.0))
        for _ in range(n):
            k, j = np.unravel_index(np.argmax(mag), mag.shape)
            if mag[k, j] == 0:
                break
            entries.append(
                {
                    "factor": name,
                    "row": row_label(est, name, int(j)).removeprefix(f"{name} "),
                    "time_s": float((est.t_ns[k] - est.t_ns[0]) / 1e9),
                    "whitened": float(r[k, j]),
                }
            )
            mag[max(0, k - 10) : k + 10, j] = 0  # the next one elsewhere
    entries.sort(key=lambda e: -abs(e["whitened"]))
    return entries[:n]

"""One long log across Ray workers: `physfuse estimate LOG --chunk S [--workers N]`.

The log's knot grid is cut into chunks of S seconds; each chunk is estimated as a Ray task
on its slice of the grid widened by `overlap` seconds on both sides (the measurements there
too), and the chunks are joined by keeping each one's own knots: at a join the estimate
comes from a chunk that has seen `overlap` seconds of log past it, where the influence of
the chunk's edge has died out. The physics' contact softness is fitted once, on the log's
start (`run.softness_fitted`), and every chunk takes it. Without mocap every chunk starts at
the start pose: each is then turned about world z and shifted to continue the one before
(`placed_after`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from estimator.batch import estimate
from estimator.config import load_config
from estimator.errors import ConfigError, PhysfuseError
from estimator.estimate import Estimate
from estimator.fleet import as_task, ray_session
from estimator.io.logs import Measurement
from estimator.knots import knot_grid
from estimator.leg_odometry import free_base, unanchored
from estimator.rotations import heading, quat_mul
from estimator.run import Summary, largest_residuals, samples_within, softness_fitted
from estimator.settings import Settings

OVERLAP_S = 2.0  # of log on each side of a chunk that its estimate sees and the join drops
SMOOTHERS = ("physics", "kinematic")  # the methods on a knot grid a chunk can be given


def estimate_chunked(
    config_path: Path,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    chunk_s: float,
    overlap_s: float = OVERLAP_S,
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Estimate, Summary]:
    """The log's estimate from chunks of `chunk_s` solved as Ray tasks and joined."""
    import ray

    start = time.perf_counter()
    check(settings, chunk_s, overlap_s)
    config = load_config(config_path)
    h = settings.h or float(config.load_model().opt.timestep)
    t_ns = knot_grid(measurements, h)
    knots, n, margin = len(t_ns), max(8, round(chunk_s / h)), round(overlap_s / h)
    settings, fitted = softness_fitted(config, measurements, settings, t_ns)
    cuts = [(a, min(a + n, knots)) for a in range(0, knots, n)]
    with ray_session(workers, address):
        shared = ray.put(dict(measurements))
        task = as_task(estimate_chunk)
        refs = []
        for a, b in cuts:
            lo, hi = max(0, a - margin), min(knots, b + margin)
            refs.append(task.remote(str(config_path), shared, settings, t_ns[lo:hi]))
        parts: list[tuple[Estimate, Summary, slice]] = []
        for i, ((a, b), ref) in enumerate(zip(cuts, refs, strict=True)):
            try:
                est, summary = ray.get(ref)
            except ray.exceptions.RayError as err:  # the chunk's error, or its workers died
                cause = getattr(err, "cause", None) or err
                line = (str(cause).strip().splitlines() or [type(cause).__name__])[-1]
                span = f"{(t_ns[a] - t_ns[0]) / 1e9:.3f}–{(t_ns[b - 1] - t_ns[0]) / 1e9:.3f} s"
                raise PhysfuseError(f"chunk {i + 1} ({span} of the log): {line}") from None
            lo = max(0, a - margin)
            parts.append((est, summary, slice(a - lo, b - lo)))
            if progress:
                progress(i + 1, len(cuts))
    model = config.load_model()
    if unanchored(model, measurements):  # x, y, yaw: each chunk's own, from the start pose
        for i in range(1, len(parts)):
            (prev, _, kept_prev), (est, summary, kept) = parts[i - 1], parts[i]
            join_at = kept_prev.stop - kept_prev.start  # knot cuts[i][0]: in both chunks
            est = placed_after(model, est, kept.start, prev, kept_prev.start + join_at)
            parts[i] = (est, summary, kept)
    est = join([(e, kept) for e, _, kept in parts])
    summaries = [s for _, s, _ in parts]
    offsets = [a for a, _ in cuts]
    summary = Summary(
        duration_s=(est.t_ns[-1] - est.t_ns[0]) / 1e9,
        knots=est.T,
        h=est.h,
        windows=sum(s.windows for s in summaries),
        iterations=[i for s in summaries for i in s.iterations],
        converged=[c for s in summaries for c in s.converged],
        cost_by_type=est.cost_by_type,
        largest_residuals=largest_residuals(est),
        wall_time_s=time.perf_counter() - start,
        warnings=[f"chunk {i + 1}: {w}" for i, s in enumerate(summaries) for w in s.warnings],
        linearizations=sum(s.linearizations for s in summaries),
        evaluations=sum(s.evaluations for s in summaries),
        knots_linearized=sum(s.knots_linearized for s in summaries),
        knots_evaluated=sum(s.knots_evaluated for s in summaries),
        model_error_mean={
            k: float(np.mean([s.model_error_mean[k] for s in summaries]))
            for k in summaries[0].model_error_mean
        },
        kept_starts=[k for s in summaries for k in s.kept_starts],
        starts_tried=[k for s in summaries for k in s.starts_tried],
        softness_fit=fitted,
        window_starts=sorted(
            {
                max(0, a - margin) + w
                for a, s in zip(offsets, summaries, strict=True)
                for w in s.window_starts
            }
        ),
    )
    return est, summary


def check(settings: Settings, chunk_s: float, overlap_s: float) -> None:
    """Raises ConfigError naming what --chunk cannot take."""
    if chunk_s <= 0 or overlap_s < 0:
        raise ConfigError(
            f"--chunk {chunk_s:g}, --chunk-overlap {overlap_s:g}: expected s > 0 and s ≥ 0"
        )
    if settings.method not in SMOOTHERS:
        raise ConfigError(
            f"--chunk cuts the smoothers' knot grid ({', '.join(SMOOTHERS)}); --method "
            f"{settings.method} estimates a log in one pass: leave --chunk out"
        )


def estimate_chunk(
    config_path: str, measurements: dict[str, Measurement], settings: Settings, knots: Any
) -> tuple[Estimate, Summary]:
    """One chunk, in a Ray worker: the estimate on `knots` from the measurements there."""
    config = load_config(config_path)
    window = {k: samples_within(m, int(knots[0]), int(knots[-1])) for k, m in measurements.items()}
    return estimate(config, window, settings, knots=np.asarray(knots))


def placed_after(
    model: mujoco.MjModel, est: Estimate, k: int, prev: Estimate, k_prev: int
) -> Estimate:
    """`est` turned about world z by ψ and shifted horizontally by t so that its free base
    at knot k has prev's x, y and heading at knot k_prev: q ← R_z(ψ) ⊗ q, p ← R_z(ψ) p + t on
    every free joint, the free joints' world-frame rows (linear velocity, acceleration, force)
    and the contacts turned with them; the physics is unchanged (gravity along z, a level
    floor). σ of x, y and yaw grows by prev's there. (The whitened residuals stay as solved.)"""
    _, adr = free_base(model)
    psi = float(
        heading(prev.qpos[k_prev, adr + 3 : adr + 7]) - heading(est.qpos[k, adr + 3 : adr + 7])
    )
    c, s = np.cos(psi), np.sin(psi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = prev.qpos[k_prev, adr : adr + 3] - R @ est.qpos[k, adr : adr + 3]
    t[2] = 0.0
    q_z = np.array([np.cos(psi / 2), 0.0, 0.0, np.sin(psi / 2)])
    qpos, std = est.qpos.copy(), est.qpos_std.copy()
    qvel, qacc = est.qvel.copy(), est.qacc.copy()
    qfrc_inverse, qfrc_known = est.qfrc_inverse.copy(), est.qfrc_known.copy()
    base_dof = -1
    for j in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
        a, dof = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        base_dof = dof if a == adr else base_dof
        qpos[:, a : a + 3] = qpos[:, a : a + 3] @ R.T + t
        qpos[:, a + 3 : a + 7] = quat_mul(q_z, qpos[:, a + 3 : a + 7])
        # a free joint's translational dofs are in the world frame
        for x in (qvel, qacc, qfrc_inverse, qfrc_known):
            x[:, dof : dof + 3] = x[:, dof : dof + 3] @ R.T
        variance = std[:, dof : dof + 2] ** 2  # x, y: R diag(σ²) Rᵀ's diagonal
        std[:, dof : dof + 2] = np.sqrt(variance @ (R[:2, :2] ** 2).T)
    for d in (base_dof, base_dof + 1, base_dof + 5):  # x, y and (about the body z) yaw
        std[:, d] = np.hypot(std[:, d], prev.qpos_std[k_prev, d])
    constraints = tuple(
        replace(
            each,
            contacts=replace(
                each.contacts, pos=each.contacts.pos @ R.T + t, frame=each.contacts.frame @ R.T
            ),
        )
        for each in est.constraints
    )
    return replace(
        est,
        qpos=qpos,
        qvel=qvel,
        qacc=qacc,
        qfrc_inverse=qfrc_inverse,
        qfrc_known=qfrc_known,
        qpos_std=std,
        constraints=constraints,
    )


def join(parts: list[tuple[Estimate, slice]]) -> Estimate:
    """One estimate from each part's `kept` knots, in order; costs summed over the parts
    (each over its own span, overlaps included)."""

    def cat(arrays: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([x[kept] for x, (_, kept) in zip(arrays, parts, strict=True)])

    ests = [e for e, _ in parts]
    first = parts[0][0]
    costs: dict[str, float] = {}
    for e, _ in parts:
        for k, v in e.cost_by_type.items():
            costs[k] = costs.get(k, 0.0) + v
    return replace(
        first,
        t_ns=cat([e.t_ns for e in ests]),
        qpos=cat([e.qpos for e in ests]),
        qvel=cat([e.qvel for e in ests]),
        qacc=cat([e.qacc for e in ests]),
        qfrc_inverse=cat([e.qfrc_inverse for e in ests]),
        qfrc_known=cat([e.qfrc_known for e in ests]),
        qpos_std=cat([e.qpos_std for e in ests]),
        constraints=tuple(c for e, kept in parts for c in e.constraints[kept]),
        imu_bias={k: cat([e.imu_bias[k] for e in ests]) for k in first.imu_bias},
        model_error={k: cat([e.model_error[k] for e in ests]) for k in first.model_error},
        residuals={k: cat([e.residuals[k] for e in ests]) for k in first.residuals},
        cost_by_type=costs,
    )

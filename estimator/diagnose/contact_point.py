"""Where on the robot an unmodeled contact acts: the body and the point of its surface whose
Jacobian best explains the residual (collision isolation as in Haddadin et al., "Robot
Collisions: A Survey on Detection, Isolation, and Identification", T-RO 2017, §V; the
contact particle filter of Manuelli and Tedrake, IROS 2016, samples the surface likewise).

A force F at a point p of body b enters the residual as J_pᵀ F (J_p: the translational
Jacobian of p moving with b) — the same force on b's centre of mass plus the moment
(p − c) × F. `detect` fits the force at the centre of mass, which cannot tell a small link
from its neighbour when a collision lands off their centres (Go2: an obstacle against the
hip, put on the thigh). Here, over the event's knots and for each hypothesis — each of the
event's `CANDIDATES` likeliest bodies, at its centre of mass and at `POINTS` points on each of
its collision geoms' surfaces (fixed in the body) —

    I_p = Σ_k A_pᵀ S_k⁻¹ A_p + I/F₀²,   g_p = Σ_k A_pᵀ S_k⁻¹ W r_k,   A_p = W J_pᵀ

(W, S, r, F₀ as in `unmodeled`), the likelihood ratio g_pᵀ I_p⁻¹ g_p, a surface point only
where its force F̂_p = I_p⁻¹ g_p presses into the surface (F̂_p · n < 0, n the outward
normal: a contact pushes). A body's evidence is the mean likelihood exp(ratio / 2) over its
hypotheses, half the prior on its centre of mass and half spread over its surface points
(the best of many chance fits does not make a body with many points win). The likeliest
body is the event's; its best hypothesis the contact point (`Event.point`, world frame at
the event's middle knot; None at the centre of mass), whose F̂_p is the event's force.
"""

from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np
from scipy.special import logsumexp

from estimator.diagnose.detect import Detection, Event
from estimator.diagnose.unmodeled import CONTACT_MARGIN_M, FORCE_PRIOR, knot_residual, with_margin
from estimator.estimate import Estimate
from physics.model import weight

CANDIDATES = 4  # bodies tried, the likeliest by the centre-of-mass fit
POINTS = 64  # per geom, spread over its surface (a Fibonacci sphere of directions)


def contact_points(
    model: mujoco.MjModel,
    est: Estimate,
    sigma: np.ndarray,
    contact_force_std: float,
    detection: Detection,
    contact_margin: float = CONTACT_MARGIN_M,
    residual: np.ndarray | None = None,
) -> list[Event]:
    """The detection's events, each unmodeled contact moved to the body and point that best
    explain it (module docstring). residual: (T, nv) the residual `detection` was made from
    if not the physics one (`unmodeled_forces`'s)."""
    model = with_margin(model, contact_margin)
    data = mujoco.MjData(model)
    return [
        _located(model, data, est, sigma, contact_force_std, detection, e, residual)
        if e.kind == "unmodeled contact"
        else e
        for e in detection.events
    ]


def _located(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    est: Estimate,
    sigma: np.ndarray,
    contact_force_std: float,
    detection: Detection,
    e: Event,
    residual: np.ndarray | None,
) -> Event:
    forces = detection.forces
    knots = np.flatnonzero((forces.t_ns >= e.start_ns) & (forces.t_ns <= e.end_ns))
    if not knots.size:
        return e
    likeliest = sorted(e.candidates, key=lambda name: -e.candidates[name])[:CANDIDATES]
    bodies = [int(forces.body_ids[forces.bodies.index(name)]) for name in likeliest]
    middle = int(knots[len(knots) // 2])
    _kinematics(model, data, est.qpos[middle])
    # hypotheses: (body, point in the body frame, outward normal in the body frame or None)
    hypotheses = [(b, np.zeros(3), None) for b in bodies]  # the centre of mass: xipos
    for b in bodies:
        hypotheses += [(b, p, n) for p, n in _surface(model, data, b)]
    P = len(hypotheses)
    info, grad = np.zeros((P, 3, 3)), np.zeros((P, 3))
    jacp = np.zeros((3, model.nv))
    for k in knots:
        r = None if residual is None else residual[k]
        knot = knot_residual(model, data, est, sigma, int(k), contact_force_std, r)
        if knot is None:
            continue
        A = np.zeros((len(knot.w), 3 * P))
        for i, (b, p, n) in enumerate(hypotheses):
            mujoco.mj_jac(model, data, jacp, None, _world(data, b, p, n is None), b)
            A[:, 3 * i : 3 * i + 3] = jacp.T[knot.known] * knot.w[:, None]
        S_inv_A = np.linalg.solve(knot.S, A)
        info += np.einsum("mpi,mpj->pij", A.reshape(-1, P, 3), S_inv_A.reshape(-1, P, 3))
        grad += (S_inv_A.T @ knot.r).reshape(P, 3)
    info += np.eye(3) / (FORCE_PRIOR * weight(model)) ** 2
    F = np.linalg.solve(info, grad[..., None])[..., 0]
    ratio = np.einsum("pi,pi->p", grad, F)
    _kinematics(model, data, est.qpos[middle])
    for i, (b, _, n) in enumerate(hypotheses):
        if n is not None and F[i] @ (data.xmat[b].reshape(3, 3) @ n) >= 0.0:
            ratio[i] = -np.inf  # it would pull on the surface
    body = np.array([b for b, _, _ in hypotheses])
    centre = np.array([n is None for _, _, n in hypotheses])
    evidence = {
        b: logsumexp(
            [
                np.log(0.5) + ratio[centre & (body == b)][0] / 2,
                np.log(0.5)
                + logsumexp(ratio[~centre & (body == b)] / 2)
                - np.log(max(1, np.sum(~centre & (body == b)))),
            ]
        )
        for b in bodies
    }
    b = max(evidence, key=evidence.__getitem__)
    best = int(np.argmax(np.where(body == b, ratio, -np.inf)))
    _, p, n = hypotheses[best]
    index = forces.body_ids.tolist().index(b)
    name = forces.bodies[index]
    cov = detection.cov[index] * detection.window / len(knots)
    point = None if n is None else _world(data, b, p, False)
    return replace(e, target=name, force=F[best], force_cov=cov, point=point)


def _kinematics(model: mujoco.MjModel, data: mujoco.MjData, qpos: np.ndarray) -> None:
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)


def _world(data: mujoco.MjData, b: int, p: np.ndarray, centre_of_mass: bool) -> np.ndarray:
    if centre_of_mass:
        return data.xipos[b].copy()
    return data.xpos[b] + data.xmat[b].reshape(3, 3) @ p


def _surface(model: mujoco.MjModel, data: mujoco.MjData, b: int) -> list[tuple]:
    """Points on body b's collision geoms (body frame) with their outward normals: where rays
    from `POINTS` directions around each geom's centre, cast back at it, meet it (primitive
    geoms; a mesh gives none)."""
    out = []
    R_b = data.xmat[b].reshape(3, 3)
    i = np.arange(POINTS) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / POINTS), np.pi * (1 + 5**0.5) * i
    directions = np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1
    )
    normal = np.zeros(3)
    for g in np.flatnonzero(model.geom_bodyid == b):
        if not (model.geom_contype[g] | model.geom_conaffinity[g]):
            continue
        centre, reach = data.geom_xpos[g], 2.0 * float(model.geom_rbound[g]) + 0.01
        for u in directions:
            start = centre + reach * u
            x = mujoco.mju_rayGeom(
                centre, data.geom_xmat[g], model.geom_size[g], start, -u,
                int(model.geom_type[g]), normal,
            )  # fmt: skip
            if x >= 0:
                point = start - x * u
                out.append((R_b.T @ (point - data.xpos[b]), R_b.T @ normal))
    return out

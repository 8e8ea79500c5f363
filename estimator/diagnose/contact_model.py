"""Unmodeled forces that a modeled contact explains: the contact's model is off, not a new
contact.

An event's force F on body b (`detect`: fitted over its interval, covariance Σ from the log's
own spread, less the body's usual offset) against one unknown: an error δ in the normal force
of b's modeled contacts over the same knots (each contact's the same). Through the physics
residual δ reads as a force F = d δ on b's centre of mass,

    d = (Σ_k I_kb)⁻¹ Σ_k A_bᵀ S_k⁻¹ a_k,   a_k = W Σ_c J_n,cᵀ

(I, A_b, S, W as in `unmodeled`; the knots where b touches something). When F is along d
within its uncertainty — the part of F off that line, χ²_⊥ = FᵀΣ⁻¹F − (dᵀΣ⁻¹F)² / dᵀΣ⁻¹d,
below the χ²(2) quantile at `NORMAL_P` — the simpler explanation stands: the event is a
model error of that contact (its softness, stiffness or the surface's height: the normal
force it gives is off by δ̂ = dᵀΣ⁻¹F / dᵀΣ⁻¹d). On a single hinge pressing its tip on the
floor every force is of this kind (one dof sees one direction); a push across a standing
foot is not.

After the contact point is found (`contact_point`), an unmodeled contact that acts within
`AT_CONTACT_M` of where its body touches something during it is that contact's force off in
every direction (`contact_force_errors`): a touchdown or lift-off a knot off the estimate's,
friction the model does not give.
"""

from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np
from scipy.stats import chi2

from estimator.diagnose.detect import Detection, Event
from estimator.diagnose.unmodeled import (
    CONTACT_MARGIN_M,
    knot_residual,
    with_margin,
)
from estimator.estimate import Estimate

NORMAL_P = 0.99  # the free force must beat the contact's normal force error at this level
AT_CONTACT_M = 0.03  # a force located this near a body's contact is that contact's
MODEL_ERROR = "model error"


def contact_model_errors(
    model: mujoco.MjModel,
    est: Estimate,
    sigma: np.ndarray,
    contact_force_std: float,
    detection: Detection,
    contact_margin: float = CONTACT_MARGIN_M,
) -> list[Event]:
    """The detection's events with each unmodeled contact that a touching body's contact
    normal force explains (module docstring) turned into a "model error" event: target
    "contact <body>–<what it touches>", force (1,) δ̂ [N] (positive: the model's contact pushes
    too little) with its variance."""
    model = with_margin(model, contact_margin)
    data = mujoco.MjData(model)
    threshold = float(chi2.ppf(NORMAL_P, 2))
    out = []
    for e in detection.events:
        if e.kind == "unmodeled contact":
            e = _as_contact_error(
                model, data, est, sigma, contact_force_std, detection, e, threshold
            )
        out.append(e)
    return out


def _as_contact_error(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    est: Estimate,
    sigma: np.ndarray,
    contact_force_std: float,
    detection: Detection,
    e: Event,
    threshold: float,
) -> Event:
    forces = detection.forces
    b = forces.bodies.index(e.target)
    body = int(forces.body_ids[b])
    knots = np.flatnonzero((forces.t_ns >= e.start_ns) & (forces.t_ns <= e.end_ns))
    jacp = np.zeros((3, model.nv))
    along = np.zeros(3)  # Σ A_bᵀ S⁻¹ a
    touching = 0
    others: dict[str, int] = {}
    for k in knots:
        knot = knot_residual(model, data, est, sigma, int(k), contact_force_std)
        if knot is None:
            continue
        a = np.zeros(len(knot.w))
        for i, (g1, g2) in enumerate(knot.contacts.geom):
            pair = (int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2]))
            if body not in pair:
                continue
            a += knot.J_c[i][0] * knot.w  # the normal row, whitened
            geom = int(g2) if pair[0] == body else int(g1)  # the other side's
            name = model.geom(geom).name or model.body(model.geom_bodyid[geom]).name or "world"
            others[name] = others.get(name, 0) + 1
        if not a.any():
            continue
        touching += 1
        mujoco.mj_jac(model, data, jacp, None, data.xipos[body], body)
        A_b = jacp.T[knot.known] * knot.w[:, None]
        along += A_b.T @ np.linalg.solve(knot.S, a)
    if touching < max(1, len(knots) // 2):
        return e  # b is not in contact for most of the event
    d = np.linalg.solve(forces.info[knots, b].sum(axis=0), along)
    F = e.force - detection.mean[b]
    Si_F, Si_d = np.linalg.solve(e.force_cov, F), np.linalg.solve(e.force_cov, d)
    dd = float(d @ Si_d)
    if dd <= 0.0 or float(F @ Si_F) - float(d @ Si_F) ** 2 / dd >= threshold:
        return e  # a force the contact cannot give: an unmodeled contact
    return replace(
        e,
        kind=MODEL_ERROR,
        target=f"contact {e.target}–{max(others, key=lambda n: others[n])}",
        component="normal force (softness, stiffness or the surface's height)",
        force=np.array([float(d @ Si_F) / dd]),
        force_cov=np.array([[1.0 / dd]]),
    )


def contact_force_errors(
    model: mujoco.MjModel,
    est: Estimate,
    events: list[Event],
    contact_margin: float = CONTACT_MARGIN_M,
) -> list[Event]:
    """`events` with each unmodeled contact located (`contact_point`) within
    `AT_CONTACT_M` of where its body touches something during it turned into a "model
    error" of that contact: its force off by the event's force, in every direction — a
    touchdown or lift-off a knot off its estimate, friction the model does not give (the
    trotting quadruped's foot asking for 330 N for 50 ms as it lifts off and lands again).
    Target "contact <body>–<what it touches>", force (3,) world frame [N]."""
    model = with_margin(model, contact_margin)
    data = mujoco.MjData(model)
    return [
        _at_contact(model, data, est, e)
        if e.kind == "unmodeled contact" and e.point is not None
        else e
        for e in events
    ]


def _at_contact(model: mujoco.MjModel, data: mujoco.MjData, est: Estimate, e: Event) -> Event:
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, e.target)
    if body < 0:  # an unnamed body ("body N"): left as it is
        return e
    knots = np.flatnonzero((est.t_ns >= e.start_ns) & (est.t_ns <= e.end_ns))
    nearest, other = np.inf, ""
    for k in knots:
        data.qpos[:] = est.qpos[k]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        for c in data.contact[: data.ncon]:
            pair = (int(model.geom_bodyid[c.geom1]), int(model.geom_bodyid[c.geom2]))
            if body not in pair:
                continue
            distance = float(np.linalg.norm(c.pos - e.point))
            if distance < nearest:
                geom = int(c.geom2) if pair[0] == body else int(c.geom1)
                other = model.geom(geom).name or model.body(model.geom_bodyid[geom]).name
                nearest = distance
    if nearest > AT_CONTACT_M:
        return e
    return replace(
        e,
        kind=MODEL_ERROR,
        target=f"contact {e.target}–{other or 'world'}",
        component="contact force (timing, friction or softness)",
    )

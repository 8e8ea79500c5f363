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

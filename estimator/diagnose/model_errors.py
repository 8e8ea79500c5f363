"""Model errors named by a parameter: each body's mass.

A body whose true mass is m + δ moves, in the model of mass m, as if an unmodeled force
F_k = δ (g − a_k) acted on its centre of mass (a_k its acceleration, g gravity; the inertia
that scales with the mass adds a moment, left out). With `unmodeled`'s per-knot information
I_kb and gradient g_kb, δ's log-likelihood over the knots is Σ_k (g_kbᵀ w_k δ −
½ w_kᵀ I_kb w_k δ²), w_k = g − a_k, so

    δ̂ = Σ_k g_kbᵀ w_k / Σ_k w_kᵀ I_kb w_k

over the knots outside every event found (a push is not a mass), before the first sensor
fault (the estimate is off after it) and not outliers (`detect.outliers`). The residuals of
a smoother are correlated in time, so δ̂'s σ is taken from the spread of the estimates over
blocks of `BLOCK_S` (batch means), at least Σ wᵀIw's. A body with |δ̂| / σ beyond the
two-sided Gaussian quantile for the false-alarm rate (the rate × the log's minutes, at most
one, spread over the bodies) is off; of those, the one whose error explains the residual
best (its likelihood ratio δ̂² Σ wᵀIw) is the log's "model error": target the body,
component "mass", size δ̂ [kg] ± σ (positive: heavier than the model says — a payload), the
others as its candidates (bodies next to it on a chain give nearly the same gravity torques:
Panda with 0.5 kg on its hand, link7's and link6's fits explain the residual within 0.5% as
well).

On an arm every joint's torque is known and the fit is sharp (Panda, 3 s at 2 ms knots, 0.5
kg in its hand: +0.49 ± 0.07 kg; `tests/test_model_errors.py`). On a robot standing on soft
contacts it is coarse: the estimate's feet sink a little deeper and the model's contacts
carry part of the extra weight, and what is left the residual allows the contact forces' σ_f
for (Go2 with 2 kg on its base, 3 s: +1.1 ± 0.46 kg, not reported; 10 s with the condition's
5% errors: σ 0.22–0.34 kg per body, the humanoid's legs and trunk 1.7–3.4 kg; H1's torso
1.95 kg light: the pelvis's −2.25 ± 0.49 kg, the torso second).
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.stats import norm

from estimator.diagnose.contact_model import MODEL_ERROR
from estimator.diagnose.detect import DetectorSettings, Event, outliers, unexplained
from estimator.diagnose.unmodeled import UnmodeledForces
from estimator.estimate import Estimate

BLOCK_S = 0.5  # batch means: blocks this long
MIN_BLOCKS = 4
EVENT_MARGIN_S = 0.1  # knots this near an event are left out too


def mass_errors(
    model: mujoco.MjModel,
    est: Estimate,
    forces: UnmodeledForces,
    events: list[Event],
    settings: DetectorSettings | None = None,
) -> list[Event]:
    """The bodies whose mass the log says is off (module docstring); `events`: those found
    so far (their knots, and every knot after the first sensor fault, are left out)."""
    settings = settings or DetectorSettings()
    T, B = forces.grad.shape[:2]
    h = est.h
    used = _quiet_knots(est, forces, events)
    used[:2] = used[-2:] = False  # no acceleration there
    blocks = np.arange(T) // max(1, round(BLOCK_S / h))
    if len(np.unique(blocks[used])) < MIN_BLOCKS:
        return []
    # one test per body and log: at the rate's probability for a minute of log at most (an
    # hour-long log is not allowed sixty)
    minutes = min((est.t_ns[-1] - est.t_ns[0]) / 60e9, 1.0)
    p = min(settings.false_alarms_per_min * minutes / max(B, 1), 1.0)
    threshold = float(norm.isf(p / 2.0))
    com = _centres_of_mass(model, est)
    acc = np.zeros_like(com)
    acc[1:-1] = (com[2:] - 2.0 * com[1:-1] + com[:-2]) / h**2
    fits = {}  # body → (δ̂, σ, likelihood ratio)
    for b, body in enumerate(forces.bodies):
        w = model.opt.gravity - acc[:, forces.body_ids[b]]  # (T, 3)
        num = np.einsum("ki,ki->k", forces.grad[:, b], w)
        den = np.einsum("ki,kij,kj->k", w, forces.info[:, b], w)
        fit = _batch_means(num[used], den[used], blocks[used])
        if fit is not None and abs(fit[0]) > threshold * fit[1]:
            fits[body] = (*fit, fit[0] ** 2 * float(den[used].sum()))
    if not fits:
        return []
    # one mass error: the body whose error explains the residual best (bodies near it on the
    # chain give nearly the same gravity torques; they are its candidates)
    best = max(fits, key=lambda body: fits[body][2])
    delta, sigma, _ = fits[best]
    return [
        Event(
            kind=MODEL_ERROR,
            start_ns=int(est.t_ns[0]),
            end_ns=int(est.t_ns[-1]),
            detected_ns=int(est.t_ns[-1]),
            target=best,
            force=np.array([delta]),
            force_cov=np.array([[sigma**2]]),
            score=abs(delta) / sigma / threshold,
            component="mass",
            candidates={body: fit[2] for body, fit in fits.items()},
        )
    ]


def _quiet_knots(est: Estimate, forces: UnmodeledForces, events: list[Event]) -> np.ndarray:
    """(T,) the knots outside every event (± `EVENT_MARGIN_S`), before the first sensor
    fault, with a physics residual and not outliers."""
    t = est.t_ns
    used = np.isfinite(forces.misfit) & ~outliers(unexplained(forces))
    margin = round(EVENT_MARGIN_S * 1e9)
    for e in events:
        if e.kind == "sensor fault" and not e.explained_by:
            used &= t < e.start_ns - margin
        else:
            used &= (t < e.start_ns - margin) | (t > e.end_ns + margin)
    return used


def _batch_means(
    num: np.ndarray, den: np.ndarray, blocks: np.ndarray
) -> tuple[float, float] | None:
    """δ̂ = Σ num / Σ den and its σ from the blocks' own estimates (at least 1/√Σ den)."""
    total = float(den.sum())
    if total <= 0.0:
        return None
    delta = float(num.sum()) / total
    ids = np.unique(blocks)
    n = np.array([num[blocks == i].sum() for i in ids])
    d = np.array([den[blocks == i].sum() for i in ids])
    keep = d > 0.0
    n, d = n[keep], d[keep]
    if len(d) < MIN_BLOCKS:
        return None
    # the weighted batch-means variance of a ratio estimator: Σ (n_i − δ̂ d_i)² / (Σ d)²
    spread = float(((n - delta * d) ** 2).sum()) / total**2 * len(d) / (len(d) - 1)
    return delta, float(np.sqrt(max(spread, 1.0 / total)))


def _centres_of_mass(model: mujoco.MjModel, est: Estimate) -> np.ndarray:
    """(T, nbody, 3) every body's centre of mass at each knot."""
    data = mujoco.MjData(model)
    out = np.zeros((len(est.t_ns), model.nbody, 3))
    for k in range(len(est.t_ns)):
        data.qpos[:] = est.qpos[k]
        mujoco.mj_kinematics(model, data)
        out[k] = data.xipos
    return out

"""Paper Fig. 2: forward vs inverse impulses of the single-joint mechanism under random control.

The mechanism (Fig. 1 left) has dry friction in its joint and a frictional contact with the
ground. It is simulated with the forward dynamics — the reference path's GPGS solver — while
random controls perturb it; at every step the inverse dynamics recover the impulses from
(q, v, v') alone. The paper reports that the two curves agree within 1e-5.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from physics.dynamics import make_dynamics
from physics.model import load_model
from physics.reproduce.common import machine, print_table, write_json

_T = mujoco.mjtConstraint


def simulate(
    path: str, duration: float, seed: int, iterations: int, tolerance: float
) -> dict[str, np.ndarray]:
    """Run `path`'s forward dynamics and its inverse at every step.

    Returns time (n,), forward and inverse friction-loss impulse (n,), normal contact impulse
    (n,) and the control (n,), all in SI units (impulses in N·s).
    """
    m = load_model("single_joint")
    dyn = make_dynamics(m, path)  # type: ignore[arg-type]
    h = dyn.h
    rng = np.random.default_rng(seed)
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home")
    qpos = (m.key_qpos[key] if key >= 0 else m.qpos0).copy()
    qvel = np.zeros(m.nv)
    lo, hi = m.actuator_ctrlrange[0]
    n = round(duration / h)
    hold = max(1, round(0.02 / h))  # a new random control every 20 ms
    out = {
        k: np.zeros(n)
        for k in ("t", "ctrl", "friction_fwd", "friction_inv", "contact_fwd", "contact_inv")
    }
    ctrl = np.zeros(m.nu)
    for k in range(n):
        if k % hold == 0:
            ctrl[:] = np.clip(rng.normal(0.0, 0.25 * (hi - lo)), lo, hi)
        fwd = dyn.forward(qpos, qvel, ctrl, iterations=iterations, tolerance=tolerance)
        inv = dyn.inverse(qpos, qvel, fwd.qacc)
        out["t"][k] = k * h
        out["ctrl"][k] = ctrl[0]
        for label, constraints in (("fwd", fwd.constraints), ("inv", inv.constraints)):
            types = constraints.efc_type
            friction = constraints.efc_impulse[types == _T.mjCNSTR_FRICTION_DOF]
            normal = [
                constraints.contact_impulse(i)[0] for i in range(len(constraints.contacts.dim))
            ]
            out[f"friction_{label}"][k] = friction.sum()
            out[f"contact_{label}"][k] = float(np.sum(normal))
        qvel_next = fwd.qvel_next
        mujoco.mj_integratePos(dyn.model, qpos, qvel_next, h)
        qvel = qvel_next
    return out


def run(out: Path, duration: float = 4.0, seed: int = 0) -> dict[str, Any]:
    results: dict[str, Any] = {"figure": "fig2", "duration_s": duration, "seed": seed}
    series = {}
    for path in ("reference", "native"):
        s = simulate(path, duration, seed, iterations=20_000, tolerance=1e-12)
        series[path] = s
        diff_friction = float(np.max(np.abs(s["friction_fwd"] - s["friction_inv"])))
        diff_contact = float(np.max(np.abs(s["contact_fwd"] - s["contact_inv"])))
        results[path] = {
            "max_abs_diff": max(diff_friction, diff_contact),
            "max_abs_diff_friction": diff_friction,
            "max_abs_diff_contact": diff_contact,
            "steps": len(s["t"]),
            "steps_friction_sticking": int(
                np.sum(np.abs(s["friction_fwd"]) < np.max(np.abs(s["friction_fwd"])) * 0.999)
            ),
            "steps_in_contact": int(np.sum(s["contact_fwd"] > 0)),
            "max_friction_impulse": float(np.max(np.abs(s["friction_fwd"]))),
            "max_contact_impulse": float(np.max(s["contact_fwd"])),
        }
    results["max_abs_diff"] = results["reference"]["max_abs_diff"]
    results["paper_bound"] = 1e-5
    results["machine"] = machine()
    write_json(out, "fig2.json", results)
    _plot(out / "fig2.png", series["reference"])
    print_table(
        "Fig. 2 — single-joint mechanism, forward vs inverse impulses (N·s)",
        ["path", "steps", "in contact", "max |Δ friction|", "max |Δ contact|", "max_abs_diff"],
        [
            [
                p,
                results[p]["steps"],
                results[p]["steps_in_contact"],
                results[p]["max_abs_diff_friction"],
                results[p]["max_abs_diff_contact"],
                results[p]["max_abs_diff"],
            ]
            for p in ("reference", "native")
        ],
    )
    print(f"max_abs_diff = {results['max_abs_diff']:.3g} (paper: within 1e-5)  -> {out}/fig2.json")
    return results


def _plot(path: Path, s: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for ax, key, label in (
        (axes[0], "friction", "friction impulse (N·s)"),
        (axes[1], "contact", "contact impulse (N·s)"),
    ):
        ax.plot(s["t"], s[f"{key}_fwd"], color="black", lw=2.5, label="forward (GPGS)")
        ax.plot(s["t"], s[f"{key}_inv"], color="tab:orange", lw=1.0, label="inverse (analytic)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[1].set_xlabel("time (s)")
    diff = max(
        np.max(np.abs(s["friction_fwd"] - s["friction_inv"])),
        np.max(np.abs(s["contact_fwd"] - s["contact_inv"])),
    )
    fig.suptitle(f"Fig. 2: single-joint mechanism, max |forward − inverse| = {diff:.1e} N·s")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

"""Paper Fig. 3: CPU time per step of forward and inverse dynamics of the 27-dof humanoid.

The humanoid is driven through many contact configurations — random pushes, falls, drops
from random poses — with all contact friction directions enabled (condim 6) for large
Jacobians. At every visited state both paths run forward dynamics with 5 and with 50
(G)PGS iterations and the inverse dynamics, each timed alone. Medians are taken per number of
impulses (nefc) and over all steps, and the forward/inverse ratio is reported — for the
reference path (the paper's algorithms in numpy) and the native path (MuJoCo's C engine),
measured in the same run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from physics.dynamics import make_dynamics
from physics.model import load_model
from physics.native import NativeDynamics
from physics.reproduce.common import machine, print_table, write_json


def humanoid_all_friction() -> mujoco.MjModel:
    """The humanoid with condim 6 (tangential, torsional and rolling friction) on every geom.

    Sensors are disabled: the paper times the dynamics, and MuJoCo evaluates every sensor
    (touch, IMU, frame sensors, with an extra RNE pass for acceleration sensors) inside both
    mj_forward and mj_inverse.
    """
    m = load_model("humanoid")
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_SENSOR
    m.geom_condim[:] = 6
    m.geom_friction[:, 1] = np.maximum(m.geom_friction[:, 1], 0.02)
    m.geom_friction[:, 2] = np.maximum(m.geom_friction[:, 2], 0.002)
    return m


State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # qpos, qvel, ctrl, qacc


def drive(m: mujoco.MjModel, duration: float, seed: int) -> list[State]:
    """States (qpos, qvel, ctrl) visited while pushing, dropping and flailing the humanoid."""
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    states: list[State] = []
    steps = round(duration / m.opt.timestep)
    drop_every = round(4.0 / m.opt.timestep)
    push_every = round(0.5 / m.opt.timestep)
    for k in range(steps):
        if k % drop_every == 0:  # drop from a random pose: new contact configurations
            mujoco.mj_resetData(m, d)
            d.qpos[2] = rng.uniform(0.9, 1.6)
            axis = rng.normal(size=3)
            mujoco.mju_axisAngle2Quat(
                d.qpos[3:7], axis / np.linalg.norm(axis), rng.uniform(0, np.pi)
            )
            d.qpos[7:] = rng.uniform(-0.5, 0.5, m.nq - 7)
        if k % push_every == 0:
            d.xfrc_applied[:] = 0.0
            body = rng.integers(1, m.nbody)
            d.xfrc_applied[body, :3] = rng.normal(0.0, 150.0, 3)
        d.ctrl[:] = rng.normal(0.0, 0.4, m.nu)
        mujoco.mj_step(m, d)
        states.append((d.qpos.copy(), d.qvel.copy(), d.ctrl.copy(), d.qacc.copy()))
    return states


def _time_us(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> float:
    """Wall-clock µs of fn(*args, **kwargs), called once untimed first so that caches are warm
    (as inside a simulation loop; a cold MjData after milliseconds of other work costs
    MuJoCo's ~10 µs calls several times their warm time)."""
    fn(*args, **kwargs)
    t0 = time.perf_counter_ns()
    fn(*args, **kwargs)
    return (time.perf_counter_ns() - t0) / 1e3


def measure(states: list[State], m: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Per state: nefc and the µs of each computation on each path."""
    ref = make_dynamics(m, "reference")
    nat_inv = make_dynamics(m, "native")  # Newton setting: mj_inverse skips the dense A
    nat_fwd5, nat_fwd50 = NativeDynamics(m), NativeDynamics(m)
    nat_fwd5.set_solver("pgs", iterations=5, tolerance=0.0)
    nat_fwd50.set_solver("pgs", iterations=50, tolerance=0.0)
    names = (
        "nefc",
        "ncon",
        "ref_inverse",
        "ref_forward5",
        "ref_forward50",
        "nat_inverse",
        "nat_forward5",
        "nat_forward50",
        "nat_inv_position",
        "nat_inv_velocity",
        "nat_inv_constraint",
        "api_inverse",
    )
    rows: dict[str, list[float]] = {k: [] for k in names}
    warm = np.zeros(m.nv)
    for qpos, qvel, ctrl, qacc in states:
        inv = nat_inv.inverse(qpos, qvel, qacc)  # untimed: warms caches, gives nefc
        rows["nefc"].append(len(inv.constraints.efc_impulse))
        rows["ncon"].append(len(inv.constraints.contacts.dim))
        rows["ref_inverse"].append(_time_us(ref.inverse, qpos, qvel, qacc))
        for n in (5, 50):
            rows[f"ref_forward{n}"].append(
                _time_us(ref.forward, qpos, qvel, ctrl, iterations=n, tolerance=0.0)
            )
        # native: the bare C calls, state copied in beforehand, as the paper timed its engine
        for name, dyn, call in (
            ("nat_inverse", nat_inv, mujoco.mj_inverse),
            ("nat_forward5", nat_fwd5, mujoco.mj_forward),
            ("nat_forward50", nat_fwd50, mujoco.mj_forward),
        ):
            d = dyn.data
            d.qpos[:], d.qvel[:], d.ctrl[:], d.qacc[:] = qpos, qvel, ctrl, qacc
            d.qacc_warmstart[:] = warm
            rows[name].append(_time_us(call, dyn.model, d))
        rows["api_inverse"].append(_time_us(nat_inv.inverse, qpos, qvel, qacc))
        warm = qacc
        # where MuJoCo's own inverse spends its time: its three stages, timed one by one
        mm, dd = nat_inv.model, nat_inv.data
        dd.qpos[:], dd.qvel[:], dd.qacc[:] = qpos, qvel, qacc
        for stage in ("position", "velocity", "constraint"):
            call = getattr(mujoco, f"mj_inv{stage.capitalize()}")
            rows[f"nat_inv_{stage}"].append(_time_us(call, mm, dd))
    return {k: np.asarray(v) for k, v in rows.items()}


def position_stage_breakdown(m: mujoco.MjModel, states: list[State]) -> dict:
    """Median µs of the Phase I pieces inside mj_invPosition (= mj_fwdPosition)."""
    d = mujoco.MjData(m)
    pieces = {
        "kinematics": mujoco.mj_kinematics,
        "com": mujoco.mj_comPos,
        "inertia CRB (M)": mujoco.mj_crb,
        "factorize M (LDL)": mujoco.mj_factorM,
        "collision": mujoco.mj_collision,
        "make constraint (J, R)": mujoco.mj_makeConstraint,
    }
    times: dict[str, list[float]] = {k: [] for k in pieces}
    for qpos, *_ in states[:: max(1, len(states) // 300)]:
        d.qpos[:] = qpos
        for name, fn in pieces.items():
            times[name].append(_time_us(fn, m, d))
    return {k: float(np.median(v)) for k, v in times.items()}


def run(out: Path, duration: float = 20.0, seed: int = 0) -> dict[str, Any]:
    m = humanoid_all_friction()
    states = drive(m, duration, seed)
    t = measure(states, m)
    results: dict[str, Any] = {
        "figure": "fig3",
        "model": "humanoid, condim 6 on every geom",
        "nv": m.nv,
        "steps": len(states),
        "seed": seed,
        "nefc_range": [int(t["nefc"].min()), int(t["nefc"].max())],
    }
    for path, prefix in (("reference", "ref"), ("native", "nat")):
        inverse = float(np.median(t[f"{prefix}_inverse"]))
        f5 = float(np.median(t[f"{prefix}_forward5"]))
        f50 = float(np.median(t[f"{prefix}_forward50"]))
        results[path] = {
            "inverse_us": inverse,
            "forward5_us": f5,
            "forward50_us": f50,
            "ratio5": f5 / inverse,
            "ratio50": f50 / inverse,
            "by_nefc": _by_nefc(t, prefix),
        }
    results["native"]["inverse_stages_us"] = {
        stage: float(np.median(t[f"nat_inv_{stage}"]))
        for stage in ("position", "velocity", "constraint")
    }
    results["native"]["position_stage_pieces_us"] = position_stage_breakdown(m, states)
    results["native"]["python_api_inverse_us"] = float(np.median(t["api_inverse"]))
    results["machine"] = machine()
    write_json(out, "fig3.json", results)
    _plot(out / "fig3.png", t)
    print_table(
        f"Fig. 3 — humanoid (nv={m.nv}, all friction directions), {len(states)} steps, "
        f"nefc {results['nefc_range'][0]}–{results['nefc_range'][1]}; medians in µs",
        ["path", "inverse", "forward 5 it", "forward 50 it", "fwd5/inv", "fwd50/inv"],
        [
            [
                p,
                results[p]["inverse_us"],
                results[p]["forward5_us"],
                results[p]["forward50_us"],
                results[p]["ratio5"],
                results[p]["ratio50"],
            ]
            for p in ("reference", "native")
        ],
    )
    stages = results["native"]["inverse_stages_us"]
    pieces = results["native"]["position_stage_pieces_us"]
    print("MuJoCo mj_inverse stages (µs): " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()))
    print("  inside the position stage: " + ", ".join(f"{k} {v:.1f}" for k, v in pieces.items()))
    print(
        f"  NativeDynamics.inverse (the same call through the Python API, results copied): "
        f"{results['native']['python_api_inverse_us']:.1f} µs"
    )
    print(f"-> {out}/fig3.json, {out}/fig3.png")
    return results


def _by_nefc(t: dict[str, np.ndarray], prefix: str) -> dict[str, dict[str, float]]:
    table = {}
    for n in np.unique(t["nefc"]):
        mask = t["nefc"] == n
        table[str(int(n))] = {
            "steps": int(mask.sum()),
            "inverse_us": float(np.median(t[f"{prefix}_inverse"][mask])),
            "forward5_us": float(np.median(t[f"{prefix}_forward5"][mask])),
            "forward50_us": float(np.median(t[f"{prefix}_forward50"][mask])),
        }
    return table


def _plot(path: Path, t: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nefc = np.unique(t["nefc"])
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for col, (prefix, title) in enumerate(
        (("ref", "reference path (numpy)"), ("nat", "native path (MuJoCo C)"))
    ):
        med = {
            k: np.array([np.median(t[f"{prefix}_{k}"][t["nefc"] == n]) for n in nefc])
            for k in ("inverse", "forward5", "forward50")
        }
        ax = axes[0, col]
        ax.semilogy(nefc, med["forward50"], "o-", ms=3, label="forward, 50 iterations")
        ax.semilogy(
            nefc, med["forward5"], "o-", ms=3, color="tab:green", label="forward, 5 iterations"
        )
        ax.semilogy(nefc, med["inverse"], "o-", ms=3, color="tab:orange", label="inverse")
        ax.set_title(title)
        ax.set_ylabel("median CPU time per step (µs)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        ax = axes[1, col]
        ax.plot(nefc, med["forward50"] / med["inverse"], "o-", ms=3, label="50 iterations")
        ax.plot(
            nefc,
            med["forward5"] / med["inverse"],
            "o-",
            ms=3,
            color="tab:green",
            label="5 iterations",
        )
        ax.axhline(1.0, color="gray", lw=0.8)
        ax.set_xlabel("number of impulses (nefc)")
        ax.set_ylabel("speedup: forward / inverse")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Fig. 3: humanoid, all friction directions enabled")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

"""The newest estimate of a stream, published as soon as its knot is ready: the EKF of
`estimator.baselines.filters` stepped key by key, while the fixed-lag smoother behind it
makes the smoothed estimate (`estimator.stream`).

A smoother's update re-solves the knots of its lag (30 ms and more on two cores), so the
knot a robot's controller waits for would wait for it. The filter's step costs one forward
dynamics with its derivatives: per new key k,

    predict    x_k⁻ = step(x_{k−1}, u_{k−1}),  P_k⁻ = F P Fᵀ + Q      (the physics step)
    force      u_k = the commands through the actuators at (q_k⁻, v_k⁻)  (`Problem.u_known`)
    linearize  at x_k⁻: sensors, A and C (`mjd_transitionFD`), ∂(a, s)/∂u
    update     the knot's sensors, chi-square gated                    (`Filter.ekf_update`)

F and Q of the next step come from the same linearization, at the prior rather than at the
posterior as the batch filter takes them: one pass of MuJoCo's finite differences per knot
instead of two.

and the knot is published with the state's velocity, the forward dynamics' acceleration at it,
the impulses of the analytic inverse there (the contacts the filter's motion asks for; not
balanced) and σ of the filter's covariance. It starts at key 1 from the raw configurations of
keys 0 and 1, as the batch filter starts (`filter_estimate`), with the model's own contact
softness (a softness fitted later is the smoother's).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

import mujoco
import numpy as np

from estimator.baselines.filters import (
    Filter,
    Force,
    Knot,
    Linearization,
    force_bound,
    held_at_start,
)
from estimator.config import Config
from estimator.estimate import Estimate
from estimator.io.logs.measurements import Measurement
from estimator.problem import Problem, ProblemBuilder
from estimator.run import initial_trajectory
from estimator.settings import Settings
from physics.dynamics import Dynamics, make_dynamics


class NewestFilter:
    """The filter of a stream's knots t0_ns + k h (the smoother's grid)."""

    def __init__(
        self,
        config: Config,
        settings: Settings,
        compiled: tuple[mujoco.MjModel, dict[str, list[str]]],
        t0_ns: int,
        h: float,
    ) -> None:
        self.config = config
        self.builder = ProblemBuilder(config, settings, compiled)  # (its model: the filter's)
        self.t0_ns, self.step_ns = t0_ns, round(h * 1e9)
        self.filter: Filter | None = None
        self.key = -1  # the newest key filtered
        self.force = Force(np.zeros(0), np.zeros(0))  # the newest key's
        self.at: Linearization | None = None  # the physics at its prior
        # (made now, not at the first key)
        model = self.builder.model
        self.bound = force_bound(model)  # σ_f of a dof with no known force
        self.dynamics: Dynamics = make_dynamics(model, "native")
        self.data = mujoco.MjData(model)
        self.diverged = ""  # why the last `add` restarted the filter

    def t_ns(self, start: int, stop: int) -> np.ndarray:
        return self.t0_ns + self.step_ns * np.arange(start, stop, dtype=np.int64)

    def steps(self, measurements: Mapping[str, Measurement], last_key: int) -> Iterator[Estimate]:
        """Filter the keys after the newest one up to last_key (their samples in
        `measurements`), one at a time: each key's Estimate (one knot) as soon as it is done
        (nothing before the filter can start). A state that is not finite any more ends the
        keys and restarts the filter at the next ones (`diverged` says so)."""
        self.diverged = ""
        if self.filter is None:
            if last_key < self.key + 2:
                return
            self._start(measurements, self.key + 1)
        first = self.key + 1
        if last_key < first:
            return
        problem = self._problem(measurements, first, last_key + 1)  # (once for the keys)
        f = self.filter
        assert f is not None
        for i, k in enumerate(range(first, last_key + 1)):
            # (checked before the step: MuJoCo resets a NaN state to the model's reference)
            if not _finite(f):
                self.diverged = f"the filter's state at key {k - 1} is not finite"
                self.filter = None  # (restarted from the measurements at the next keys)
                return
            f.ekf_predict(self.force, self.at)
            self._linearize(problem, i)
            f.ekf_update(Knot.at(problem, i, k), self.force, self.at)
            self.key = k
            yield self._estimate(problem, i)

    # -- the steps -----------------------------------------------------------------------------

    def _problem(self, measurements: Mapping[str, Measurement], start: int, stop: int) -> Problem:
        """The keys' sensor blocks and known forces (interpolated to the knots, as the batch
        filter's)."""
        return self.builder.build(measurements, self.t_ns(start, stop), at_sample_times=False)

    def _start(self, measurements: Mapping[str, Measurement], key: int) -> None:
        """Keys `key` and `key` + 1: q and v from the raw configurations, the first key's
        sensors."""
        problem = self._problem(measurements, key, key + 2)
        model = problem.model
        measured = np.zeros((2, model.nq), dtype=bool)
        qpos0 = initial_trajectory(model, measurements, problem.t_ns, measured_out=measured)
        self.filter = Filter(problem, qpos0, "ekf", held_at_start(model, measured, problem.h))
        f = self.filter
        self._linearize(problem, 0)
        f.ekf_update(Knot.at(problem, 0, key), self.force, self.at)
        f.tighten_initial_velocity()
        self.key = key

    def _linearize(self, problem: Problem, i: int) -> None:
        """At the prior of knot i: the force u_i and σ_f² (the commands through the actuators
        at the state), and the physics linearized once, for this update and the next step."""
        f, data = self.filter, self.data
        assert f is not None
        q, v = f.chart.qpos(f.reference, f.ekf.x), f.ekf.x[f.nv : 2 * f.nv]
        data.qpos[:], data.qvel[:] = q, v
        mujoco.mj_fwdPosition(problem.model, data)
        mujoco.mj_fwdVelocity(problem.model, data)
        u = problem.u_known(data, i)[0]
        sigma = problem.physics_sigma[i]
        sigma = np.where(np.isfinite(sigma), sigma, self.bound)
        self.force = Force(np.nan_to_num(u), sigma**2)
        self.at = f.physics.linearize(q, v, self.force.u)

    def _estimate(self, problem: Problem, i: int) -> Estimate:
        """Knot i's Estimate, the posterior: a = the forward dynamics' at the state, the
        impulses of the analytic inverse at (q, v, a)."""
        f, dyn = self.filter, self.dynamics
        assert f is not None
        x, nv, u = f.ekf.x, f.nv, self.force.u
        qpos, qvel, bias = f.reference.copy(), x[nv : 2 * nv].copy(), x[2 * nv :]
        f.physics.sensors(qpos, qvel, u)  # (mj_forward)
        qacc = f.physics.data.qacc.copy()
        inv = dyn.inverse(qpos, qvel, qacc)
        return Estimate(
            t_ns=problem.t_ns[i : i + 1],
            h=problem.h,
            qpos=qpos[None],
            qvel=qvel[None],
            qacc=qacc[None],
            qfrc_inverse=inv.qfrc_inverse[None],
            qfrc_known=np.where(np.isfinite(problem.physics_sigma[i]), u, np.nan)[None],
            qpos_std=np.sqrt(np.clip(np.diag(f.ekf.P)[:nv], 0.0, None))[None],
            constraints=(inv.constraints,),
            model_name=self.config.model_ref,
            imu_bias={name: bias[None, problem.bias_of[name]] for name in problem.imu_streams},
        )


def _finite(f: Filter) -> bool:
    return bool(
        np.isfinite(f.ekf.x).all() and np.isfinite(f.ekf.P).all() and np.isfinite(f.reference).all()
    )

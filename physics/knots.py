"""The engine at many states at once: inverse dynamics, sensors and their derivatives at a
trajectory's knots, on MuJoCo's own threads (MuJoCo releases the GIL).

The one way the estimator enters the engine at its knots. Per knot k, at (q_k, v_k, a_k):

    u_k = qfrc_inverse                 `mj_inverse` with mjENBL_INVDISCRETE: the inverse of
    s_k = sensordata                   the Euler step (`native.use_discrete_inverse`), its
                                       implicit joint damping included; the sensors at the same
                                       state, acceleration stage from the inverse's forces
    ∂(u, s)/∂(q, v, a)                 `mjd_inverseFD`, forward differences of step `eps`, in
                                       MuJoCo's transposed layout (row i: by x_i)

    batch = KnotBatch(model, threads=2)
    batch.map(work, 1, T - 1)    # work(engine, range) on each chunk, an engine per thread
    batch.close()

`path = "reference"` takes u from the paper's numpy inverse (`physics.reference`) instead.
"""

from __future__ import annotations

import queue
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np

from physics.dynamics import make_dynamics
from physics.native import use_discrete_inverse


class KnotEngine:
    """One thread's engine: its own MjData on a model with the discrete inverse set."""

    def __init__(self, model: mujoco.MjModel, path: str = "native", eps: float = 1e-6) -> None:
        use_discrete_inverse(model)
        self.model = model
        self.data = mujoco.MjData(model)
        self.eps = eps
        self.reference = make_dynamics(model, "reference") if path == "reference" else None

    def inverse(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u (nv,) and sensordata (ns,) at (q, v, a); `data` then holds the state (positions,
        velocities, actuation computed)."""
        d = self.data
        d.qpos[:], d.qvel[:], d.qacc[:] = q, v, a
        mujoco.mj_inverse(self.model, d)
        u = d.qfrc_inverse.copy()
        if self.reference is not None:
            u = self.reference.inverse(q, v, a).qfrc_inverse
        return u, d.sensordata.copy()

    def derivatives(
        self, q: np.ndarray, v: np.ndarray, a: np.ndarray, *out: np.ndarray | None
    ) -> None:
        """`mjd_inverseFD` at (q, v, a) into out = (DfDq, DfDv, DfDa) (nv, nv) and (DsDq,
        DsDv, DsDa) (nv, ns); None: not needed (MuJoCo skips the v or a differences when
        nothing asks for them)."""
        d = self.data
        d.qpos[:], d.qvel[:], d.qacc[:] = q, v, a
        mujoco.mjd_inverseFD(self.model, d, self.eps, False, *out, None)


# a batch of at most this many knots runs on the caller's thread: the hand-offs to the pool
# cost more than a second thread gains (a stream's incremental update)
INLINE_KNOTS = 16


class KnotBatch:
    """`threads` engines on one model, and a pool that hands each chunk of knots to an idle
    one."""

    def __init__(
        self, model: mujoco.MjModel, threads: int, path: str = "native", eps: float = 1e-6
    ) -> None:
        self.threads = threads
        self.idle: queue.SimpleQueue[KnotEngine] = queue.SimpleQueue()
        for _ in range(threads):
            self.idle.put(KnotEngine(model, path, eps))
        self.pool = ThreadPoolExecutor(threads)

    def map(
        self,
        work: Callable[[KnotEngine, range], None],
        start: int,
        stop: int,
        pieces: int | None = None,
    ) -> None:
        """work(engine, chunk) over range(start, stop) in contiguous chunks (default: four per
        thread, to balance the load), each on an engine no other thread is using."""

        def run(chunk: range) -> None:
            engine = self.idle.get()
            try:
                work(engine, chunk)
            finally:
                self.idle.put(engine)

        if self.threads == 1 or stop - start <= INLINE_KNOTS:  # on the caller's thread
            run(range(start, stop))
            return
        list(self.pool.map(run, chunks(start, stop, pieces or 4 * self.threads)))

    def close(self) -> None:
        self.pool.shutdown()


def chunks(start: int, stop: int, pieces: int) -> list[range]:
    """range(start, stop) in at most `pieces` contiguous, nonempty pieces."""
    n = max(1, min(pieces, stop - start))
    edges = np.linspace(start, stop, n + 1).round().astype(int)
    return [range(edges[j], edges[j + 1]) for j in range(n) if edges[j + 1] > edges[j]]

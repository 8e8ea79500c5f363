"""The incremental fixed lag's linear algebra against dense matrices, and its estimate against
the whole-window updates' on a recording."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from estimator.config import load_config
from estimator.io.logs.source import open_log
from estimator.io.state_topics import at_times, read_state_topics, trajectory_errors
from estimator.settings import Settings
from estimator.solver.banded import MARGINAL_REGULARIZER, BandedSystem, factor_std, front_std
from estimator.solver.incremental import IncrementalLag, eliminate_first, times
from estimator.stream import Stream

ROOT = Path(__file__).resolve().parents[1]


def random_banded(T: int, nz: int, span: int, seed: int = 0) -> BandedSystem:
    """JᵀJ + I of random rows on `span` consecutive keys, and a random g."""
    rng = np.random.default_rng(seed)
    H = np.eye(T * nz)
    for k in range(T - span + 1):
        J = rng.normal(size=(2 * nz, span * nz)) * rng.uniform(0.1, 1e3)  # stiff and soft rows
        cols = slice(k * nz, (k + span) * nz)
        H[cols, cols] += J.T @ J
    diag = np.stack([H[k * nz : (k + 1) * nz, k * nz : (k + 1) * nz] for k in range(T)])
    lower = [
        np.stack([H[(k + o) * nz : (k + o + 1) * nz, k * nz : (k + 1) * nz] for k in range(T - o)])
        for o in range(1, span)
    ]
    return BandedSystem(diag, lower, rng.normal(size=(T, nz)))


def dense(system: BandedSystem) -> np.ndarray:
    T, nz, _ = system.diag.shape
    H = np.zeros((T * nz, T * nz))
    for k in range(T):
        H[k * nz : (k + 1) * nz, k * nz : (k + 1) * nz] = system.diag[k]
    for o, lo in enumerate(system.lower, 1):
        for k in range(len(lo)):
            H[(k + o) * nz : (k + o + 1) * nz, k * nz : (k + 1) * nz] = lo[k]
            H[k * nz : (k + 1) * nz, (k + o) * nz : (k + o + 1) * nz] = lo[k].T
    return H


def test_eliminating_the_first_key_is_the_dense_schur_complement():
    for span in (3, 4):
        system = random_banded(T=7, nz=5, span=span, seed=span)
        H, g, nz = dense(system), system.g.reshape(-1), 5
        e, r = slice(0, nz), slice(nz, None)
        schur = H[r, r] - H[r, e] @ np.linalg.solve(H[e, e], H[e, r])
        g_r = g[r] - H[r, e] @ np.linalg.solve(H[e, e], g[e])
        out = eliminate_first(system)
        assert np.allclose(dense(out), schur, rtol=1e-10, atol=1e-8 * np.abs(schur).max())
        assert np.allclose(out.g.reshape(-1), g_r, rtol=1e-10, atol=1e-8 * np.abs(g_r).max())
        # the minimum over the kept keys is the whole system's
        x = np.linalg.solve(H, -g)
        assert np.allclose(np.linalg.solve(dense(out), -out.g.reshape(-1)), x[r], rtol=1e-8)


def test_the_banded_product_is_the_dense_one():
    system = random_banded(T=6, nz=4, span=4, seed=1)
    d = np.random.default_rng(2).normal(size=(6, 4))
    assert np.allclose(times(system, d).reshape(-1), dense(system) @ d.reshape(-1))


def test_the_published_sigmas_from_one_factor_are_the_dense_inverses():
    system = random_banded(T=8, nz=6, span=4, seed=3)
    nv = 4  # (the first nv of each key's nz unknowns: the dofs, then the biases)
    s, ab = system.scaled_band()
    L = BandedSystem.factor(ab, MARGINAL_REGULARIZER)
    exact = np.sqrt(np.diag(np.linalg.inv(dense(system)))).reshape(8, 6)[:, :nv]
    newest = factor_std(L, s, 6, nv, range(6, 8))
    front = front_std(L, s, 6, nv, range(1, 3))
    assert np.allclose(newest[6:], exact[6:], rtol=1e-7)
    assert np.allclose(front[1:3], exact[1:3], rtol=1e-7)
    assert np.isnan(newest[:6]).all() and np.isnan(front[[0, *range(3, 8)]]).all()


def smoothed_joint_error(relinearize_s: float) -> tuple[float, Stream]:
    """recordings/humanoid_push.mcap through the Stream, one update per ready key, with the
    node's settings: the smoothed estimate's joint error against the ground truth."""
    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5, relinearize_s=relinearize_s)
    updates = []
    for raw in open_log(ROOT / "recordings" / "humanoid_push.mcap", log_time=(0, int(2.5e9))):
        stream.push(raw)
        updates += stream.update()
    updates += stream.close()
    model = config.load_model()
    t = np.concatenate([u.estimate.t_ns[u.smoothed] for u in updates])
    q = np.concatenate([u.estimate.qpos[u.smoothed] for u in updates])
    tg, qg = read_state_topics(ROOT / "recordings" / "humanoid_push.mcap").qpos(model)
    return trajectory_errors(model, q, at_times(tg, qg, t))["joint_deg"], stream


def test_incremental_updates_smooth_as_well_as_whole_window_ones():
    """Each update relinearizes the newest 0.04 s of rows only: the smoothed estimate is as
    good as the one from whole-window updates (humanoid_push's first 2.5 s: 0.00498° against
    0.00537°), one key at a time."""
    incremental, stream = smoothed_joint_error(0.04)
    assert isinstance(stream.lag, IncrementalLag) and stream.lag.kept is not None
    whole, _ = smoothed_joint_error(0.0)
    assert incremental <= 1.1 * whole, (incremental, whole)

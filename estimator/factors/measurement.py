"""The rows of one `SensorBlock`: MuJoCo's sensor values at the knots against the samples.

    vector   (s + b − m) / σ                 s at the knot, or between knots k − 1 and k for a
    quat     Log(m⁻¹ ⊗ s) / σ                position-stage sample at t_{k−1} + α h
                                             (`between_knots`)

Rows without a sample are 0 and not `valid`. The block's robust kernel acts per element
(`SensorBlock.group` rows).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from estimator.factors.base import Block, SensorBlock, Terms
from estimator.factors.robust import weighted
from estimator.rotations import quat_errors, quat_log_between

if TYPE_CHECKING:
    from estimator.problem import Problem


def rows(p: Problem, t: Terms, bias: np.ndarray, sensor: SensorBlock, robust: bool = True) -> Block:
    K = p.T - 2
    meas = sensor.values[1:-1]
    g = sensor.group or meas.shape[1]
    valid = np.isfinite(meas).reshape(K, -1, g).all(axis=2)  # (K, elements)
    measured = np.repeat(valid, g, axis=1)  # (K, n_meas)
    sig = sensor.sigma[1:-1] if sensor.sigma.ndim == 2 else np.tile(sensor.sigma, (K, 1))
    pred = t.s[:, sensor.rows]
    Js = t.Js[:, sensor.rows] if t.Js is not None else None
    if sensor.alpha is not None:
        pred, Js = between_knots(sensor, pred, Js, p.model.nv)
    J_bias = None
    if sensor.kind == "quat":
        target = np.where(measured, meas, pred)
        if Js is None:  # e = Log(meas⁻¹ ⊗ pred)
            r = quat_log_between(target, pred) / sig
        else:
            e, de_dp = quat_errors(pred, target)
            r = e / sig
            Js = np.einsum("kij,kjc->kic", de_dp, Js)
    else:
        b = bias[1:-1, sensor.bias] if sensor.bias is not None else 0.0
        r = (pred + b - np.where(measured, meas, 0.0)) / sig
        if t.Js is not None and sensor.bias is not None:
            J_bias = np.zeros((K, r.shape[1], p.nb))
            cols = np.arange(r.shape[1])
            J_bias[:, cols, sensor.bias.start + cols] = 1.0 / sig
    J = Js / sig[:, :, None] if Js is not None else None
    rows_valid = np.repeat(valid, r.shape[1] // valid.shape[1], axis=1)  # (K, n_res)
    r[~rows_valid] = 0.0
    for M in (J, J_bias):
        if M is not None:
            M[~rows_valid] = 0.0
    block = Block(
        sensor.stream, r, J, np.zeros(K), rows_valid, J_bias, sensor=True, slot=sensor.slot
    )
    kernel = getattr(p.settings, sensor.kernel)
    return weighted(block, kernel, p.settings.huber_k, robust, group=sensor.group)


def between_knots(
    sensor: SensorBlock, s: np.ndarray, Js: np.ndarray | None, nv: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """A sample between knots k − 1 and k (`SensorBlock.alpha`): the prediction
    (1 − α) s_{k−1} + α s_k (K, n) and its Jacobian (K, n, 3 nv) over (x_{k−1}, x_k,
    x_{k+1}) from the knots' own s and Js (position stage: on x_k alone). A quaternion
    q_{k−1} is first put on q_k's side and the blend m normalized: ∂(m/‖m‖)/∂m =
    (I − p̂p̂ᵀ)/‖m‖, whose projection the quaternion error's Jacobian makes anyway."""
    assert sensor.alpha is not None and sensor.stage == "pos"
    alpha = sensor.alpha[1:-1, None]  # (K, 1); knot 1's α is 1: s_0 is not needed
    prev = np.concatenate([s[:1], s[:-1]])  # s_{k−1}
    w_prev = 1.0 - alpha
    if sensor.kind == "quat":
        w_prev = w_prev * np.where(np.sum(prev * s, axis=1, keepdims=True) < 0, -1.0, 1.0)
    blend = w_prev * prev + alpha * s
    scale = np.ones_like(alpha)
    if sensor.kind == "quat":
        scale = 1.0 / np.linalg.norm(blend, axis=1, keepdims=True)
        blend *= scale
    if Js is None:
        return blend, None
    at_k = Js[:, :, nv : 2 * nv]
    J = np.zeros_like(Js)
    J[1:, :, :nv] = (w_prev * scale)[1:, :, None] * at_k[:-1]
    J[:, :, nv : 2 * nv] = (alpha * scale)[:, :, None] * at_k
    return blend, J

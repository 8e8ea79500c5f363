"""Rotations as unit quaternions (w, x, y, z), batched over leading axes: the one home of the
SO(3) operations the estimator, the simulator, the filters and the evaluation share.

    quat_mul(a, b)            a ⊗ b
    quat_conj(q)              q⁻¹ of a unit quaternion
    heading(q)                the yaw ψ of R = R_z(ψ) R_y(θ) R_x(φ); R_z(δ) ⊗ q adds δ to it
    quat_exp(φ)               Exp(φ), rotation vector → quaternion
    quat_log_between(q1, q2)  Log(q1⁻¹ ⊗ q2), the short way round (MuJoCo's mju_subQuat)
    quat_errors(pred, meas)   Log(meas⁻¹ ⊗ pred) and its Jacobian in pred
    jr_inverse(φ)             the inverse right Jacobian J_r⁻¹(φ)
    quat_slerp(q0, q1, a)     shortest-path interpolation
    rotation_angles(q, g)     the angle between two sequences
    rotate_inverse(q, v)      R(q)ᵀ v
    xyzw(q)                   (x, y, z, w) order, as Rerun and ROS messages store it
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of (..., 4) quaternions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    """q⁻¹ = (w, −x, −y, −z) of (..., 4) unit quaternions."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def heading(q: np.ndarray) -> np.ndarray:
    """The heading (yaw about world z, rad) of (..., 4) quaternions: ψ of R_z(ψ) R_y(θ) R_x(φ)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) of rotation vectors (..., 3) [rad]."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-300), 0.5)
    return np.concatenate([np.cos(half), scale * rotvec], axis=-1)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Shortest-path slerp from q0 to q1 (..., 4) at fractions a (broadcast to (..., 1))."""
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-6
    sin = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * theta) / sin)
    w1 = np.where(small, a, np.sin(a * theta) / sin)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotate_inverse(quat_wxyz: Sequence[float], v: np.ndarray) -> np.ndarray:
    """R(q)ᵀ v for vectors v (..., 3): site-frame vectors into the sensor frame."""
    rot = Rotation.from_quat(np.asarray(quat_wxyz, dtype=float), scalar_first=True)
    return rot.inv().apply(v.reshape(-1, 3)).reshape(v.shape)


def quat_log_between(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """φ = Log(q1⁻¹ ⊗ q2) (K, 3) of unit quaternions (K, 4), the short way round (as
    mju_subQuat(φ, q2, q1))."""
    w1, v1 = q1[:, 0], -q1[:, 1:]
    w2, v2 = q2[:, 0], q2[:, 1:]
    w = w1 * w2 - np.sum(v1 * v2, axis=1)
    v = w1[:, None] * v2 + w2[:, None] * v1 + np.cross(v1, v2)
    sign = np.where(w < 0, -1.0, 1.0)
    w, v = w * sign, v * sign[:, None]
    s = np.linalg.norm(v, axis=1)
    theta = 2.0 * np.arctan2(s, w)
    scale = np.where(s > 1e-12, theta / np.where(s > 1e-12, s, 1.0), 2.0 / np.maximum(w, 1e-300))
    return v * scale[:, None]


def quat_errors(pred: np.ndarray, meas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """e = Log(meas⁻¹ ⊗ pred) (K, 3) and ∂e/∂pred (K, 3, 4) for linear changes of pred (K, 4).

    pred ⊗ Exp(ξ) ≈ pred + dq gives ξ = 2 Im(pred* ⊗ dq); then de = J_r⁻¹(e) ξ, with
    J_r⁻¹(φ) = I + ½[φ]× + (1/θ² − (1 + cos θ)/(2θ sin θ)) [φ]×², θ = ‖φ‖.
    """
    e = quat_log_between(meas, pred)
    w2 = pred[:, 0]
    x, y, z = pred[:, 1], pred[:, 2], pred[:, 3]
    G = np.stack(
        [  # Im(q* ⊗ p) as a 3×4 matrix of p = (pw, px, py, pz)
            np.stack([-x, w2, z, -y], axis=1),
            np.stack([-y, -z, w2, x], axis=1),
            np.stack([-z, y, -x, w2], axis=1),
        ],
        axis=1,
    )
    return e, np.einsum("kij,kjl->kil", jr_inverse(e), 2.0 * G)


def jr_inverse(phi: np.ndarray) -> np.ndarray:
    """(K, 3, 3) inverse right Jacobian of SO(3) at φ (K, 3)."""
    theta = np.linalg.norm(phi, axis=1)
    hat = np.zeros((len(phi), 3, 3))
    hat[:, 0, 1], hat[:, 0, 2], hat[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    hat -= hat.transpose(0, 2, 1)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    c = np.where(small, 1.0 / 12.0, 1.0 / t**2 - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t)))
    return np.eye(3) + 0.5 * hat + c[:, None, None] * (hat @ hat)


def rotation_angles(quat_wxyz: np.ndarray, quat_true_wxyz: np.ndarray) -> np.ndarray:
    """(N,) angle [rad] of the rotation between two quaternion sequences (N, 4), the short way:
    θ = 2 atan2(‖Im(q_true* ⊗ q)‖, |Re(q_true* ⊗ q)|)."""
    q = quat_wxyz / np.linalg.norm(quat_wxyz, axis=1, keepdims=True)
    g = quat_true_wxyz / np.linalg.norm(quat_true_wxyz, axis=1, keepdims=True)
    w = np.sum(q * g, axis=1)  # Re(g* ⊗ q)
    v = g[:, :1] * q[:, 1:] - q[:, :1] * g[:, 1:] - np.cross(g[:, 1:], q[:, 1:])  # Im(g* ⊗ q)
    return 2.0 * np.arctan2(np.linalg.norm(v, axis=1), np.abs(w))


def xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions w, x, y, z (MuJoCo, ROS decode) → x, y, z, w (Rerun)."""
    q = np.asarray(quat_wxyz, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)

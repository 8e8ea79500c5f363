"""The softness parameters of Section V: ε, κ, r_min (and MuJoCo's impratio).

Eq. 27:  R_ii = max(ε·A_ii, r_min)        with A_ii MuJoCo's approximate diagonal of A
Eq. 28:  B_ii = 2(1+ε)/κ,  K_ii = (1+ε)/κ²  (K = 0 in friction dimensions)
Eq. 22:  r_j = r_F μ_j⁻² / ⟨μ_j⁻²⟩,  μ̂² = r_F / (r_0 ⟨μ_j⁻²⟩)

Exact mapping to MuJoCo (engine_core_constraint.c, mj_makeImpedance):
    solimp = (d, d, ·, ·, ·), d = 1/(1+ε)  (flat impedance: R = (1−d)/d·diagApprox = ε·diagApprox)
    solref = (κ, 1)                            (B = 2/(d κ) = 2(1+ε)/κ;  K·d = 1/(d κ²) = (1+ε)/κ²)
    r_min  = mjMINVAL = 1e-15               (MuJoCo floors R there; the native path takes no other)
    impratio = r_0 / R_1, i.e. r_F = r_0 μ_1² ⟨μ_j⁻²⟩ / impratio, and μ̂ = μ_1/√impratio = contact.mu
MuJoCo clamps κ to ≥ 2h unless the `refsafe` flag is disabled; we reject such κ instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from physics.errors import UnsupportedModelError

# mjMINIMP / mjMAXIMP bound MuJoCo's impedance d; ε = (1−d)/d must map inside them.
_D_MIN, _D_MAX = 0.0001, 0.9999
EPS_MIN, EPS_MAX = (1 - _D_MAX) / _D_MAX, (1 - _D_MIN) / _D_MIN


@dataclass(frozen=True)
class Softness:
    """Constraint softness, one set for the whole model (paper Section V).

    eps:      ε, impulse regularization scaling (dimensionless), R = ε·diag(A).
    kappa:    κ, error-reduction time constant in seconds (critically damped).
    r_min:    floor on the regularizer R (units of A).
    impratio: ratio r_0 / R_1 of normal to friction regularizer (MuJoCo's opt.impratio).
    """

    eps: float = 0.05
    kappa: float = 0.02
    r_min: float = mujoco.mjMINVAL
    impratio: float = 1.0

    def __post_init__(self) -> None:
        if not EPS_MIN <= self.eps <= EPS_MAX:
            raise UnsupportedModelError(
                f"softness eps={self.eps} is outside [{EPS_MIN:.6g}, {EPS_MAX:.6g}] "
                "(MuJoCo's impedance d = 1/(1+eps) must lie in [0.0001, 0.9999])"
            )
        for name in ("kappa", "r_min", "impratio"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise UnsupportedModelError(f"softness {name}={value} must be finite and > 0")

    @property
    def d(self) -> float:
        """MuJoCo's impedance d = 1/(1+ε)."""
        return 1.0 / (1.0 + self.eps)

    @property
    def B(self) -> float:
        """Damping of the x-space PD controller, eq. 28: B = 2(1+ε)/κ."""
        return 2.0 * (1.0 + self.eps) / self.kappa

    @property
    def K(self) -> float:
        """Stiffness of the x-space PD controller, eq. 28: K = (1+ε)/κ²."""
        return (1.0 + self.eps) / self.kappa**2

    def solref(self) -> np.ndarray:
        """MuJoCo solref (timeconst, dampratio) = (κ, 1)."""
        return np.array([self.kappa, 1.0])

    def solimp(self) -> np.ndarray:
        """MuJoCo solimp (d0, dwidth, width, midpoint, power) with flat impedance d."""
        return np.array([self.d, self.d, 0.001, 0.5, 2.0])

    @classmethod
    def from_mujoco(cls, solref, solimp, impratio: float = 1.0) -> Softness:
        """Inverse mapping from one element's MuJoCo solref/solimp (flat impedance only)."""
        timeconst, dampratio = float(solref[0]), float(solref[1])
        d0, d1 = float(solimp[0]), float(solimp[1])
        if timeconst <= 0 or dampratio != 1.0:
            raise UnsupportedModelError(
                f"solref={tuple(solref)}: expected (kappa > 0, 1) — the paper's critically "
                "damped stabilization; the direct (negative) format has no (eps, kappa)"
            )
        if d0 != d1:
            raise UnsupportedModelError(
                f"solimp={tuple(solimp)}: expected flat impedance (d0 == dwidth) — the paper's "
                "constant eps = (1-d)/d"
            )
        return cls(eps=(1 - d0) / d0, kappa=timeconst, impratio=impratio)

    def apply(self, model: mujoco.MjModel) -> None:
        """Write these settings into every solref/solimp of `model` and its impratio."""
        override(model, eps=self.eps, kappa=self.kappa)
        model.pair_solreffriction[:] = 0.0  # (0, 0): friction dimensions use solref
        model.opt.o_solref[:] = self.solref()
        model.opt.o_solimp[:] = self.solimp()
        model.opt.impratio = self.impratio

    @classmethod
    def of_model(cls, model: mujoco.MjModel) -> Softness:
        """The one softness every constraint element of `model` has (the reference path takes
        one); raises UnsupportedModelError naming the first element that differs. Elements
        that make no constraint (an unlimited joint's solreflimit, …) are not looked at."""
        found: tuple[str, Softness] | None = None
        for (ref_name, imp_name), used in zip(
            SOLREF_SOLIMP_FIELDS, _constraining(model), strict=True
        ):
            refs, imps = getattr(model, ref_name), getattr(model, imp_name)
            for i in np.flatnonzero(used):
                element = f"{ref_name.removesuffix('_solref').split('_solref')[0]} {i}"
                try:
                    softness = cls.from_mujoco(refs[i], imps[i], float(model.opt.impratio))
                except UnsupportedModelError as err:
                    raise UnsupportedModelError(f"{element}: {err}") from None
                if found is None:
                    found = (element, softness)
                elif softness != found[1]:
                    raise UnsupportedModelError(
                        f"{element} has softness eps={softness.eps:.6g}, kappa={softness.kappa:.6g}"
                        f" but {found[0]} eps={found[1].eps:.6g}, kappa={found[1].kappa:.6g}: "
                        "the paper's path takes one softness for the whole model"
                    )
        return found[1] if found else cls(impratio=float(model.opt.impratio))


# every (solref, solimp) pair of MjModel, by element kind
SOLREF_SOLIMP_FIELDS = (
    ("geom_solref", "geom_solimp"),
    ("pair_solref", "pair_solimp"),
    ("jnt_solref", "jnt_solimp"),
    ("dof_solref", "dof_solimp"),
    ("eq_solref", "eq_solimp"),
    ("tendon_solref_lim", "tendon_solimp_lim"),
    ("tendon_solref_fri", "tendon_solimp_fri"),
)


def _constraining(model: mujoco.MjModel) -> tuple[np.ndarray, ...]:
    """Per SOLREF_SOLIMP_FIELDS entry, which elements can make a constraint row."""
    return (
        (model.geom_contype | model.geom_conaffinity) != 0,
        np.ones(model.npair, bool),
        model.jnt_limited.astype(bool),
        model.dof_frictionloss > 0,
        np.ones(model.neq, bool),
        model.tendon_limited.astype(bool),
        model.tendon_frictionloss > 0,
    )


def override(model: mujoco.MjModel, eps: float | None = None, kappa: float | None = None) -> None:
    """Replace the model's own softness, in place, where given: ε writes the flat impedance
    d = 1/(1+ε) into every solimp, κ writes (κ, 1) into every solref. The model's impratio,
    friction and contact geometry stay its own."""
    given = Softness(eps=0.05 if eps is None else eps, kappa=0.02 if kappa is None else kappa)
    refsafe = not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE
    if kappa is not None and refsafe and kappa < 2 * model.opt.timestep:
        raise UnsupportedModelError(
            f"softness kappa={kappa} s is below 2*timestep={2 * model.opt.timestep} s; "
            "MuJoCo would silently clamp it (refsafe). Raise kappa or lower the timestep."
        )
    for ref_name, imp_name in SOLREF_SOLIMP_FIELDS:
        if kappa is not None:
            getattr(model, ref_name)[:] = given.solref()
        if eps is not None:
            getattr(model, imp_name)[:] = given.solimp()


def kappa_scale_floor(model: mujoco.MjModel) -> float:
    """The least factor on the model's own contact time constants κ (geoms' and pairs') that
    every one of them still takes: MuJoCo clamps a κ below 2·timestep (refsafe), so a factor
    below max 2h/κ moves that contact no further (the paper's κ = 0.02 s at h = 10 ms: no
    factor below 1). 0 without refsafe or without a time-constant solref."""
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE:
        return 0.0
    kappa = np.concatenate([model.geom_solref[:, 0], model.pair_solref[:, 0]])
    kappa = kappa[kappa > 0]
    return float(np.max(2.0 * model.opt.timestep / kappa)) if len(kappa) else 0.0


def scale(model: mujoco.MjModel, eps_scale: float = 1.0, kappa_scale: float = 1.0) -> None:
    """Scale the model's own softness, in place, element by element: ε = (1 − d)/d of every
    solimp's d0 and dwidth times eps_scale, every solref time constant (the (κ, damping ratio)
    format) times kappa_scale. Unlike `override`, per-geom differences are kept."""
    for ref_name, imp_name in SOLREF_SOLIMP_FIELDS:
        if eps_scale != 1.0:
            imp = getattr(model, imp_name)
            eps = (1.0 - imp[:, :2]) / imp[:, :2]
            imp[:, :2] = 1.0 / (1.0 + eps_scale * eps)
        if kappa_scale != 1.0:
            ref = getattr(model, ref_name)
            ref[:, 0] = np.where(ref[:, 0] > 0, ref[:, 0] * kappa_scale, ref[:, 0])

"""Model mismatch: the simulated robot differs from the model the estimator is given.

`Mismatch.apply(model, rng)` returns a perturbed copy of the model (the "true" robot), the true
contact softness, and a `MismatchRecord` of every perturbed value next to its nominal one,
which the simulator writes into the log's metadata (`physfuse.mismatch`). Perturbations are
multiplicative log-normal factors exp(σ·N(0, 1)), so a relative standard deviation σ keeps
every quantity positive:

    body_mass[b]        *= exp(σ_m z_b)
    body_inertia[b, i]  *= exp(σ_m z_b) · exp(σ_I z_bi)   (principal moments; the triangle
                                                          inequality is kept, else only the
                                                          mass factor is applied)
    geom_friction[g, 0] *= exp(σ_μ z_g)   (sliding friction; also explicit pairs' friction)
    softness ε, κ       *= exp(σ_s z_ε), exp(σ_s z_κ)   (κ kept ≥ 2h, MuJoCo's refsafe floor)

The softness is the paper's one (ε, κ) for the whole model (the bundled scenarios), or, with
`own_softness`, a scale s_ε, s_κ of the model's own per-element values (`physfuse simulate
--model`): for every solimp d_i = 1/(1 + s_ε ε_i) with ε_i = (1 − d_i)/d_i, for d0 and dwidth;
for every solref time constant κ_i s_κ (kept ≥ 2h; the direct format (−k, −b): k / s_κ²,
b / s_κ, as K ∝ 1/κ², B ∝ 1/κ); impratio and everything else stay the model's.

`SignedMismatch` instead sets each factor to exactly 1 ± σ, the sign that of the same draw z
(the `mismatch` condition of `physfuse simulate`: masses ±10%, friction ±30%).

Derived constants (subtree masses, the inverse weights behind MuJoCo's regularizer) are
recomputed with `mj_setConst`.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Mapping
from dataclasses import dataclass, field

import mujoco
import numpy as np

from physics.softness import SOLREF_SOLIMP_FIELDS, Softness


@dataclass(frozen=True)
class MismatchRecord:
    """Nominal and true values of everything a `Mismatch` changed.

    body_mass: body → (nominal, true) [kg]; body_inertia: body → (nominal (3,), true (3,))
    [kg·m²]; geom_friction: geom (or "pair:<name>") → (nominal, true) sliding coefficient;
    softness: "eps" / "kappa" → (nominal, true); with own softness "eps_scale" /
    "kappa_scale" → (1, s).
    """

    body_mass: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    body_inertia: Mapping[str, tuple[tuple[float, ...], tuple[float, ...]]] = field(
        default_factory=dict
    )
    geom_friction: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    softness: Mapping[str, tuple[float, float]] = field(default_factory=dict)

    def metadata(self) -> dict[str, str]:
        """The MCAP metadata record: one JSON object per category, {name: [nominal, true]}."""
        return {
            "body_mass": json.dumps(dict(self.body_mass)),
            "body_inertia": json.dumps(
                {k: [list(v[0]), list(v[1])] for k, v in self.body_inertia.items()}
            ),
            "geom_friction": json.dumps(dict(self.geom_friction)),
            "softness": json.dumps(dict(self.softness)),
        }


@dataclass(frozen=True)
class Mismatch:
    """Relative standard deviations of the perturbations (0 leaves a quantity nominal).

    mass_rel_std: σ_m, body masses (inertias scale with them).
    inertia_rel_std: σ_I, each principal moment on top of the mass factor.
    friction_rel_std: σ_μ, sliding friction of every geom and explicit pair.
    softness_rel_std: σ_s, the softness parameters ε and κ of Section V.
    """

    mass_rel_std: float = 0.05
    inertia_rel_std: float = 0.05
    friction_rel_std: float = 0.1
    softness_rel_std: float = 0.1

    @classmethod
    def none(cls) -> Mismatch:
        """The simulated robot is exactly the model."""
        return cls(0.0, 0.0, 0.0, 0.0)

    def factor(self, sigma: float, z: np.ndarray | float) -> np.ndarray:
        """The multiplicative perturbation exp(σ z) of standard normal draw(s) z."""
        return np.exp(sigma * np.asarray(z))

    def apply(
        self,
        model: mujoco.MjModel,
        rng: np.random.Generator,
        softness: Softness | None = None,
        *,
        own_softness: bool = False,
    ) -> tuple[mujoco.MjModel, Softness | None, MismatchRecord]:
        """A perturbed copy of `model`, the true softness, and the record of both.

        softness: the nominal softness (default `Softness()`, what the estimator assumes).
        own_softness: scale the model's own solref/solimp instead (in the returned model; the
        true softness returned is then None: the model's own).
        Draws from `rng` in a fixed order (masses, inertias, friction, softness), also when a
        σ is 0, so that changing one σ does not reshuffle the others.
        """
        nominal = softness or Softness()
        true = copy.deepcopy(model)
        bodies = range(1, model.nbody)
        z_mass = rng.standard_normal(model.nbody)
        z_inertia = rng.standard_normal((model.nbody, 3))
        z_friction = rng.standard_normal(model.ngeom + model.npair)
        z_soft = rng.standard_normal(2)

        masses, inertias = {}, {}
        for b in bodies:
            if model.body_mass[b] <= 0:
                continue
            name = _name(model, mujoco.mjtObj.mjOBJ_BODY, b)
            scale = float(self.factor(self.mass_rel_std, z_mass[b]))
            true.body_mass[b] = model.body_mass[b] * scale
            moments = (
                model.body_inertia[b] * scale * self.factor(self.inertia_rel_std, z_inertia[b])
            )
            if not _triangle(moments):
                moments = model.body_inertia[b] * scale
            true.body_inertia[b] = moments
            if self.mass_rel_std:
                masses[name] = (float(model.body_mass[b]), float(true.body_mass[b]))
            if self.mass_rel_std or self.inertia_rel_std:
                inertias[name] = (
                    tuple(float(v) for v in model.body_inertia[b]),
                    tuple(float(v) for v in true.body_inertia[b]),
                )

        frictions = {}
        if self.friction_rel_std:
            for g in range(model.ngeom):
                if not (model.geom_contype[g] or model.geom_conaffinity[g]):
                    continue
                true.geom_friction[g, 0] *= self.factor(self.friction_rel_std, z_friction[g])
                frictions[_name(model, mujoco.mjtObj.mjOBJ_GEOM, g)] = (
                    float(model.geom_friction[g, 0]),
                    float(true.geom_friction[g, 0]),
                )
            for p in range(model.npair):
                factor = self.factor(self.friction_rel_std, z_friction[model.ngeom + p])
                true.pair_friction[p, :2] *= factor
                frictions[f"pair:{_name(model, mujoco.mjtObj.mjOBJ_PAIR, p)}"] = (
                    float(model.pair_friction[p, 0]),
                    float(true.pair_friction[p, 0]),
                )

        if own_softness:
            s_eps, s_kappa = (float(self.factor(self.softness_rel_std, z)) for z in z_soft)
            if (s_eps, s_kappa) != (1.0, 1.0):
                scale_softness(true, s_eps, s_kappa)
            soft = {}
            if self.softness_rel_std:
                soft = {"eps_scale": (1.0, s_eps), "kappa_scale": (1.0, s_kappa)}
            mujoco.mj_setConst(true, mujoco.MjData(true))
            return true, None, MismatchRecord(masses, inertias, frictions, soft)

        eps = nominal.eps * float(self.factor(self.softness_rel_std, z_soft[0]))
        kappa = nominal.kappa * float(self.factor(self.softness_rel_std, z_soft[1]))
        kappa = max(kappa, 2.0 * float(model.opt.timestep))
        true_softness = Softness(
            eps=eps, kappa=kappa, r_min=nominal.r_min, impratio=nominal.impratio
        )
        soft = {}
        if self.softness_rel_std:
            soft = {"eps": (nominal.eps, true_softness.eps), "kappa": (nominal.kappa, kappa)}

        mujoco.mj_setConst(true, mujoco.MjData(true))
        record = MismatchRecord(masses, inertias, frictions, soft)
        return true, true_softness, record


@dataclass(frozen=True)
class SignedMismatch(Mismatch):
    """Every quantity off by exactly its σ: factor 1 + σ·sign(z), the sign drawn per body,
    moment, geom and softness parameter (the same draws, in the same order, as `Mismatch`).

    signed: marks the record in the log's metadata (`physfuse.simulation` "mismatch").
    """

    signed: bool = True

    def factor(self, sigma: float, z: np.ndarray | float) -> np.ndarray:
        """1 + σ·sign(z): a perturbation of exactly ±σ (z = 0 counts as +)."""
        return 1.0 + sigma * np.where(np.asarray(z) < 0.0, -1.0, 1.0)


def scale_softness(model: mujoco.MjModel, s_eps: float, s_kappa: float) -> None:
    """Scale every solimp's ε_i = (1 − d_i)/d_i (d0 and dwidth) by s_eps and every solref's
    time constant κ_i by s_kappa (≥ 2h), in place (the module docstring has the formulas)."""
    floor = 2.0 * float(model.opt.timestep)
    fields = [*SOLREF_SOLIMP_FIELDS, ("pair_solreffriction", None)]
    for ref_name, imp_name in fields:
        ref = getattr(model, ref_name)
        if len(ref):
            timeconst = ref[:, 0] > 0  # (κ, damping ratio); ≤ 0: direct (−k, −b) or unset
            direct = ref[:, 0] < 0
            ref[timeconst, 0] = np.maximum(ref[timeconst, 0] * s_kappa, floor)
            ref[direct, 0] /= s_kappa**2
            ref[direct, 1] /= s_kappa
        if imp_name is not None and len(getattr(model, imp_name)):
            d = getattr(model, imp_name)[:, :2]  # a view: d0, dwidth
            eps = (1.0 - np.clip(d, 1e-4, 1.0)) / np.clip(d, 1e-4, 1.0)  # MuJoCo's d ≥ 1e-4
            d[:] = 1.0 / (1.0 + s_eps * eps)


def _triangle(moments: np.ndarray) -> bool:
    """Whether principal moments (3,) can belong to a rigid body: each ≤ the sum of the others."""
    a, b, c = (float(v) for v in moments)
    return a <= b + c and b <= a + c and c <= a + b


def _name(model: mujoco.MjModel, obj: int, index: int) -> str:
    return mujoco.mj_id2name(model, obj, index) or f"#{index}"

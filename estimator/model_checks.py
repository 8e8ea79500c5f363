"""What the model says before anything is estimated: whether `physfuse estimate` can use it
with the config's settings at all (`check_for_estimate`), its actuators, its contact settings
and how deep they let the robot sink, and whether the logged commands agree with the logged
joint efforts through those actuators. Used by `physfuse inspect --config` and `estimate`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import mujoco
import numpy as np

from estimator.actuation import (
    actuator_kind,
    check_commanded,
    commanded_force,
    unsupported_reason,
)
from estimator.config import Config
from estimator.errors import ConfigError
from estimator.io.logs.measurements import Measurement
from estimator.settings import Settings, softness_error
from physics.dynamics import Path as EnginePath
from physics.dynamics import check_model
from physics.errors import UnsupportedModelError
from physics.softness import Softness

_OBJ = mujoco.mjtObj


# -- what estimate needs ----------------------------------------------------------------------
def check_for_estimate(config: Config, settings: Settings | None = None) -> None:
    """Every model and setting problem `physfuse estimate` would meet with this config, found
    before a log is read: a ConfigError naming the config, the model file, the option, what
    is expected and how to fix it. settings: those the estimate runs with (default: the
    config's [estimator] table)."""
    settings = settings or Settings.from_config(config)
    model = config.load_model()
    where = f"{config.path}: model {config.model_path}"
    # the engine's requirements on the model's options (friction cone, integrator, noslip,
    # override): every method reports its forces through the native analytic inverse, and
    # the smoother's residuals go through the reference path when estimator.path says so
    paths: list[EnginePath] = ["native"]
    if settings.method in ("physics", "kinematic") and settings.path == "reference":
        paths.append("reference")
    for path in paths:
        try:
            check_model(model, path)
        except UnsupportedModelError as err:
            on = "" if path == "native" else " (for estimator.path = 'reference')"
            raise ConfigError(f"{where}: {err}{on}") from None
    # commands turn into forces through the actuators they name (names the model lacks are
    # the checklist's of `physfuse inspect`, or an error of load_config)
    for name, stream in config.streams.items():
        if stream.kind == "command":
            ids = [mujoco.mj_name2id(model, _OBJ.mjOBJ_ACTUATOR, a) for a in stream.elements]
            check_commanded(model, [i for i in ids if i >= 0], f"{config.path}: streams.{name}")
    # the softness settings on the estimate's model: its timestep the knot step h
    model.opt.timestep = settings.h or model.opt.timestep
    try:
        settings.apply_softness(model)
    except UnsupportedModelError as err:  # κ below 2h
        raise softness_error(config, err) from None
    if "reference" in paths:
        try:
            Softness.of_model(model)
        except UnsupportedModelError as err:
            raise ConfigError(
                f"{where}: {err}; estimator.path = 'reference' takes one flat contact softness "
                "for the whole model: use path = 'native', or set softness_eps and "
                "softness_kappa in [estimator]"
            ) from None
    fits = settings.fit_softness == "first_window" and settings.method == "physics"
    if fits and not settings.sets_softness and settings.model_softness_std == 0:
        raise ConfigError(
            f"{config.path}: estimator.model_softness_std = 0 gives fit_softness = "
            "'first_window' no prior to fit the contact softness against; set "
            "model_softness_std > 0 (default 0.1), or fit_softness = 'none'"
        )


# -- actuators ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class ActuatorRow:
    name: str
    kind: str  # motor | position | velocity | general
    target: str  # the joint (or tendon, site) it drives
    gear: float
    kp: float  # position gain (−biasprm[1]); 0 when none
    kv: float  # velocity gain (−biasprm[2]); 0 when none
    ctrlrange: tuple[float, float] | None
    forcerange: tuple[float, float] | None
    unsupported: str | None  # why commands to it cannot be used (None: they can)


def actuator_rows(model: mujoco.MjModel) -> list[ActuatorRow]:
    rows = []
    for i in range(model.nu):
        trn = int(model.actuator_trntype[i])
        obj = {
            mujoco.mjtTrn.mjTRN_JOINT.value: _OBJ.mjOBJ_JOINT,
            mujoco.mjtTrn.mjTRN_JOINTINPARENT.value: _OBJ.mjOBJ_JOINT,
            mujoco.mjtTrn.mjTRN_TENDON.value: _OBJ.mjOBJ_TENDON,
            mujoco.mjtTrn.mjTRN_SITE.value: _OBJ.mjOBJ_SITE,
        }.get(trn)
        target = mujoco.mj_id2name(model, obj, int(model.actuator_trnid[i, 0])) if obj else None
        rows.append(
            ActuatorRow(
                name=mujoco.mj_id2name(model, _OBJ.mjOBJ_ACTUATOR, i) or f"#{i}",
                kind=actuator_kind(model, i),
                target=target or "?",
                gear=float(model.actuator_gear[i, 0]),
                kp=float(-model.actuator_biasprm[i, 1]),
                kv=float(-model.actuator_biasprm[i, 2]),
                ctrlrange=_range(model.actuator_ctrllimited[i], model.actuator_ctrlrange[i]),
                forcerange=_range(model.actuator_forcelimited[i], model.actuator_forcerange[i]),
                unsupported=unsupported_reason(model, i),
            )
        )
    return rows


def _range(limited: int, values: np.ndarray) -> tuple[float, float] | None:
    return (float(values[0]), float(values[1])) if limited else None


# -- contact settings --------------------------------------------------------------------------
@dataclass(frozen=True)
class ContactSetting:
    """One distinct set of contact parameters and the colliding geoms (or pairs) that have it."""

    solref: tuple[float, ...]  # (κ timeconst, damping ratio), or negative (−stiffness, −damping)
    solimp: tuple[float, ...]  # (d0, dwidth, width, midpoint, power)
    friction: tuple[float, ...]
    condim: int
    margin: float
    elements: tuple[str, ...]

    @property
    def eps(self) -> tuple[float, float]:
        """ε = (1 − d)/d at d0 and at dwidth (paper eq. 27: R = ε·diag(A))."""
        d0, d1 = self.solimp[0], self.solimp[1]
        return (1 - d0) / d0, (1 - d1) / d1


def contact_settings(model: mujoco.MjModel) -> list[ContactSetting]:
    """The colliding geoms' and explicit pairs' contact parameters, grouped when equal."""
    groups: dict[
        tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...], int, float], list[str]
    ] = {}
    for g in range(model.ngeom):
        if not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        key = (
            tuple(np.round(model.geom_solref[g], 12)),
            tuple(np.round(model.geom_solimp[g], 12)),
            tuple(np.round(model.geom_friction[g], 12)),
            int(model.geom_condim[g]),
            float(model.geom_margin[g]),
        )
        groups.setdefault(key, []).append(_geom_name(model, g))
    for p in range(model.npair):
        key = (
            tuple(np.round(model.pair_solref[p], 12)),
            tuple(np.round(model.pair_solimp[p], 12)),
            tuple(np.round(model.pair_friction[p, :3], 12)),
            int(model.pair_dim[p]),
            float(model.pair_margin[p]),
        )
        name = mujoco.mj_id2name(model, _OBJ.mjOBJ_PAIR, p) or f"pair #{p}"
        groups.setdefault(key, []).append(f"pair {name}")
    return [
        ContactSetting(solref, solimp, friction, condim, margin, tuple(names))
        for (solref, solimp, friction, condim, margin), names in groups.items()
    ]


def _geom_name(model: mujoco.MjModel, g: int) -> str:
    name = mujoco.mj_id2name(model, _OBJ.mjOBJ_GEOM, g)
    if name:
        return name
    body = mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, int(model.geom_bodyid[g])) or "world"
    return f"{body}/geom #{g}"


@dataclass(frozen=True)
class RestingDepth:
    """How far a free body sinks into what carries it where its weight is held by contacts."""

    body: str
    penetration_m: float  # the deepest of its (subtree's) contacts, −dist
    height_m: float  # the free joint's z there
    contacts: int


def resting_penetration(model: mujoco.MjModel, keyframe: int | None = None) -> list[RestingDepth]:
    """Per free joint: the height at which its contacts, at rest (v = 0, a = 0) in the
    keyframe's posture (or qpos0), carry its subtree's weight — MuJoCo's inverse dynamics
    (mj_inverse) gives the contact force of each penetration, bisected on the height until the
    free joint's vertical force balances — and the deepest penetration there. Soft contacts
    (a small d, a long κ) rest deep."""
    data = mujoco.MjData(model)
    out = []
    for j in range(model.njnt):
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            continue
        body = int(model.jnt_bodyid[j])
        adr, dof = model.jnt_qposadr[j], model.jnt_dofadr[j]
        if keyframe is not None:
            mujoco.mj_resetDataKeyframe(model, data, keyframe)
        else:
            mujoco.mj_resetData(model, data)
        data.qvel[:], data.qacc[:] = 0.0, 0.0
        z0 = float(data.qpos[adr + 2])

        def lift(z: float, adr: int = adr, dof: int = dof) -> float:
            """The free joint's vertical generalized force needed at height z (> 0: sinking)."""
            data.qpos[adr + 2] = z
            mujoco.mj_inverse(model, data)
            return float(data.qfrc_inverse[dof + 2])

        low, high = z0 - 0.5, z0 + 0.5
        if lift(high) <= 0 or lift(low) >= 0:  # no contact carries it within ±0.5 m
            continue
        for _ in range(60):  # lift(z) > 0: too high to be carried
            mid = 0.5 * (low + high)
            low, high = (low, mid) if lift(mid) > 0 else (mid, high)
        lift(low)
        mine = _subtree(model, body)
        depths = [
            -data.contact[i].dist
            for i in range(data.ncon)
            if {
                int(model.geom_bodyid[data.contact[i].geom1]),
                int(model.geom_bodyid[data.contact[i].geom2]),
            }
            & mine
        ]
        if depths:
            name = mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, body) or f"body{body}"
            out.append(RestingDepth(name, max(depths), low, len(depths)))
    return out


def _subtree(model: mujoco.MjModel, root: int) -> set[int]:
    """The bodies of root's subtree (itself included)."""
    out = {root}
    for b in range(root + 1, model.nbody):
        if int(model.body_parentid[b]) in out:
            out.add(b)
    return out


# -- commands against efforts ------------------------------------------------------------------
@dataclass(frozen=True)
class CommandCheck:
    """The commands' force on one joint through its actuator, against the logged effort."""

    actuator: str
    joint: str
    samples: int
    effort_rms: float  # of the logged effort
    commanded_rms: float  # of the commands' force at the logged joint states
    gain: float  # least-squares effort ≈ gain · commanded
    correlation: float  # of effort and commanded force (about zero)
    residual_rms: float  # of effort − commanded
    clamped: float  # fraction of samples where MuJoCo clamped the force at forcerange
    # σ of effort − commanded force from the encoder's noise: the effort's, and the position
    # and velocity noise through the actuator's stiffness and damping (kp σ_q, kv σ_q̇)
    noise_std: float = 0.0

    @property
    def problem(self) -> str | None:
        """What looks wrong, or None: effort and commanded force apart by more than half the
        effort's RMS and 3σ of the encoder's noise."""
        if self.residual_rms <= max(0.5 * self.effort_rms, 3 * self.noise_std, 1e-12):
            return None
        if self.correlation < -0.9:
            return f"opposite sign (effort ≈ {self.gain:.2g} × the commands' force)"
        if self.correlation > 0.9 and not 1 / 3 < self.gain < 3:
            return (
                f"wrong units or gear? effort ≈ {self.gain:.3g} × the commands' force "
                f"(RMS {self.effort_rms:.3g} against {self.commanded_rms:.3g})"
            )
        return (
            f"disagree: RMS {self.residual_rms:.3g} apart against an effort RMS of "
            f"{self.effort_rms:.3g} (wrong actuator mapping, actuator type or gains?)"
        )


def command_effort_checks(
    model: mujoco.MjModel,
    measurements: Mapping[str, Measurement],
    noise: Mapping[str, float] | None = None,
) -> list[CommandCheck]:
    """For every actuator with logged commands that drives one hinge or slide whose encoder
    logs effort: the force of the commands (zero-order hold) at the logged joint states
    (positions, velocities) through MuJoCo's actuation, against that effort. noise: the
    encoder stream's σ (position_std, velocity_std, effort_std)."""
    noise = noise or {}
    sigma_q, sigma_v = noise.get("position_std", 0.0), noise.get("velocity_std", 0.0)
    sigma_effort = noise.get("effort_std", 0.0)
    encoders = [m for m in measurements.values() if m.kind == "joint_state" and len(m)]
    commands = [m for m in measurements.values() if m.kind == "command" and len(m)]
    if not encoders or not commands:
        return []
    joint_state = encoders[0]
    effort = joint_state.component("effort")  # (N, E)
    position, velocity = joint_state.component("position"), joint_state.component("velocity")
    ctrl = np.full((len(joint_state), model.nu), np.nan)
    for m in commands:
        index = np.searchsorted(m.t_ns, joint_state.t_ns, side="right") - 1
        ok = index >= 0
        for e, name in enumerate(m.elements):
            a = mujoco.mj_name2id(model, _OBJ.mjOBJ_ACTUATOR, name)
            ctrl[ok, a] = m.values[index[ok], e, 0]
    data = mujoco.MjData(model)
    checks = []
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) != mujoco.mjtTrn.mjTRN_JOINT.value:
            continue
        if unsupported_reason(model, a) is not None:
            continue
        j = int(model.actuator_trnid[a, 0])
        joint = mujoco.mj_id2name(model, _OBJ.mjOBJ_JOINT, j) or ""
        if joint not in joint_state.elements or model.jnt_type[j] not in (2, 3):  # slide, hinge
            continue
        e = joint_state.elements.index(joint)
        use = np.isfinite(ctrl[:, a]) & np.isfinite(effort[:, e]) & np.isfinite(position[:, e])
        if use.sum() < 3:
            continue
        commanded, clamped, stiffness, damping = [], 0, 0.0, 0.0
        only = np.full(model.nu, np.nan)
        for k in np.flatnonzero(use):
            data.qpos[model.jnt_qposadr[j]] = position[k, e]
            data.qvel[model.jnt_dofadr[j]] = np.nan_to_num(velocity[k, e])
            mujoco.mj_fwdPosition(model, data)
            mujoco.mj_fwdVelocity(model, data)
            only[a] = ctrl[k, a]
            dof = model.jnt_dofadr[j]
            qfrc, dq, dv = commanded_force(model, data, only, jacobians=True)
            commanded.append(qfrc[dof])
            assert dq is not None and dv is not None
            stiffness, damping = max(stiffness, abs(dq[dof, dof])), max(damping, abs(dv[dof, dof]))
            low, high = model.actuator_forcerange[a]
            f = data.actuator_force[a]
            clamped += bool(model.actuator_forcelimited[a] and (f <= low or f >= high))
        c, y = np.array(commanded), effort[use, e]
        gain = float(c @ y / (c @ c)) if c @ c > 0 else 0.0
        norms = float(np.linalg.norm(c) * np.linalg.norm(y))
        checks.append(
            CommandCheck(
                actuator=mujoco.mj_id2name(model, _OBJ.mjOBJ_ACTUATOR, a) or f"#{a}",
                joint=joint,
                samples=int(use.sum()),
                effort_rms=_rms(y),
                commanded_rms=_rms(c),
                gain=gain,
                correlation=float(c @ y) / norms if norms > 0 else 0.0,
                residual_rms=_rms(y - c),
                clamped=clamped / max(int(use.sum()), 1),
                noise_std=float(
                    np.hypot(np.hypot(sigma_effort, stiffness * sigma_q), damping * sigma_v)
                ),
            )
        )
    return checks


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else 0.0


def command_warnings(checks: list[CommandCheck]) -> list[str]:
    """One warning per actuator whose commands disagree with the logged effort, or whose force
    sits at its forcerange more than a tenth of the time."""
    out = []
    for c in checks:
        if c.problem:
            out.append(
                f"commands to actuator {c.actuator!r} and the effort on {c.joint!r}: {c.problem}"
            )
        elif c.clamped > 0.1:
            out.append(
                f"commands to actuator {c.actuator!r}: its force is at its forcerange "
                f"{100 * c.clamped:.0f}% of the time (wrong units or gains?)"
            )
    return out


def commands_against_efforts(
    config: Config, model: mujoco.MjModel, measurements: Mapping[str, Measurement]
) -> list[CommandCheck]:
    """`command_effort_checks` with the noise σ of the config's encoder stream."""
    noises = [s.noise for s in config.streams.values() if s.kind == "joint_state"]
    return command_effort_checks(model, measurements, noises[0] if noises else None)

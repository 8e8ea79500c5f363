"""The estimator's settings: the `[estimator]` table of a config, one declaration each.

    settings = Settings.from_config(load_config("configs/go2.toml"))
    replace(settings, window_s=2.0)

Each field is declared once, with its default, its meaning and, where it has them, its
choices and whether it must be > 0 (`setting`); `SETTINGS`, `CHOICES` and
`POSITIVE_SETTINGS` are read off the fields. `Settings.from_config` checks every key, type,
range and choice with one line naming the file and key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import mujoco

from estimator.config import Config
from estimator.errors import ConfigError
from physics.errors import UnsupportedModelError
from physics.softness import Softness, override
from physics.softness import scale as scale_softness


def setting(
    default: Any, meaning: str, *, choices: tuple[str, ...] = (), positive: bool = False
) -> Any:
    """A Settings field: its default, what it means (summary.json, the docs), its choices,
    and whether it must be > 0 (a σ, a threshold, a length or a step that divides or scales;
    the others may be 0, which means none, exact or the model's own)."""
    return field(
        default=default, metadata={"meaning": meaning, "choices": choices, "positive": positive}
    )


@dataclass(frozen=True)
class Settings:
    method: str = setting(
        "physics",
        "physics (the physics prior) | kinematic (sensors and a smoothness prior)",
        choices=(
            "physics",
            "kinematic",
            "ekf",
            "ukf",
            "raw",
            "gtsam-legged-ekf",
            "gtsam-legged-smoother",
        ),
    )
    path: str = setting(
        "native",
        "physics path for the residuals: native | reference",
        choices=("native", "reference"),
    )
    h: float = setting(0.0, "knot spacing in s (0: the model's timestep)")
    physics_std_unactuated: float = setting(
        20.0, "σ of u on dofs no actuator drives, N or N·m", positive=True
    )
    physics_std_actuated: float = setting(
        20.0, "σ of u − (actuator force of the commands), N or N·m", positive=True
    )
    accel_prior_std: float = setting(
        200.0, "σ of the smoothness prior on a_k, units/s²", positive=True
    )
    # a constant-acceleration (white jerk) prior with σ_j of fast legged-robot motion, set once
    # (not fitted to any recording); the kinematic baseline's only motion model
    jerk_prior_std: float = setting(
        1000.0, "σ of a constant-acceleration prior on (a_{k+1} − a_k)/h, units/s³ (0: none)"
    )
    jerk_kernel: str = setting(
        "auto",
        "robust kernel of the jerk prior, per dof: none | huber | cauchy | auto (physics: cauchy,"
        " so that impacts get through; kinematic: none)",
        choices=("auto", "none", "huber", "cauchy"),
    )
    huber_k: float = setting(
        2.0, "robust kernel threshold k on a whitened residual block's norm", positive=True
    )
    physics_kernel: str = setting(
        "cauchy",
        "robust kernel of the physics factors: huber | cauchy",
        choices=("huber", "cauchy"),
    )
    sensor_kernel: str = setting(
        "huber",
        "robust kernel of the kinematic sensors (mocap, encoders, IMU)",
        choices=("huber", "cauchy"),
    )
    force_sensor_kernel: str = setting(
        "cauchy",
        "robust kernel of force/torque sensors, predicted through the contact model",
        choices=("huber", "cauchy"),
    )
    window_s: float = setting(4.0, "length of one smoothing window, s", positive=True)
    window_s_no_mocap: float = setting(
        0.5,
        "length of one physics window of a log without mocap, s (the stream's lag: over a "
        "longer one the model's mass error steers the heading through the gyro's bias)",
        positive=True,
    )
    overlap_s: float = setting(
        0.5, "look-ahead of a window: the knots past those it keeps, re-solved by the next, s"
    )
    backward_s: float = setting(
        30.0,
        "how far back the backward pass reaches, s: each window follows the keys the next one "
        "moved, through its marginalized past (0: none; memory grows with it)",
    )
    join: str = setting(
        "quiet",
        "where a window hands over to the next: quiet (the key of least jerk in the later half "
        "of its look-ahead, off impacts, where the marginal prior's linearization holds) | fixed "
        "(overlap_s before its end)",
        choices=("quiet", "fixed"),
    )
    max_iterations: int = setting(
        30, "Levenberg–Marquardt iterations per solve (a window has up to 3)", positive=True
    )
    init: str = setting(
        "best",
        "where each window's physics solve starts: measurements (interpolated to the knots; a "
        "free body's lost pose through a tracked body below it) | kinematic (the kinematic "
        "smoother's solution of the window) | best (from both; the solution of lower cost) | "
        "best_across_gaps (both only in a window where the measurements' start has a gap or "
        "its solve does not converge, else the measurements: one solve where every "
        "coordinate is measured)",
        choices=("measurements", "kinematic", "best", "best_across_gaps"),
    )
    tolerance: float = setting(
        0.001, "stop when an iteration lowers the cost by less than this fraction"
    )
    model_error_std: float = setting(
        0.0,
        "σ of a generalized force offset on the unactuated dofs, which absorbs a constant model "
        "error (weight, contact softness), N or N·m (0: none)",
    )
    model_error_walk: float = setting(
        1.0, "random walk of that offset, N/√s or N·m/√s", positive=True
    )
    contact_forces: str = setting(
        "balanced",
        "contact forces reported: model (the analytic inverse's at the estimate) | balanced "
        "(those plus the least-squares correction that closes the physics residual where the "
        "force is known)",
        choices=("balanced", "model"),
    )
    contact_force_std: float = setting(
        1.0,
        "σ of that correction per contact force component, in units of the robot's weight (0: no "
        "correction)",
    )
    # the model's own contact softness unless set (an override of every element's)
    softness_eps: float | None = setting(
        None,
        "ε replacing every solimp of the model, R = ε·diag(A) (paper eq. 27); unset: the model's "
        "own solimp",
    )
    softness_kappa: float | None = setting(
        None,
        "κ in s replacing every solref of the model (eq. 28; ≥ 2h); unset: the model's own solref",
        positive=True,
    )
    fit_softness: str = setting(
        "first_window",
        "first_window: fit factors on the model's own ε and κ to the log's start (the physics and"
        " the mocap together), then estimate the log with them, unless the config gives the "
        "softness (softness_eps, softness_kappa or a scale: taken as calibrated) | none",
        choices=("none", "first_window"),
    )
    fit_softness_s: float = setting(
        2.0, "how much of the log's start fit_softness fits on, s", positive=True
    )
    softness_eps_scale: float = setting(
        1.0,
        "a factor on the model's own ε = (1 − d)/d of every solimp, per-geom values kept (after "
        "softness_eps when that is set); `physfuse calibrate --setting softness_eps_scale` fits "
        "it",
        positive=True,
    )
    softness_kappa_scale: float = setting(
        1.0, "a factor on every solref time constant κ of the model", positive=True
    )
    model_softness_std: float = setting(
        0.1,
        "relative σ of the model's contact softness (ε and κ), which the covariances account for "
        "(consider covariance; 0: the model's softness taken as exact)",
    )
    model_mass_std: float = setting(
        0.05, "relative σ of the model's masses, which the covariances account for (0: exact)"
    )
    bias_prior_accel: float = setting(0.5, "σ of the first accelerometer bias, m/s²", positive=True)
    bias_prior_gyro: float = setting(0.05, "σ of the first gyro bias, rad/s", positive=True)
    fd_eps: float = setting(1e-06, "finite-difference step of mjd_inverseFD", positive=True)

    @property
    def jerk_robust_kernel(self) -> str:
        """The jerk prior's kernel: "auto" is Cauchy with the physics factors, none without."""
        if self.jerk_kernel != "auto":
            return self.jerk_kernel
        return "cauchy" if self.method == "physics" else "none"

    @property
    def sets_softness(self) -> bool:
        """Whether these settings give the contact softness (a value or a factor)."""
        return (
            self.softness_eps is not None
            or self.softness_kappa is not None
            or self.softness_eps_scale != 1.0
            or self.softness_kappa_scale != 1.0
        )

    def apply_softness(self, model: mujoco.MjModel) -> None:
        """Override the model's own softness where softness_eps / softness_kappa are set,
        then scale it by softness_eps_scale / softness_kappa_scale."""
        override(model, eps=self.softness_eps, kappa=self.softness_kappa)
        scale_softness(model, self.softness_eps_scale, self.softness_kappa_scale)

    @classmethod
    def from_config(cls, config: Config) -> Settings:
        """Read the optional [estimator] table; unknown keys and bad values name themselves
        (`load_config` runs this, so that a bad setting fails before anything is read)."""
        table = config.sections.get("estimator", {})
        if not isinstance(table, Mapping):
            raise ConfigError(
                f"{config.path}: estimator = {table!r}; expected a table [estimator] of settings"
            )
        unknown = [key for key in table if key not in SETTINGS]
        if unknown:
            raise ConfigError(
                f"{config.path}: estimator.{unknown[0]} is not a setting "
                f"(settings: {', '.join(SETTINGS)})"
            )
        values = {key: _setting_value(config, key, value) for key, value in table.items()}
        settings = cls(**values)
        try:  # validates ε and κ
            Softness(
                **{
                    name: value
                    for name, value in (
                        ("eps", settings.softness_eps),
                        ("kappa", settings.softness_kappa),
                    )
                    if value is not None
                }
            )
        except UnsupportedModelError as err:
            raise softness_error(config, err) from None
        return settings


# key → (default, meaning); key → choices; the keys that must be > 0
SETTINGS: Mapping[str, tuple[object, str]] = {
    f.name: (f.default, f.metadata["meaning"]) for f in fields(Settings)
}
CHOICES: Mapping[str, tuple[str, ...]] = {
    f.name: f.metadata["choices"] for f in fields(Settings) if f.metadata["choices"]
}
POSITIVE_SETTINGS = frozenset(f.name for f in fields(Settings) if f.metadata["positive"])


def _setting_value(config: Config, key: str, value: Any) -> Any:
    """One [estimator] value checked against its setting's type and range (ConfigError)."""
    default, meaning = SETTINGS[key]
    where = f"{config.path}: estimator.{key} = {value!r}"
    if key in CHOICES:
        if not isinstance(value, str) or value not in CHOICES[key]:
            raise ConfigError(f"{where}; expected one of " + ", ".join(map(repr, CHOICES[key])))
        return value
    if isinstance(default, int) and not isinstance(default, bool):  # a count
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{where}; expected an integer ≥ 1 ({meaning})")
        return value
    number = isinstance(value, int | float) and not isinstance(value, bool)
    what = "a factor" if key.endswith("_scale") else "a number"
    bound = "> 0" if key in POSITIVE_SETTINGS else "≥ 0"
    if not number or not math.isfinite(value) or value < 0:
        raise ConfigError(f"{where}; expected {what} {bound} ({meaning})")
    if value == 0 and key in POSITIVE_SETTINGS:
        raise ConfigError(f"{where}; expected {what} > 0 ({meaning})")
    return float(value)


def softness_error(config: Config, err: UnsupportedModelError) -> ConfigError:
    """Softness's message "softness kappa=… is …" as the config's setting's, one line:
    "CONFIG: estimator.softness_kappa=… is …"."""
    return ConfigError(f"{config.path}: estimator." + str(err).replace("softness ", "softness_", 1))

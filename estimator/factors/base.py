"""What a sensor kind's factor unit works with: the rows it adds to a window's problem.

A unit (one module per kind, `estimator.factors`) does three things for a stream:

    add_sensors(spec, stream) -> names   the MuJoCo sensors that predict its measurements,
                                         per element, in measurement order
    factors(stream, m, rows, grid)       its residual rows on the knots: `SensorBlock`s, the
        -> StreamFactors                 bias dims it adds, the efforts it knows
    holdout(stream)                      its channels for `evaluate --holdout`: names, σ and
        -> Holdout                       prediction − measurement per sample

The residual of a block at knot k, whitened by σ (the linearizer adds the robust kernel and
the Jacobians through `mjd_inverseFD`'s sensor derivatives):

    vector   (s(q_k, v_k, a_k) + b_k − m_k) / σ
    quat     Log(m_k⁻¹ ⊗ s(q_k)) / σ
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from estimator.config import StreamConfig
from estimator.io.logs.measurements import Measurement
from estimator.knots import interpolated_at_knots, samples_between_knots
from estimator.settings import Settings

_OBJ = mujoco.mjtObj
MODEL_ERROR = "model error"  # Problem.bias_of key of the generalized force offset
OBJ_OF_ELEMENT = {
    "body": _OBJ.mjOBJ_XBODY,
    "site": _OBJ.mjOBJ_SITE,
    "joint": _OBJ.mjOBJ_JOINT,
    "geom": _OBJ.mjOBJ_GEOM,
}


@dataclass(frozen=True)
class SensorBlock:
    """One stream's rows in the residual: which sensordata entries and how to compare them.

    rows:    (n,) sensordata indices of the prediction, in measurement component order
    kind:    "vector" (p − m), "quat" (Log(m⁻¹ p), 4 sensordata rows → 3 residual rows)
    values:  (T, n_meas) the measurement at each knot (NaN: no measurement)
    sigma:   (n_res,) per residual row
    bias:    slice of the bias vector added to the prediction (IMU, F/T), or None
    stage:   "pos", "vel" or "acc": what the sensor depends on (an acceleration-stage sensor
             sees a knot's position through a_k, 1/h² strongly)
    group:   rows per element (a marker's 3, a joint's 1): missing samples and the robust
             kernel go by element; 0: the block is one element
    kernel:  the Settings field that names its robust kernel
    alpha:   (T,) or None. A position-stage stream's samples, one per knot and slot: the
             sample of knot k was taken at t_{k−1} + α_k h and is predicted between the two
             knots, (1 − α_k) s(q_{k−1}) + α_k s(q_k) (quaternions normalized). None: the
             measurement is at the knot's time (interpolated to it, or averaged)
    slot:    which of a knot's samples (0: its first; a stream faster than the knots has
             several blocks)
    labels:  (n_res,) what each residual row is: element and component ("torso position z")
    """

    stream: str
    kind: str
    rows: np.ndarray
    values: np.ndarray
    sigma: np.ndarray
    bias: slice | None = None
    stage: str = "pos"
    group: int = 0
    kernel: str = "sensor_kernel"
    alpha: np.ndarray | None = None
    slot: int = 0
    labels: tuple[str, ...] = ()

    def elements(self) -> list[SensorBlock]:
        """One block per element (per `group` rows); [self] for a one-element block."""
        if not self.group or self.group == len(self.rows):
            return [self]
        g = self.group
        sigma = self.sigma
        return [
            replace(
                self,
                rows=self.rows[i : i + g],
                values=self.values[:, i : i + g],
                sigma=sigma[..., i : i + g],
                bias=None
                if self.bias is None
                else slice(self.bias.start + i, self.bias.start + i + g),
                group=0,
                labels=self.labels[i : i + g],
            )
            for i in range(0, len(self.rows), g)
        ]


@dataclass(frozen=True)
class Grid:
    """The window a unit maps its stream onto.

    model: the problem's model, with every stream's sensors; t_ns: (T,) knot times; nb: the
    first bias dim still free; at_sample_times: position-stage samples at their own times
    (`SensorBlock.alpha`), else interpolated to the knots (the filters, which step from knot
    to knot)."""

    model: mujoco.MjModel
    t_ns: np.ndarray
    settings: Settings
    nb: int
    at_sample_times: bool = True

    @property
    def T(self) -> int:
        return len(self.t_ns)

    @property
    def h_ns(self) -> int:
        """The knot step, ns (the model's timestep is the knots')."""
        return round(self.model.opt.timestep * 1e9)

    def position_slots(self, m: Measurement) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """A position-stage stream's values (T, E, K) on the knots by slot, with α (or None)."""
        if self.at_sample_times:
            return samples_between_knots(m, self.t_ns)
        return [(interpolated_at_knots(m, self.t_ns), None)]


@dataclass
class StreamFactors:
    """What one stream adds to a window's problem.

    blocks:     its residual rows
    bias_walk:  (nb_s,) random walk σ per √s of the bias dims it adds (after `Grid.nb`)
    bias_prior: (nb_s,) σ of those dims at the first knot
    efforts:    dof → (T,) a measured generalized force held at the knots (NaN: none), which
                the physics factor takes as known where no command drives the dof
    """

    blocks: list[SensorBlock] = field(default_factory=list)
    bias_walk: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bias_prior: np.ndarray = field(default_factory=lambda: np.zeros(0))
    efforts: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class Holdout:
    """A stream's channels for `evaluate --holdout`: names (C,), σ (C,), the units of its
    quantities, and residuals(predicted (N, sensor rows), m) → (N, C) prediction −
    measurement, channels in sensor order."""

    names: tuple[str, ...]
    sigma: np.ndarray
    units: tuple[str, ...]
    residuals: Callable[[np.ndarray, Measurement], np.ndarray]


def labels(element: str, quantity: str) -> tuple[str, ...]:
    """Labels of a 3-axis residual: "<element> <quantity> x", … (either may be empty)."""
    prefix = " ".join(w for w in (element, quantity) if w)
    return tuple(f"{prefix} {axis}".strip() for axis in "xyz")


def add_element_sensors(
    spec: mujoco.MjSpec,
    stream: StreamConfig,
    sensors: Sequence[tuple[mujoco.mjtSensor, str]],
    on: Sequence[tuple[int, str]] | None = None,
) -> list[str]:
    """Add `sensors` (type, tag) to `spec` for each element of the stream, on the element
    itself (or on `on[e]`: (mjtObj, name)); their names, elements × sensors order."""
    added: list[str] = []
    for e, element in enumerate(stream.elements):
        objtype, objname = on[e] if on else (OBJ_OF_ELEMENT[stream.element_type], element)
        for kind, tag in sensors:
            sensor = spec.add_sensor()
            sensor.name = f"physfuse/{stream.name}/{element}/{tag}"
            sensor.type = kind
            sensor.objtype = objtype
            sensor.objname = objname
            added.append(sensor.name)
    return added


def vector_residuals(columns: Callable[[Measurement], np.ndarray]) -> Callable[..., np.ndarray]:
    """residuals(predicted, m) = predicted − columns(m) (N, C)."""
    return lambda predicted, m: predicted - columns(m)


def biased_pair(
    name: str,
    rows: list[np.ndarray],
    values: tuple[np.ndarray, np.ndarray],
    counts: tuple[np.ndarray, np.ndarray],
    std: tuple[float, float],
    stages: tuple[str, str],
    nb: int,
    quantities: tuple[str, str],
    kernel: str = "sensor_kernel",
) -> list[SensorBlock]:
    """The two 3-axis halves of an IMU (accelerometer, gyro) or a force/torque sensor, with
    their biases b[nb : nb + 3] and b[nb + 3 : nb + 6]. values, counts: (T, 3) each, the mean
    of the samples a knot stands for and how many; averaging n samples gives σ/√n."""
    return [
        SensorBlock(
            name,
            "vector",
            rows[i],
            values[i],
            std[i] / np.sqrt(np.maximum(counts[i], 1)),  # (T, 3)
            slice(nb + 3 * i, nb + 3 * i + 3),
            stages[i],
            kernel=kernel,
            labels=labels("", quantities[i]),
        )
        for i in range(2)
    ]


# -- a factor's rows at every interior knot ----------------------------------------------------
@dataclass
class Terms:
    """Inverse dynamics and sensors at the interior knots k = 1 … T−2, stacked (row i ↔ knot
    i + 1). a, u, known (u_known at the state): (K, nv); s: (K, ns). With Jacobians,
    derivatives with respect to (x_{k−1}, x_k, x_{k+1}): Ju (K, nv, 3 nv) of u − u_known,
    Js (K, ns, 3 nv), and da (K, 3, nv, 3) by key and dof group (`Linearizer.dense`: a_k's row
    d reaches only d's group)."""

    a: np.ndarray
    u: np.ndarray
    known: np.ndarray
    s: np.ndarray
    Ju: np.ndarray | None = None
    Js: np.ndarray | None = None
    da: np.ndarray | None = None


@dataclass
class Block:
    """One factor's whitened rows at every interior knot, robust weights applied.

    r: (K, m); J: (K, m, 3 nv) over (x_{k−1}, x_k, x_{k+1}) or None; dofwise (the priors, m =
    nv): J (K, keys, nv, 3) by key and dof group instead (`Linearizer.dense`; the jerk prior
    reaches 4 keys, to x_{k+2}); J_bias: (K, m, nb) over b_k or None; cost: (K,) robust cost of
    the rows at each knot; valid: (K, m) rows that carry a factor (a measurement, a known
    force); the others are 0.
    """

    name: str
    r: np.ndarray
    J: np.ndarray | None
    cost: np.ndarray
    valid: np.ndarray
    J_bias: np.ndarray | None = None
    dofwise: bool = False  # row d reaches dof d's group only (itself; a rotation's 3)
    sensor: bool = False  # a sensor's rows (`BandedSystem.of` stacks them with the others')
    slot: int = 0  # a sensor's: which of a knot's samples (`SensorBlock.slot`)

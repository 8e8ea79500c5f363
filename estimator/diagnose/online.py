"""`detect`'s unmodeled-contact test run causally, knot by knot, on a stream's newest
estimates (`estimator.stream.Stream(diagnose=...)`).

Per new knot: the force each body's residual asks for (`unmodeled_forces`; nothing from a knot
whose residual no force on one body explains beyond the `OUTLIER_QUANTILE` of the stream's
knots at the last calibration), its median over the window of L knots that ends at the knot,
d² against the calibration, divided by the noise level of the knots `GUARD_S` to
`REFERENCE_S` before (`local_scale`, causal), against the batch detector's threshold. The
calibration (a robust mean and covariance per body, `robust_mean_cov`) comes from the
stream's own windows so far: nothing is tested before `CALIBRATE_S` of them, and it is
refitted every `RECALIBRATE_S` on the last `HISTORY_S`.

An alarm that has lasted a window is reported at once (`Event.ongoing`: body, force and
interval from the knots so far; `detected_ns` the knot that confirmed it), and again, final,
when it has been off for `JOIN_S`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import mujoco
import numpy as np

from estimator.diagnose.detect import (
    JOIN_S,
    OUTLIER_QUANTILE,
    REFERENCE_S,
    Detection,
    DetectorSettings,
    Event,
    alarm_event,
    alarm_threshold,
    knot_forces,
    local_scale,
    robust_mean_cov,
    unexplained,
    windowed_median,
)
from estimator.diagnose.unmodeled import (
    CONTACT_MARGIN_M,
    UnmodeledForces,
    unmodeled_forces,
    with_margin,
)
from estimator.estimate import Estimate

CALIBRATE_S = 2.0  # windows before the first test
RECALIBRATE_S = 1.0
HISTORY_S = 60.0  # the windows the calibration is fitted on


class OnlineDetector:
    """Unmodeled contacts, online. model: the estimate's model; sigma_f: the contact-force
    prior σ_f [N] (`diagnose`); h: the knot step [s]."""

    def __init__(
        self,
        model: mujoco.MjModel,
        sigma_f: float,
        h: float,
        settings: DetectorSettings | None = None,
    ) -> None:
        self.settings = replace(settings or DetectorSettings(), causal=True)
        self.model = with_margin(model, CONTACT_MARGIN_M)  # once, not per update
        self.sigma_f, self.h = sigma_f, h
        self.L = max(1, round(self.settings.window_s / h))
        self.keep = round(HISTORY_S / h)
        self.calibrate_after, self.recalibrate = round(CALIBRATE_S / h), round(RECALIBRATE_S / h)
        self.join = max(self.L, round(JOIN_S / h))
        self.reach = max(2, round(REFERENCE_S / h)) + 1
        self.t_ns: list[int] = []  # the knots so far (the last `keep`)
        self.info: list[np.ndarray] = []  # (B, 3, 3) per knot
        self.grad: list[np.ndarray] = []  # (B, 3)
        self.own: list[np.ndarray] = []  # (B, 3) the force each knot alone asks for
        self.misfit: list[float] = []  # rᵀS⁻¹r per knot
        self.unexplained: list[float] = []  # what no force on one body explains of it
        self.cut = np.inf  # knots less explained are left out (`detect.outliers`)
        self.force: list[np.ndarray] = []  # (B, 3) the windowed force F̂
        self.d2_raw: list[np.ndarray] = []  # (B,) before the local scale
        self.d2: list[np.ndarray] = []  # (B,)
        self.bodies: tuple[str, ...] = ()
        self.body_ids = np.zeros(0, dtype=int)
        self.mean = self.cov = self.cov_inv = np.zeros(0)
        self.seen = np.zeros(0, dtype=bool)  # bodies whose force the residual sees
        self.threshold = np.inf
        self.calibrated_at = -1  # knot count at the last calibration
        self.count = 0  # knots seen
        self.alarm: tuple[int, int] | None = None  # the open run: first and last alarmed knot
        self.reported_ns: int | None = None  # the open run's first report, when

    def add(self, est: Estimate, knots: Sequence[int], sigma: np.ndarray) -> list[Event]:
        """The knots `knots` of `est` (consecutive, after the last ones added; sigma: (T, nv)
        the physics σ) in; the events they report out."""
        knots = [k for k in knots if not self.t_ns or est.t_ns[k] > self.t_ns[-1]]
        if not knots:
            return []
        forces = unmodeled_forces(self.model, est, sigma, self.sigma_f, 0.0, knots=knots)
        if not self.bodies:
            self.bodies, self.body_ids = forces.bodies, forces.body_ids
            B = len(self.bodies)
            self.mean, self.cov = np.zeros((B, 3)), np.tile(np.eye(3), (B, 1, 1))
            self.cov_inv = self.cov.copy()
            self.threshold = alarm_threshold(self.settings, B)
        per_knot, left = knot_forces(forces), unexplained(forces)
        events = []
        for k in knots:
            events += self._knot(
                int(est.t_ns[k]),
                forces.info[k],
                forces.grad[k],
                per_knot[k],
                (float(forces.misfit[k]), float(left[k])),
            )
        return events

    def close(self) -> list[Event]:
        """The end of the stream: an open alarm's final report."""
        if self.alarm is None:
            return []
        event = self._final(*self.alarm)
        self.alarm = None
        return [event] if event else []

    # -- one knot ---------------------------------------------------------------------------

    def _knot(
        self,
        t_ns: int,
        info: np.ndarray,
        grad: np.ndarray,
        own: np.ndarray,
        misfit: tuple[float, float],
    ) -> list:
        self.t_ns.append(t_ns)
        self.info.append(info)
        self.grad.append(grad)
        self.misfit.append(misfit[0])
        self.unexplained.append(misfit[1])
        self.own.append(own if not misfit[1] > self.cut else np.full_like(own, np.nan))
        B = len(self.bodies)
        window = np.array(self.own[-self.L :])  # (≤ L, B, 3)
        force = np.full((B, 3), np.nan)
        if len(window) == self.L:
            for b in range(B):
                force[b] = windowed_median(window[:, b], self.L, causal=True)[-1]
        self.force.append(force)
        self.d2_raw.append(self._d2(force))
        self.count += 1
        if self.count >= self.calibrate_after and (
            self.calibrated_at < 0 or self.count - self.calibrated_at >= self.recalibrate
        ):
            self._calibrate()
        scale = local_scale(np.array(self.d2_raw[-self.reach :]), self.h, causal=True)[-1]
        d2 = self.d2_raw[-1] / scale
        self.d2.append(d2)
        self._trim()
        return self._track(bool(np.nan_to_num(d2, nan=0.0).max() > self.threshold))

    def _calibrate(self) -> None:
        force = np.array(self.force)
        B = len(self.bodies)
        self.seen = np.zeros(B, dtype=bool)
        for b in range(B):
            ok = np.isfinite(force[:, b]).all(axis=1)
            # as `detect`: a body whose force the residual never sees has none to diagnose
            if ok.sum() > 10 and np.ptp(force[ok, b], axis=0).any():
                self.mean[b], self.cov[b] = robust_mean_cov(force[ok, b])
                self.cov_inv[b] = np.linalg.inv(self.cov[b])
                self.seen[b] = True
        left = np.array(self.unexplained)
        left = left[np.isfinite(left)]
        self.cut = float(np.quantile(left, OUTLIER_QUANTILE)) if left.size else np.inf
        self.calibrated_at = self.count
        # the reference cells of the local scale, under the new calibration
        for i in range(max(0, len(self.force) - self.reach), len(self.force)):
            self.d2_raw[i] = self._d2(self.force[i])

    def _d2(self, force: np.ndarray) -> np.ndarray:
        """(B,) d² of one knot's windowed force (NaN before the calibration)."""
        if self.calibrated_at < 0:
            return np.full(len(self.bodies), np.nan)
        diff = force - self.mean
        d2 = np.einsum("bi,bij,bj->b", diff, self.cov_inv, diff)
        return np.where(self.seen, d2, np.nan)

    def _trim(self) -> None:
        extra = len(self.t_ns) - self.keep
        if extra > 0 and self.alarm is None:
            for buffer in (self.t_ns, self.info, self.grad, self.force, self.d2_raw, self.d2):
                del buffer[:extra]
            for numbers in (self.misfit, self.unexplained):
                del numbers[:extra]
            del self.own[:extra]

    # -- alarms → events --------------------------------------------------------------------

    def _track(self, alarm: bool) -> list[Event]:
        k = len(self.t_ns) - 1
        out = []
        if self.alarm is not None and k - self.alarm[1] > self.join:  # the alarm is over
            final = self._final(*self.alarm)
            out += [final] if final else []
            self.alarm = None
        if alarm:
            if self.alarm is None:
                self.alarm, self.reported_ns = (k, k), None
            s = self.alarm[0]
            self.alarm = (s, k)
            if self.reported_ns is None and k - s + 1 >= self.L:  # an event lasts a window
                self.reported_ns = self.t_ns[k]
                out.append(replace(self._event(s, k), detected_ns=self.t_ns[k], ongoing=True))
        return out

    def _final(self, s: int, e: int) -> Event | None:
        if self.reported_ns is None:  # shorter than a window: a contact made a knot off
            return None
        return replace(self._event(s, e), detected_ns=self.reported_ns)

    def _event(self, s: int, e: int) -> Event:
        """`detect.alarm_event` on the knots of the alarm s … e (indices into the buffers)."""
        lo = max(0, s - self.L + 1)
        span = slice(lo, e + 1)
        forces = UnmodeledForces(
            np.array(self.t_ns[span]),
            self.bodies,
            self.body_ids,
            np.array(self.info[span]),
            np.array(self.grad[span]),
            np.array(self.misfit[span]),
        )
        det = Detection(
            forces,
            self.settings,
            self.L,
            np.array(self.force[span]),
            self.mean,
            self.cov,
            np.array(self.d2[span]),
            self.threshold,
            [],
        )
        return alarm_event(det, s - lo, e - lo)

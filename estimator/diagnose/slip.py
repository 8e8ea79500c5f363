"""Slips: a modeled contact that slides where the model holds it.

Per touching pair (a robot body and what it touches) and knot of the estimate, over its
pressing contacts (each weighted by its normal force): the slide velocity — the contact
points' velocity relative to what they touch, its tangential part (J_c v, tangent rows) —;
whether the analytic inverse slides there (Algorithm 5's branch: the impulse on the friction
cone, `efc_state` CONE); and the friction the balanced contact forces ask for against what
the cone gives, ‖f_t‖ / (μ f_n) (the forces that, with the known actuation, best explain the
motion, `estimator.contact_forces`). A contact that slides while the motion asks for far less
friction than the model gives — below `STICKING` of its cone — is one the model would have
held: the surface is more slippery than the model's (a foot on ice). A contact that slides
with about the model's friction slides as the model expects (Go2 standing under pushes and
excitation: its feet slide by centimetres at 0.5–0.7 of the cone; on a patch of a twentieth
of the friction, 0.15–0.22).

1. The slide over windows of `WINDOW_S`: D_k = Σ_j v_t,j h over the window's touching knots
   (a slide moves the contact; the estimate's velocity noise comes back), in the tangent
   plane of the pair's usual normal; a window needs half its knots touching.
2. Calibration from the log: per pair, a robust mean and covariance of D over the log (as
   `detect.robust_mean_cov`: slips are rare, so they do not set the scale).
3. Detection: the Mahalanobis d² of D against χ²(2)'s quantile for the target false-alarm
   rate, spread over the windows per minute and the pairs (`DetectorSettings`).
4. Alarms less than `JOIN_S` apart are one slip, widened over the knots around them where
   the contact keeps moving (faster than `MOVING` × its median speed while touching: a slow
   start or end that one window does not show), if its contact moved at least
   `MIN_SLIDE_M` over it, the inverse slides at most of its touching knots and the friction
   asked for is below `STICKING` of the cone on average over them; a slide with the model's
   friction is the model's own, no event.

Event: kind "slip", from the first to the last knot its contact moves, target the body
(the pair's name where neither side is the world), component "contact <body>–<what it
touches>", force (1,) the distance its contact points slid over the interval (their path
[m]), its variance that of the windows' slide.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import mujoco
import numpy as np
from scipy.stats import chi2

from estimator.contact_forces import contact_jacobian
from estimator.diagnose.detect import DetectorSettings, Event, robust_mean_cov, runs
from estimator.diagnose.online import CALIBRATE_S, HISTORY_S, RECALIBRATE_S
from estimator.estimate import Estimate

WINDOW_S = 0.1  # of the slide test
STICKING = 0.4  # of the friction cone: a slide asking for less is not the model's
MIN_SLIDE_M = 0.005  # a slide shorter than this is none
JOIN_S = 0.25  # alarms closer than this are one slip (a foot that lifts and lands sliding)
MOVING = 5.0  # × the pair's median speed while touching: its contact point moves
PRESSING = 1e-3  # of the robot's weight: a contact's normal force above this presses
SLIP = "slip"


@dataclass(frozen=True)
class Slides:
    """Per touching pair: which knots it touches, its slide there and the model's verdict."""

    pairs: list[tuple[int, int]]  # (robot body, what it touches: body id, 0 the world)
    touching: np.ndarray  # (T, P) bool
    velocity: np.ndarray  # (T, P, 3) tangential velocity, world frame [m/s] (0: not touching)
    normal: np.ndarray  # (T, P, 3) the contacts' mean normal
    sliding: np.ndarray  # (T, P) the inverse's contacts on the cone (a weighted fraction)
    friction: np.ndarray  # (T, P) ‖f_t‖ / (μ f_n) of the balanced forces


def slides(model: mujoco.MjModel, est: Estimate, weight: float) -> Slides:
    """The slide velocity of every touching pair along the estimate (module docstring)."""
    data = mujoco.MjData(model)
    T = len(est.t_ns)
    per_knot: list[dict[tuple[int, int], np.ndarray]] = []
    for k in range(T):
        data.qpos[:] = est.qpos[k]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        per_knot.append(_knot(model, data, est, k, weight))
    pairs = sorted({pair for knot in per_knot for pair in knot})
    at = np.zeros((T, len(pairs), 8))  # velocity, normal, sliding, friction
    touching = np.zeros((T, len(pairs)), dtype=bool)
    for k, knot in enumerate(per_knot):
        for pair, row in knot.items():
            touching[k, pairs.index(pair)] = True
            at[k, pairs.index(pair)] = row
    return Slides(pairs, touching, at[..., :3], at[..., 3:6], at[..., 6], at[..., 7])


def _knot(
    model: mujoco.MjModel, data: mujoco.MjData, est: Estimate, k: int, weight: float
) -> dict[tuple[int, int], np.ndarray]:
    """pair → (tangential velocity (3), normal (3), sliding, friction) at knot k, its pressing
    contacts weighted by their normal force."""
    constraints = est.constraints[k]
    contacts = constraints.contacts
    sums: dict[tuple[int, int], np.ndarray] = {}  # Σ f_n, then Σ f_n × each quantity
    for i in np.flatnonzero(contacts.efc_address >= 0):
        a, dim = int(contacts.efc_address[i]), int(contacts.dim[i])
        if dim < 3:
            continue  # frictionless: nothing holds it
        f = constraints.efc_impulse[a : a + 3] / est.h
        if f[0] <= PRESSING * weight:
            continue
        b1, b2 = (int(model.geom_bodyid[g]) for g in contacts.geom[i])
        pair = (b2, b1) if b2 and (b1 == 0 or b2 < b1) else (b1, b2)
        rel = contact_jacobian(model, data, contacts, int(i)) @ est.qvel[k]  # geom2 − geom1
        if pair[0] != b2:
            rel = -rel  # the velocity of the pair's first body over the second
        frame = contacts.frame[i]
        mu = contacts.friction[i, :2]
        friction = float(np.hypot(f[1] / mu[0], f[2] / mu[1]) / f[0])
        sliding = float(constraints.efc_state[a] == mujoco.mjtConstraintState.mjCNSTRSTATE_CONE)
        row = np.r_[1.0, frame[1:].T @ rel[1:], frame[0], sliding, friction]
        sums[pair] = sums.get(pair, np.zeros(9)) + f[0] * row
    out = {}
    for pair, s in sums.items():
        row = s[1:] / s[0]
        row[3:6] /= np.linalg.norm(row[3:6])
        out[pair] = row
    return out


def slips(
    model: mujoco.MjModel,
    est: Estimate,
    weight: float,
    settings: DetectorSettings | None = None,
) -> list[Event]:
    """The slips of the estimate (module docstring); `weight` the robot's [N]."""
    settings = settings or DetectorSettings()
    found = slides(model, est, weight)
    h, T = est.h, len(est.t_ns)
    L = max(2, round(WINDOW_S / h))
    threshold = alarm_threshold(settings, len(found.pairs))
    out = []
    for j, pair in enumerate(found.pairs):
        touching = found.touching[:, j]
        if touching.sum() < 4 * L:
            continue
        slide = _windowed_sum(found.velocity[:, j] * h, touching, L, settings.causal)
        calibration = _calibrated(slide, found.normal[touching, j])
        if calibration is None:
            continue
        d2 = calibration.d2(slide)
        speed = np.linalg.norm(found.velocity[:, j], axis=1)
        moving = touching & (speed > MOVING * np.median(speed[touching]))
        spans: list[list[int]] = []  # lo, hi, first alarm, last alarm
        for s, e in runs(np.nan_to_num(d2) > threshold, gap=round(JOIN_S / h)):
            lo, hi = (s - L + 1, e) if settings.causal else (s - L // 2, e + (L - 1) // 2)
            lo, hi = max(0, lo), min(T - 1, hi)
            # the slide's slow start and end, below the window test: the contact moving on
            while lo > 0 and moving[lo - 1]:
                lo -= 1
            while not settings.causal and hi < T - 1 and moving[hi + 1]:
                hi += 1
            if spans and lo <= spans[-1][1]:
                spans[-1][1], spans[-1][3] = hi, e
            else:
                spans.append([lo, hi, s, e])
        for lo, hi, s, e in spans:
            knots = slice(lo, hi + 1)
            slid = _slip(
                est.t_ns[knots],
                touching[knots],
                speed[knots],
                found.sliding[knots, j],
                found.friction[knots, j],
                moving[knots],
                h,
            )
            if slid is not None:
                score = float(np.nanmax(d2[s : e + 1])) / threshold
                out.append(_event(model, pair, slid, int(est.t_ns[s]), score, calibration, L))
    return sorted(out, key=lambda e: e.start_ns)


def alarm_threshold(settings: DetectorSettings, pairs: int) -> float:
    """χ²(2)'s quantile for the false-alarm rate, spread over the windows per minute and the
    touching pairs (Bonferroni)."""
    p = settings.false_alarms_per_min * WINDOW_S / 60.0 / max(pairs, 1)
    return float(chi2.isf(p, 2))


@dataclass(frozen=True)
class Calibration:
    """A pair's window slides where nothing happens: in its tangent plane (`basis`, (2, 3)),
    their robust mean and covariance."""

    basis: np.ndarray
    mean: np.ndarray
    cov: np.ndarray

    def d2(self, slide: np.ndarray) -> np.ndarray:
        """(…,) the Mahalanobis d² of window slides (…, 3), world frame (NaN stays NaN)."""
        diff = slide @ self.basis.T - self.mean
        return np.einsum("...i,ij,...j->...", diff, np.linalg.inv(self.cov), diff)


def _calibrated(slide: np.ndarray, normals: np.ndarray) -> Calibration | None:
    """The calibration from a pair's window slides (T, 3) (NaN: a window it hardly touched)
    and its contacts' normals; None with too few windows."""
    ok = np.isfinite(slide).all(axis=1)
    if ok.sum() < 10:
        return None
    basis = _tangent_basis(np.median(normals, axis=0))
    mean, cov = robust_mean_cov(slide[ok] @ basis.T)
    return Calibration(basis, mean, cov)


@dataclass(frozen=True)
class _Slid:
    start_ns: int
    end_ns: int
    path: float  # m
    knots: int  # from the first to the last moving knot


def _slip(
    t_ns: np.ndarray,
    touching: np.ndarray,
    speed: np.ndarray,
    sliding: np.ndarray,
    friction: np.ndarray,
    moving: np.ndarray,
    h: float,
) -> _Slid | None:
    """Whether the knots of an alarm (arrays over them) are a slip (module docstring, 4)."""
    path = float(speed[touching].sum() * h)
    slides_itself = sliding[touching].mean() >= 0.5 if touching.any() else False
    held = friction[touching].mean() < STICKING if touching.any() else False
    if path < MIN_SLIDE_M or not (slides_itself and held) or not moving.any():
        return None
    first, last = np.flatnonzero(moving)[[0, -1]]  # from the first to the last moving knot
    return _Slid(int(t_ns[first]), int(t_ns[last]), path, int(last - first + 1))


def _event(
    model: mujoco.MjModel,
    pair: tuple[int, int],
    slid: _Slid,
    detected_ns: int,
    score: float,
    calibration: Calibration,
    L: int,
) -> Event:
    name = _name(model, pair)
    return Event(
        kind=SLIP,
        start_ns=slid.start_ns,
        end_ns=slid.end_ns,
        detected_ns=detected_ns,
        target=name,
        component=f"contact {name}–{_body(model, pair[1])}",
        force=np.array([slid.path]),
        force_cov=np.array([[np.trace(calibration.cov) * slid.knots / L]]),
        score=score,
    )


class OnlineSlips:
    """`slips` run causally on a stream's newest knots (`estimator.stream.Stream(diagnose=…)`):
    per touching pair the slide over the window that ends at the knot, d² against a
    calibration from the stream's own windows (after `CALIBRATE_S`, refitted every
    `RECALIBRATE_S` on the last `HISTORY_S`), the batch threshold. An alarm is reported once
    its knots so far pass the slip's checks (`Event.ongoing`), and again, final, when it has
    been off for `JOIN_S`. model: the estimate's; weight: the robot's [N]; h: the knot step."""

    def __init__(
        self,
        model: mujoco.MjModel,
        weight: float,
        h: float,
        settings: DetectorSettings | None = None,
    ) -> None:
        self.model, self.weight, self.h = model, weight, h
        self.settings = replace(settings or DetectorSettings(), causal=True)
        self.data = mujoco.MjData(model)
        self.L = max(2, round(WINDOW_S / h))
        self.keep = round(HISTORY_S / h)
        self.calibrate_after, self.recalibrate = round(CALIBRATE_S / h), round(RECALIBRATE_S / h)
        self.join = round(JOIN_S / h)
        self.t_ns: list[int] = []
        self.rows: list[dict[tuple[int, int], np.ndarray]] = []  # per knot: `_knot`'s
        self.slide: dict[tuple[int, int], list[np.ndarray]] = {}  # per pair and knot
        self.calibration: dict[tuple[int, int], Calibration] = {}
        self.moving_mps: dict[tuple[int, int], float] = {}  # faster: the contact moves
        self.threshold = np.inf
        self.count, self.calibrated_at = 0, -1
        self.alarms: dict[tuple[int, int], list] = {}  # pair → [first, last, reported_ns]

    def add(self, est: Estimate, knots: Sequence[int]) -> list[Event]:
        """The knots `knots` of `est` (consecutive, after the last ones added) in; the
        events they report out."""
        out = []
        for k in knots:
            if self.t_ns and est.t_ns[k] <= self.t_ns[-1]:
                continue
            self.data.qpos[:] = est.qpos[k]
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_comPos(self.model, self.data)
            out += self._knot(int(est.t_ns[k]), _knot(self.model, self.data, est, k, self.weight))
        return out

    def close(self) -> list[Event]:
        """The end of the stream: the open alarms' final reports."""
        out = [e for pair, a in self.alarms.items() if (e := self._final(pair, *a))]
        self.alarms = {}
        return out

    def _knot(self, t_ns: int, rows: dict[tuple[int, int], np.ndarray]) -> list[Event]:
        self.t_ns.append(t_ns)
        self.rows.append(rows)
        self.count += 1
        for pair in rows:
            self.slide.setdefault(pair, [np.full(3, np.nan)] * (len(self.t_ns) - 1))
        recent = self.rows[-self.L :]
        for pair, buffer in self.slide.items():
            touching = [r[pair][:3] for r in recent if pair in r]
            full = len(recent) == self.L and len(touching) >= self.L / 2
            buffer.append(np.sum(touching, axis=0) * self.h if full else np.full(3, np.nan))
        if self.count >= self.calibrate_after and (
            self.calibrated_at < 0 or self.count - self.calibrated_at >= self.recalibrate
        ):
            self._calibrate()
        out = []
        for pair, calibration in self.calibration.items():
            d2 = float(np.nan_to_num(calibration.d2(self.slide[pair][-1])))
            out += self._track(pair, d2 > self.threshold, d2)
        self._trim()
        return out

    def _calibrate(self) -> None:
        for pair, buffer in self.slide.items():
            touching = np.array([r[pair] for r in self.rows if pair in r])
            if len(touching) >= 4 * self.L:
                calibration = _calibrated(np.array(buffer), touching[:, 3:6])
                if calibration is not None:
                    self.calibration[pair] = calibration
                    speed = np.linalg.norm(touching[:, :3], axis=1)
                    self.moving_mps[pair] = MOVING * float(np.median(speed))
        self.threshold = alarm_threshold(self.settings, len(self.slide))
        self.calibrated_at = self.count

    def _trim(self) -> None:
        extra = len(self.t_ns) - self.keep
        if extra > 0 and not self.alarms:
            del self.t_ns[:extra], self.rows[:extra]
            for buffer in self.slide.values():
                del buffer[:extra]

    def _track(self, pair: tuple[int, int], alarm: bool, d2: float) -> list[Event]:
        k = len(self.t_ns) - 1
        out = []
        a = self.alarms.get(pair)
        if a is not None and k - a[1] > self.join:  # the alarm is over
            final = self._final(pair, *a)
            out += [final] if final else []
            del self.alarms[pair]
            a = None
        if alarm:
            if a is None:
                a = self.alarms[pair] = [k, k, None, d2]
            a[1], a[3] = k, max(a[3], d2)
            if a[2] is None and (event := self._event(pair, a[0], k, a[3])) is not None:
                a[2] = self.t_ns[k]
                out.append(replace(event, detected_ns=self.t_ns[k], ongoing=True))
        return out

    def _final(self, pair: tuple[int, int], s: int, e: int, reported: int | None, d2: float):
        event = self._event(pair, s, e, d2)
        if event is None:
            return None
        return replace(event, detected_ns=reported if reported is not None else self.t_ns[-1])

    def _event(self, pair: tuple[int, int], s: int, e: int, d2: float) -> Event | None:
        """The slip of the alarm s … e (buffer indices), if it is one, from the window
        before it on (and the knots before where the contact was already moving)."""
        fast = self.moving_mps[pair]

        def moving(i: int) -> bool:
            row = self.rows[i].get(pair)
            return row is not None and float(np.linalg.norm(row[:3])) > fast

        lo = max(0, s - self.L + 1)
        while lo > 0 and moving(lo - 1):
            lo -= 1
        rows = np.array([r.get(pair, np.full(8, np.nan)) for r in self.rows[lo : e + 1]])
        touching = np.isfinite(rows[:, 0])
        speed = np.where(touching, np.linalg.norm(np.nan_to_num(rows[:, :3]), axis=1), 0.0)
        sliding, friction = np.nan_to_num(rows[:, 6]), np.nan_to_num(rows[:, 7])
        t_ns = np.array(self.t_ns[lo : e + 1])
        slid = _slip(t_ns, touching, speed, sliding, friction, touching & (speed > fast), self.h)
        if slid is None:
            return None
        calibration = self.calibration[pair]
        return _event(
            self.model, pair, slid, self.t_ns[e], d2 / self.threshold, calibration, self.L
        )


def _windowed_sum(x: np.ndarray, ok: np.ndarray, L: int, causal: bool) -> np.ndarray:
    """(T, 3) Σ of x over each window of L knots (centred, or ending at the knot if causal)
    where `ok`; NaN where fewer than half its knots are."""
    c = np.r_[np.zeros((1, 3)), np.cumsum(np.where(ok[:, None], x, 0.0), axis=0)]
    n = np.r_[0, np.cumsum(ok)]
    T = len(x)
    end = np.arange(T) + (1 if causal else (L + 1) // 2)
    end = np.minimum(end, T)
    start = np.maximum(end - L, 0)
    out = c[end] - c[start]
    out[(n[end] - n[start]) < L / 2] = np.nan
    return out


def _tangent_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) two orthonormal directions across `normal`."""
    n = normal / np.linalg.norm(normal)
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.vstack([e1, np.cross(n, e1)])


def _body(model: mujoco.MjModel, b: int) -> str:
    return "world" if b == 0 else (model.body(b).name or f"body {b}")


def _name(model: mujoco.MjModel, pair: tuple[int, int]) -> str:
    """The robot body of a pair touching the world; both bodies' names otherwise."""
    first = _body(model, pair[0])
    return first if pair[1] == 0 else f"{first}–{_body(model, pair[1])}"

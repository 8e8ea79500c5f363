"""Unmodeled contacts: detected, isolated to a body and identified as a force, from
`UnmodeledForces`.

1. Windowed fit: per body, the force each knot alone asks for (I_kb⁻¹ g_kb, `unmodeled`),
   its component-wise median over each window of L knots (`window_s`): F̂_kb. Left out: the
   knots whose residual no force on one body explains (`unexplained` above its
   `OUTLIER_QUANTILE` over the log) — where the estimate let the motion disagree with the
   model (its physics kernel's outliers: a foot chattering on touchdown asks for hundreds of
   newtons on every other knot, and five such in a window move its median); a push is
   explained by a force on its body. A window needs half its knots.
2. Calibration from the log's own residuals: per body, a robust mean μ_b and covariance C_b of
   F̂_kb over the log (the trimmed covariance of the 90% of windows nearest the median,
   corrected for the trimming, iterated): events are rare, so they do not set the scale.
   μ_b is the force the model is off by all along (a mass or a mounting), not an event.
3. Detection: d²_kb = (F̂_kb − μ_b)ᵀ C_b⁻¹ (F̂_kb − μ_b) is χ²(3) where nothing happens,
   divided by the log's local noise level (`local_scale`, a CFAR test); the alarm threshold
   is χ²(3)'s quantile for the target false-alarm rate, spread over the windows per minute
   and the bodies (Bonferroni): p = rate · window_s / 60 s / B. The log's first and last
   window are not tested.
4. Alarms less than `JOIN_S` apart are one event if they last a window or more. Isolation:
   the body whose constant force explains the residual over the event best (`robust_fit`'s
   likelihood ratio). Interval:
   within the alarms widened by half a window, the knots [a, b] that maximize
   (Σ uᵀg)² / Σ uᵀI u along the force's direction u (a constant force that starts and
   stops: the likelihood ratio of the interval). Identification: `robust_fit` over [a, b],
   its covariance C_b scaled by L / (b − a + 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from estimator.diagnose.unmodeled import UnmodeledForces

TRIM = 0.9  # the fraction of windows that set the calibration
GUARD_S, REFERENCE_S = 0.35, 1.5  # `local_scale`: the cells around a knot it compares with
REFERENCE_QUANTILE = 0.5
JOIN_S = 0.1  # alarms closer than this are one event
OUTLIER_QUANTILE = 0.99  # knots less explained than this fraction of the log's are left out
HUBER = 4.0  # a knot's misfit beyond this many medians is down-weighted (`robust_fit`)
RIDGE = 1e-9  # relative, keeps a body with no information at a knot solvable


@dataclass(frozen=True)
class DetectorSettings:
    window_s: float = 0.05  # length of the force fit's window
    false_alarms_per_min: float = 1.0  # target rate that sets the threshold
    causal: bool = False  # windows that end at the knot (online) instead of centred on it


@dataclass(frozen=True)
class Event:
    """One detected event. Times in ns (log clock).

    kind: "unmodeled contact" (target: the body; force: world frame [N], at `point` or its
    centre of mass) or "sensor fault" (target: the stream; component: the residual row, "gyro z",
    "FR_hip_joint position"; force: the size of the step in the row's units, whitened σ),
    "model error" (`contact_model`) or "slip" (`slip`: force (1,) the distance slid [m]).
    score: the peak statistic over its threshold (> 1).
    """

    kind: str
    start_ns: int
    end_ns: int
    detected_ns: int  # when the detector first alarmed (a causal detector: its delay)
    target: str
    force: np.ndarray  # (3,) | (1,)
    force_cov: np.ndarray  # (3, 3) | (1, 1)
    score: float
    component: str = ""
    candidates: dict[str, float] = field(default_factory=dict)  # body → likelihood ratio
    explained_by: str = ""  # a sensor fault that explains this event ("": none)
    ongoing: bool = False  # online: the first report, its alarm still on (the final follows)
    point: np.ndarray | None = None  # (3,) where the force acts, world [m] (None: at the
    # body's centre of mass; `contact_point`)

    @property
    def magnitude(self) -> float:
        return float(np.linalg.norm(self.force))

    @property
    def magnitude_std(self) -> float:
        u = self.force / max(self.magnitude, 1e-12)
        return float(np.sqrt(max(u @ self.force_cov @ u, 0.0)))


@dataclass(frozen=True)
class Detection:
    """What the detector saw: per knot and body the windowed force and its statistic."""

    forces: UnmodeledForces
    settings: DetectorSettings
    window: int  # L, knots
    force: np.ndarray  # (T, B, 3) F̂_kb (NaN where no window fits)
    mean: np.ndarray  # (B, 3) μ_b
    cov: np.ndarray  # (B, 3, 3) C_b
    d2: np.ndarray  # (T, B)
    threshold: float
    events: list[Event]


def detect(forces: UnmodeledForces, settings: DetectorSettings | None = None) -> Detection:
    settings = settings or DetectorSettings()
    T, B = forces.grad.shape[:2]
    L = max(1, round(settings.window_s / forces.h))
    per_knot = knot_forces(forces)
    per_knot[outliers(unexplained(forces))] = np.nan
    force = np.full((T, B, 3), np.nan)
    mean, cov = np.zeros((B, 3)), np.tile(np.eye(3), (B, 1, 1))
    d2 = np.full((T, B), np.nan)
    for b in range(B):
        force[:, b] = windowed_median(per_knot[:, b], L, settings.causal)
        ok = np.isfinite(force[:, b]).all(axis=1)
        # a body whose force the residual never sees (its dofs' forces all unknown, or moved
        # only through a joint whose force is free) has none to diagnose
        if ok.sum() > 10 and np.ptp(force[ok, b], axis=0).any():
            mean[b], cov[b] = robust_mean_cov(force[ok, b])
            diff = force[ok, b] - mean[b]
            d2[ok, b] = np.einsum("ki,ij,kj->k", diff, np.linalg.inv(cov[b]), diff)
    # the log's first and last window: the smoother saw them from one side only
    d2[: L + 1], d2[max(0, T - L - 1) :] = np.nan, np.nan
    threshold = alarm_threshold(settings, B)
    d2 = d2 / local_scale(d2, forces.h, settings.causal)[:, None]
    detection = Detection(forces, settings, L, force, mean, cov, d2, threshold, [])
    alarm = np.nan_to_num(d2, nan=0.0).max(axis=1) > threshold
    joined = runs(alarm, gap=max(L, round(JOIN_S / forces.h)))
    # an event lasts: a push of a window or more keeps a window's median up that long; a
    # contact made or broken a knot off its estimate moves it for less
    events = [alarm_event(detection, s, e) for s, e in joined if e - s + 1 >= L]
    return Detection(forces, settings, L, force, mean, cov, d2, threshold, events)


def alarm_threshold(settings: DetectorSettings, bodies: int) -> float:
    """χ²(3)'s quantile for the false-alarm rate, spread over the windows per minute and the
    bodies (Bonferroni): p = rate · window_s / 60 s / B."""
    p = settings.false_alarms_per_min * settings.window_s / 60.0 / max(bodies, 1)
    return float(chi2.isf(p, 3))


def alarm_event(det: Detection, s: int, e: int) -> Event:
    """The event of alarmed windows s … e (inclusive)."""
    forces, L = det.forces, det.window
    T = len(forces.t_ns)
    if det.settings.causal:  # the windows ending at s … e cover s − L + 1 … e
        lo, hi = max(0, s - L + 1), e
    else:
        lo, hi = max(0, s - L // 2), min(T - 1, e + (L - 1) // 2)
    span = slice(lo, hi + 1)
    fits = [
        robust_fit(forces.info[span, b], forces.grad[span, b]) for b in range(len(forces.bodies))
    ]
    ratio = np.array([fit[2] for fit in fits])
    b = int(np.argmax(ratio))
    F, w = fits[b][0], fits[b][1]
    info, grad = forces.info[span, b] * w[:, None, None], forces.grad[span, b] * w[:, None]
    a, z = best_interval(info, grad, F)
    force = robust_fit(forces.info[lo + a : lo + z + 1, b], forces.grad[lo + a : lo + z + 1, b])[0]
    a, z = lo + a, lo + z
    cov = det.cov[b] * L / (z - a + 1)
    peak = float(np.nanmax(det.d2[s : e + 1]))
    return Event(
        kind="unmodeled contact",
        start_ns=int(forces.t_ns[a]),
        end_ns=int(forces.t_ns[z]),
        detected_ns=int(forces.t_ns[s]),
        target=forces.bodies[b],
        force=force,
        force_cov=cov,
        score=peak / det.threshold,
        candidates={name: float(r) for name, r in zip(forces.bodies, ratio, strict=True)},
    )


def local_scale(d2: np.ndarray, h: float, causal: bool) -> np.ndarray:
    """(T,) how much noisier the residual is around each knot than over the whole log (≥ 1):
    the `REFERENCE_QUANTILE` of d² (every body) over the reference knots — from `GUARD_S` to
    `REFERENCE_S` before the knot (and after it, unless causal) — over that quantile of
    χ²(3). A constant-false-alarm-rate test (radar's CFAR): a robot that rocks after a push
    or trots over impacts raises its own threshold there, the guard keeps an event out of its
    own reference."""
    T = len(d2)
    guard, reach = max(1, round(GUARD_S / h)), max(2, round(REFERENCE_S / h))
    level = np.nanmax(np.nan_to_num(d2, nan=-np.inf), axis=1)  # the largest over bodies
    level = np.where(np.isfinite(level), level, np.nan)
    expected = chi2.ppf(REFERENCE_QUANTILE, 3)
    out = np.ones(T)
    for k in range(T):
        before = level[max(0, k - reach) : max(0, k - guard)]
        after = level[k + guard : k + reach] if not causal else level[:0]
        cells = np.concatenate([before, after])
        cells = cells[np.isfinite(cells)]
        if len(cells) >= guard:
            out[k] = max(1.0, float(np.quantile(cells, REFERENCE_QUANTILE)) / expected)
    return out


def unexplained(forces: UnmodeledForces) -> np.ndarray:
    """(T,) what of each knot's misfit no constant force on one body explains: rᵀS⁻¹r −
    max_b g_kbᵀ I_kb⁻¹ g_kb (NaN where the knot has no residual)."""
    explained = np.einsum("tbi,tbi->tb", forces.grad, np.nan_to_num(knot_forces(forces)))
    return forces.misfit - explained.max(axis=1, initial=0.0)


def outliers(unexplained: np.ndarray, cut: float | None = None) -> np.ndarray:
    """(T,) bool: the knots above `cut` (default: the `OUTLIER_QUANTILE` of `unexplained`)."""
    finite = unexplained[np.isfinite(unexplained)]
    if cut is None:
        if not finite.size:
            return np.zeros(len(unexplained), dtype=bool)
        cut = float(np.quantile(finite, OUTLIER_QUANTILE))
    return np.nan_to_num(unexplained, nan=-np.inf) > cut


def knot_forces(forces: UnmodeledForces) -> np.ndarray:
    """(T, B, 3) the force each knot alone asks for on each body, I_kb⁻¹ g_kb (NaN: none)."""
    out = np.full(forces.grad.shape, np.nan)
    has = np.trace(forces.info, axis1=2, axis2=3) > 0
    out[has] = _solve(forces.info[has], forces.grad[has])
    return out


def windowed_median(x: np.ndarray, L: int, causal: bool) -> np.ndarray:
    """(T, 3) component-wise median of x (T, 3) over windows of L knots ending at each knot
    (causal) or centred on it, of the knots that have a value (NaN: left out); NaN where the
    window is not whole or fewer than half its knots have one. A median: a knot or two the
    model cannot explain (a foot touching down a knot early asks for hundreds of newtons) do
    not move it; a force that lasts the window does."""
    T = len(x)
    pad = np.full((L - 1, x.shape[1]), np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(np.vstack([pad, x]), L, axis=0)
    has = np.isfinite(windows).all(axis=1)  # (T, L)
    out = np.full((T, x.shape[1]), np.nan)
    enough = has.sum(axis=1) >= (L + 1) // 2
    enough[: L - 1] = False  # not whole
    out[enough] = np.nanmedian(windows[enough], axis=-1)
    if causal:
        return out[:T]
    shift = L // 2  # centred: the window ending at k + L//2
    return np.vstack([out[shift:T], np.full((shift, x.shape[1]), np.nan)])


def robust_fit(info: np.ndarray, grad: np.ndarray, iterations: int = 5):
    """The constant force that best explains knots (info (n, 3, 3), grad (n, 3)), knots that
    disagree with it down-weighted (Huber on each knot's misfit (g − I F)ᵀ I⁻¹ (g − I F), at
    `HUBER` × its median): (F, weights (n,), likelihood ratio (Σwg)ᵀ(ΣwI)⁻¹(Σwg))."""
    has = np.trace(info, axis1=1, axis2=2) > 0
    w = has.astype(float)
    if not has.any():
        return np.zeros(3), w, 0.0
    F = np.median(_solve(info[has], grad[has]), axis=0)
    for _ in range(iterations):
        misfit = grad - info @ F
        e = np.zeros(len(w))
        e[has] = np.einsum("ki,ki->k", misfit[has], _solve(info[has], misfit[has]))
        c = HUBER * max(float(np.median(e[has])), 1e-300)
        w = np.where(has, np.minimum(1.0, np.sqrt(c / np.maximum(e, 1e-300))), 0.0)
        F = _solve((info * w[:, None, None]).sum(axis=0), (grad * w[:, None]).sum(axis=0))
    g = (grad * w[:, None]).sum(axis=0)
    return F, w, float(g @ F)


def best_interval(info: np.ndarray, grad: np.ndarray, force: np.ndarray) -> tuple[int, int]:
    """[a, b] (inclusive, indices into the knots given) maximizing (Σ uᵀg)² / Σ uᵀI u with
    u = force / |force|: where a force along u most likely acted."""
    u = force / max(float(np.linalg.norm(force)), 1e-12)
    s = np.r_[0.0, np.cumsum(grad @ u)]
    n = np.r_[0.0, np.cumsum(np.einsum("i,kij,j->k", u, info, u))]
    best, out = -np.inf, (0, len(grad) - 1)
    for a in range(len(grad)):
        num = (s[a + 1 :] - s[a]) ** 2
        den = np.maximum(n[a + 1 :] - n[a], 1e-12)
        ratio = num / den
        z = int(np.argmax(ratio))
        if ratio[z] > best and (s[a + 1 + z] - s[a]) > 0:
            best, out = float(ratio[z]), (a, a + z)
    return out


def runs(mask: np.ndarray, gap: int = 0) -> list[tuple[int, int]]:
    """(start, end) inclusive of each run of True, runs less than `gap` apart joined."""
    idx = np.flatnonzero(mask)
    if not idx.size:
        return []
    out = [[int(idx[0]), int(idx[0])]]
    for k in idx[1:]:
        if k - out[-1][1] <= gap:
            out[-1][1] = int(k)
        else:
            out.append([int(k), int(k)])
    return [(a, b) for a, b in out]


def robust_mean_cov(x: np.ndarray, iterations: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the `TRIM` fraction of rows nearest the centre (Mahalanobis),
    scaled to be consistent at the normal distribution."""
    p = x.shape[1]
    mean = np.median(x, axis=0)
    cov = np.cov(x, rowvar=False) + RIDGE * np.eye(p)
    cut = chi2.ppf(TRIM, p)
    consistency = TRIM / chi2.cdf(cut, p + 2)
    for _ in range(iterations):
        diff = x - mean
        d2 = np.einsum("ki,ij,kj->k", diff, np.linalg.inv(cov), diff)
        keep = d2 <= np.quantile(d2, TRIM)
        mean = x[keep].mean(axis=0)
        cov = np.cov(x[keep], rowvar=False) * consistency
        cov += RIDGE * np.trace(cov) * np.eye(p)
    return mean, cov


def _solve(info: np.ndarray, grad: np.ndarray) -> np.ndarray:
    ridge = RIDGE * np.maximum(np.trace(info, axis1=-2, axis2=-1), 1e-300)
    return np.linalg.solve(info + ridge[..., None, None] * np.eye(3), grad[..., None])[..., 0]

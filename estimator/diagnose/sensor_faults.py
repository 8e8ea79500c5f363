"""Sensor faults: a stream's residual rows that step, drift or jump, isolated to the stream and
the component (`Estimate.residuals`, whitened, labelled by `residual_labels`).

Each row is standardized by its own robust scale over the log (median and 1.4826 × the
median absolute deviation — the log's statistics, not the config's σ). A fault is a step: the
row's mean over windows of `STEP_S` leaves its usual range and stays there, for `PERSIST_S`
or to the end of the log — an IMU bias step, a drifting sensor, a mount that moved, an
encoder whose reading jumped (the estimate follows an encoder only partly: the other sensors
and the physics hold it). What the motion does to the residuals comes back: a push the
estimate follows late, a grasp the contact model predicts a little off (on the nominal
recordings, excursions of 0.6–0.9 s at up to 16× the threshold; humanoid_push's torso mocap
around its 1.0 s push then "explained" the push away). An event starts where the cumulative
sum of the row's deviation turns (the CUSUM change point).

Threshold: the Gaussian tail for the false-alarm rate (`DetectorSettings`), spread over the
rows and the windows per minute, both signs.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.stats import norm

from estimator.diagnose.detect import DetectorSettings, Event, runs
from estimator.estimate import Estimate

STEP_S = 0.5  # window of the step test
PERSIST_S = 2.0  # how long a step must stay (unless the log ends first)
MIN_SCALE = 0.1  # of the stated σ
ONE_FAULT_S = 0.5  # faults starting this close together: one fault and its consequences
NOT_SENSORS = ("physics", "prior", "jerk prior")  # factor types that are not a sensor's


def sensor_faults(est: Estimate, settings: DetectorSettings | None = None) -> list[Event]:
    settings = settings or DetectorSettings()
    h = est.h
    out = []
    streams = {n: r for n, r in est.residuals.items() if n not in NOT_SENSORS}
    rows = sum(r.shape[1] for r in streams.values())
    if not rows:
        return []
    step_threshold = norm.isf(settings.false_alarms_per_min * STEP_S / 60.0 / rows / 2.0)
    L = max(2, round(STEP_S / h))
    for name, r in streams.items():
        labels = est.residual_labels.get(name, [])
        for j in range(r.shape[1]):
            x = r[:, j]
            ok = np.isfinite(x)
            if ok.sum() < 2 * L:
                continue
            label = labels[j] if j < len(labels) else f"row {j}"
            centre, scale = _robust(x[ok])
            z = (x - centre) / scale
            out += _steps(est, name, label, z, L, step_threshold, scale)
    return isolated(out)


def isolated(faults: list[Event]) -> list[Event]:
    """Faults starting within `ONE_FAULT_S` of each other are one: the highest-scoring row
    is the fault, the others its consequences (explained_by it): a stream that steps
    moves the estimate, and with it every other stream's residuals."""
    faults = sorted(faults, key=lambda e: e.start_ns)
    out: list[Event] = []
    group: list[Event] = []
    for fault in [*faults, None]:
        if fault is not None and group and fault.start_ns - group[0].start_ns <= ONE_FAULT_S * 1e9:
            group.append(fault)
            continue
        if group:
            top = max(group, key=lambda e: e.score)
            name = f"{top.target} {top.component}"
            out += [top] + [replace(e, explained_by=name) for e in group if e is not top]
        group = [fault] if fault is not None else []
    return out


def _steps(
    est: Estimate, stream: str, label: str, z: np.ndarray, L: int, threshold: float, scale: float
) -> list[Event]:
    ok = np.isfinite(z)
    filled = np.where(ok, z, 0.0)
    c = np.r_[0.0, np.cumsum(filled)]
    n = np.r_[0.0, np.cumsum(ok)]
    end = np.arange(len(z)) + 1
    start = np.maximum(end - L, 0)
    count = n[end] - n[start]
    mean = np.where(count >= L / 2, (c[end] - c[start]) / np.maximum(count, 1), np.nan)
    if not np.isfinite(mean).any():  # a row sampled too sparsely for a step's window
        return []
    centre, spread = _robust(mean[np.isfinite(mean)])
    standard = (mean - centre) / spread
    events = []
    last = int(np.flatnonzero(np.isfinite(mean))[-1])
    stays = max(L, round(PERSIST_S / est.h))
    for s, e in runs(np.nan_to_num(np.abs(standard)) > threshold, gap=L):
        if e - s + 1 < L or (e - s + 1 < stays and e < last - 1):  # a step stays; the motion's
            continue  # transients come back
        lo = max(0, s - L)
        # the change point: where the cumulative deviation from the usual level turns
        cusum = np.cumsum(filled[lo : e + 1] - centre)
        line = cusum[-1] * np.arange(1, len(cusum) + 1) / len(cusum)
        onset = lo + int(np.argmax(np.abs(cusum - line)))
        after = z[onset : e + 1][np.isfinite(z[onset : e + 1])]
        size = (float(after.mean()) - centre) * scale if after.size else float("nan")
        peak = float(np.nanmax(np.abs(standard[s : e + 1])))
        events.append(_event(est, stream, label, onset, e, s, size, peak / threshold))
    return events


def _event(
    est: Estimate, stream: str, label: str, a: int, b: int, alarm: int, size: float, score: float
) -> Event:
    return Event(
        kind="sensor fault",
        start_ns=int(est.t_ns[a]),
        end_ns=int(est.t_ns[b]),
        detected_ns=int(est.t_ns[alarm]),
        target=stream,
        component=label,
        force=np.array([size]),
        force_cov=np.zeros((1, 1)),
        score=score,
    )


def _robust(x: np.ndarray) -> tuple[float, float]:
    """Median and robust σ, the σ at least `MIN_SCALE` (whitened: a fraction of the stated
    noise; a quantized encoder's residuals can be nearly all zero)."""
    centre = float(np.median(x))
    return centre, max(1.4826 * float(np.median(np.abs(x - centre))), MIN_SCALE)

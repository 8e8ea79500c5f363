"""Measurements on the knot grid: the grid itself, and a stream's samples aligned to it.

Three alignments, by what a sample measures (`estimator.problem` explains the Euler step):

    samples_between_knots   a position-stage sample at t_{k−1} + α h, kept as a sample of
                            knot k with its α (poses, markers, encoders)
    averaged_at_knots       the mean of the rate or acceleration samples of the Euler step a
                            knot's v_k or a_k belongs to (gyro, accelerometer, force/torque)
    interpolated_at_knots   linear interpolation to the knots (the filters; initial guesses)
    held_at_knots           the last sample at or before each knot (commands, efforts)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from estimator.errors import ConfigError, LogError
from estimator.io.logs.align import resample
from estimator.io.logs.measurements import Measurement

MAX_KNOTS = 50_000_000  # 28 h at 2 ms: more is a clock mismatch, and would not fit in memory


def knot_grid(measurements: Mapping[str, Measurement], h: float) -> np.ndarray:
    """(T,) knot times spanning the measured streams (commands excluded), step h."""
    spans = {
        m.stream: (int(m.t_ns[0]), int(m.t_ns[-1]))
        for m in measurements.values()
        if len(m) and m.kind != "command"
    }
    if not spans:
        raise ConfigError("no measurements to estimate from: every mapped stream is empty")
    step = round(h * 1e9)
    start = min(a for a, _ in spans.values())
    end = max(b for _, b in spans.values())
    if (end - start) // step >= MAX_KNOTS:  # streams on different clocks, not a long log
        each = ", ".join(f"{name} {a / 1e9:.3f}–{b / 1e9:.3f} s" for name, (a, b) in spans.items())
        raise LogError(
            f"the streams span {(end - start) / 1e9:.6g} s, over {MAX_KNOTS:.0e} knots of "
            f"{h * 1e3:g} ms ({each}); are they on different clocks? Align them with a "
            "stream's time_offset_ns, or read the recorder's times with stamp = \"log\""
        )
    return np.arange(start, end + 1, step, dtype=np.int64)


def interpolated_at_knots(m: Measurement, t_ns: np.ndarray) -> np.ndarray:
    """(T, E, K) linear interpolation (quaternions normalized) between the samples that
    bracket each knot; NaN across gaps longer than 2.5 sample periods."""
    period = int(np.median(np.diff(m.t_ns))) if len(m) > 1 else 0
    return resample(m, t_ns, max_gap_ns=int(2.5 * period))


def samples_between_knots(
    m: Measurement, t_ns: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """The samples of `m` on the knots, by slot: per slot, values (T, E, K) (NaN where a knot
    has no sample in that slot) and α (T,). The sample at t ∈ (t_{k−1}, t_k] belongs to knot k,
    α_k = (t − t_{k−1})/h, its first such sample to slot 0, a second to slot 1, …. Only knots
    whose prediction is on interior knots (k − 1 ≥ 1 and k ≤ T − 2; k = 1 for a sample at t_1)
    carry samples."""
    T = len(t_ns)
    h_ns = int(t_ns[1] - t_ns[0]) if T > 1 else 1
    k = np.searchsorted(t_ns, m.t_ns, side="left")
    inside = ((k >= 2) & (k <= T - 2)) | ((k == 1) & (m.t_ns == t_ns[min(1, T - 1)]))
    k, t, values = k[inside], m.t_ns[inside], m.values[inside]
    slot = np.arange(len(k)) - np.searchsorted(k, k, side="left")  # samples sorted by time
    out: list[tuple[np.ndarray, np.ndarray | None]] = []
    for s in range(int(slot.max()) + 1 if len(k) else 1):
        mine = slot == s
        slot_values = np.full((T, *m.values.shape[1:]), np.nan)
        slot_values[k[mine]] = values[mine]
        alpha = np.ones(T)
        alpha[k[mine]] = (t[mine] - t_ns[k[mine] - 1]) / h_ns
        out.append((slot_values, alpha))
    return out


def averaged_at_knots(
    m: Measurement, t_ns: np.ndarray, stage: str, late_ns: int = 0, h_ns: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(T, E, K) mean of the samples each knot stands for and (T, E, K) their counts.

    NaN components (not carried, or left out) are not counted; NaN where a knot has none.
    The samples of knot k are those of the Euler step its quantity belongs to:
    stage "vel": (t_k − h, t_k], the step that v_k = (q_k ⊖ q_{k−1})/h moves through (the
    mean rate over it; gyro); "acc": [t_k, t_k + h), the step over which qacc_k acts
    (accelerometer, force/torque). late_ns shifts the bins: a sample stamped up to late_ns
    after t_k still belongs to knot k (a stream sampled on the knots' own clock, whose stamps
    jitter around the knot times). h_ns: the knot step (default: the grid's own; a grid of one
    knot, a stream's filter stepping key by key, has none).
    """
    if h_ns is None:
        h_ns = int(t_ns[1] - t_ns[0]) if len(t_ns) > 1 else 1
    if late_ns:
        m = replace(m, t_ns=m.t_ns - late_ns)
    if stage == "vel":
        index = np.searchsorted(t_ns, m.t_ns, side="left")
        ok = (index < len(t_ns)) & (m.t_ns > t_ns[np.minimum(index, len(t_ns) - 1)] - h_ns)
    else:
        index = np.searchsorted(t_ns, m.t_ns, side="right") - 1
        ok = (index >= 0) & (m.t_ns < t_ns[np.maximum(index, 0)] + h_ns)
    carried = np.isfinite(m.values[ok])
    sums = np.zeros((len(t_ns), *m.values.shape[1:]))
    n = np.zeros_like(sums)
    np.add.at(sums, index[ok], np.where(carried, m.values[ok], 0.0))
    np.add.at(n, index[ok], carried)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, sums / n, np.nan), n


def held_at_knots(m: Measurement, t_ns: np.ndarray, component: int = 0) -> np.ndarray:
    """(T, E) the last sample at or before each knot (NaN before the first)."""
    index = np.searchsorted(m.t_ns, t_ns, side="right") - 1
    out = np.full((len(t_ns), len(m.elements)), np.nan)
    ok = index >= 0
    out[ok] = m.values[index[ok], :, component]
    return out

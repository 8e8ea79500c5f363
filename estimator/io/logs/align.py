"""Multi-rate streams onto one time grid.

Streams arrive at their own rates and jitter; the estimator works on a grid `t_grid_ns`.
`resample` gives a stream's values at the grid times: linear interpolation between the two
samples around each grid time (quaternions: normalized linear interpolation in a
sign-consistent hemisphere), or a zero-order hold for commands (a command holds until the
next one). A grid time without a sample within `max_gap_ns` on both sides (before, for a
hold) is NaN, so a dropout never becomes a made-up value. Each field is resampled from the
samples that carry it, so a joint missing from some JointState messages is interpolated
from the messages that have it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from estimator.io.logs.measurements import Measurement

# Stream kinds whose samples hold until the next one instead of being interpolated.
HOLD_KINDS = ("command",)


def time_grid(measurements: Iterable[Measurement], rate_hz: float) -> np.ndarray:
    """(G,) int64 grid at `rate_hz` over the span every non-empty stream covers."""
    spans = [(int(m.t_ns[0]), int(m.t_ns[-1])) for m in measurements if len(m)]
    if not spans or rate_hz <= 0:
        return np.zeros(0, dtype=np.int64)
    start = max(s for s, _ in spans)
    stop = min(e for _, e in spans)
    step = round(1e9 / rate_hz)
    if stop < start:
        return np.zeros(0, dtype=np.int64)
    return np.arange(start, stop + 1, step, dtype=np.int64)


def align(
    measurements: Mapping[str, Measurement], t_grid_ns: np.ndarray, *, max_gap_ns: int
) -> dict[str, np.ndarray]:
    """Per stream, (G, E, K) values at the grid times (see `resample`)."""
    return {name: resample(m, t_grid_ns, max_gap_ns=max_gap_ns) for name, m in measurements.items()}


def resample(m: Measurement, t_grid_ns: np.ndarray, *, max_gap_ns: int) -> np.ndarray:
    """(G, E, K) values of `m` at `t_grid_ns` (int64, increasing); NaN where unknown."""
    grid = np.asarray(t_grid_ns, dtype=np.int64)
    _, n_el, n_comp = m.values.shape
    out = np.full((len(grid), n_el, n_comp), np.nan)
    hold = m.kind in HOLD_KINDS
    quat = _quaternion_columns(m.components)
    scalar = [k for k in range(n_comp) if quat is None or not quat.start <= k < quat.stop]
    if scalar and np.isfinite(m.values[:, :, scalar]).all():  # every column at once
        columns = m.values[:, :, scalar].reshape(len(m.t_ns), -1)
        block = _resample_block(m.t_ns, columns, grid, max_gap_ns, hold, unit=False)
        out[:, :, scalar] = block.reshape(len(grid), n_el, len(scalar))
        scalar = []
    for e in range(n_el):
        if quat is not None:
            q = quat
            out[:, e, q] = _resample_block(
                m.t_ns, m.values[:, e, q], grid, max_gap_ns, hold, unit=True
            )
        for k in scalar:  # each column from its own finite samples
            out[:, e, k] = _resample_block(
                m.t_ns, m.values[:, e, k : k + 1], grid, max_gap_ns, hold, unit=False
            )[:, 0]
    return out


def _quaternion_columns(components: tuple[str, ...]) -> slice | None:
    if "qw" not in components:
        return None
    start = components.index("qw")
    return slice(start, start + 4)


def _resample_block(
    t: np.ndarray, v: np.ndarray, grid: np.ndarray, max_gap_ns: int, hold: bool, *, unit: bool
) -> np.ndarray:
    """(G, c) values of the block v: (N, c) at the grid, from rows where v is all finite."""
    keep = np.isfinite(v).all(axis=1)
    t, v = t[keep], v[keep]
    out = np.full((len(grid), v.shape[1]), np.nan)
    if not len(t):
        return out
    if unit:  # flip signs so consecutive quaternions lie in one hemisphere
        flips = np.cumsum(np.einsum("ij,ij->i", v[1:], v[:-1]) < 0) % 2
        v = v.copy()
        v[1:][flips == 1] *= -1
    i = np.searchsorted(t, grid, side="right") - 1  # last sample at or before each grid time
    before = i >= 0
    exact = before & (t[np.maximum(i, 0)] == grid)
    if hold:
        ok = before & (grid - t[np.maximum(i, 0)] <= max_gap_ns)
        out[ok] = v[i[ok]]
        return out
    j = i + 1
    inside = before & (j < len(t))
    ii, jj = np.maximum(i, 0), np.minimum(j, len(t) - 1)
    gap = t[jj] - t[ii]
    ok = inside & (gap <= max_gap_ns) & ~exact
    w = np.zeros(len(grid))
    w[ok] = (grid[ok] - t[ii[ok]]) / gap[ok]
    out[ok] = (1 - w[ok, None]) * v[ii[ok]] + w[ok, None] * v[jj[ok]]
    out[exact] = v[i[exact]]
    if unit:
        out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out

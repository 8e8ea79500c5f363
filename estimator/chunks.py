"""One long log in chunks across Ray workers, each reading its own slice of the file:
`physfuse estimate LOG --chunk S [--workers N]`.

The log's knot grid (`knot_grid` of its first and last seconds: the streams' first and last
samples) is cut into chunks of S seconds. Each chunk is a Ray task that reads its own slice of
the log file (its knots widened by `overlap` seconds on both sides, and the measurements
there: `read_log(..., log_time=...)`, which reads only the file's chunks in that time range),
estimates it and returns its own knots. The driver takes the parts in order as they come and
hands each on (`on_part`: the CLI writes it to the outputs at once), with at most
`workers + 1` chunks in flight, so that memory holds a few chunks, never the whole log (an
hour-long humanoid log in 60 s chunks on 2 workers: 1.94 GB at most, docs/fleet.md).

At a join the estimate comes from a chunk that has seen `overlap` seconds of log past it, where
the influence of the chunk's edge has died out. The physics' contact softness is fitted once,
on the log's start (`run.softness_fitted`), and every chunk takes it. Without mocap every
chunk starts at the start pose: each is then turned about world z and shifted to continue the
one before (`placed_after`). What reading skipped or lost is counted once: a chunk reads its
slice as three, the log time before its own share, its share, and after, and reports its share.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from estimator import heap
from estimator.batch import estimate
from estimator.config import Config, load_config
from estimator.errors import ConfigError, LogError, MissingTopicError, PhysfuseError
from estimator.estimate import Estimate
from estimator.fleet import as_task, ray_session
from estimator.io.logs import Log, LostData, Measurement, read_log
from estimator.io.logs.source import log_time_span
from estimator.io.state_topics import at_times, read_ground_truth, trajectory_errors
from estimator.knots import knot_grid
from estimator.leg_odometry import free_base
from estimator.rotations import heading, quat_mul
from estimator.run import (
    WINDOW_MARGIN_NS,
    Summary,
    initial_trajectory,
    samples_within,
    softness_fitted,
)
from estimator.settings import Settings

OVERLAP_S = 2.0  # of log on each side of a chunk that its estimate sees and the join drops
SMOOTHERS = ("physics", "kinematic")  # the methods on a knot grid a chunk can be given
HEAD_S = 2.0  # of log read for the grid's start and end (more for fit_softness_s)
CLOCK_SLACK_NS = 1_000_000_000  # a slice's extra log time either side (stamps vs receipt)
# glibc's malloc: blocks of 128 kB and more from mmap, so that a window's freed numpy
# temporaries go back to the system (by default the threshold rises to 32 MB after the first
# such free, and the heap keeps them: a humanoid chunk's worker peaked at 753 MB, with this 643)
WORKER_ENV = {"MALLOC_MMAP_THRESHOLD_": "131072"}
TRIM = 2  # knots at each end of the log left out of the accuracy (`trajectory_errors`)


@dataclass
class Part:
    """A chunk's own knots of the estimate, and what the chunk read for them.

    log: what it read: the measurements over its own knots, and the skipped-sample counts
    and damage of its share of the log (`_read_slice`); accuracy:
    per metric (RMSE, knots) against the log's ground truth, of the raw measurements and of
    the estimate (None without ground truth).
    """

    estimate: Estimate
    summary: Summary
    log: Log
    accuracy: dict[str, dict[str, tuple[float, int]]] | None
    kept: dict[str, int]  # per stream, the samples received in the chunk's share of the log


@dataclass
class ChunkedRun:
    """What a chunked estimate leaves once its parts are handed on."""

    summary: Summary
    warnings: list[str] = field(default_factory=list)  # the log's (damage), once each
    skipped: dict[str, dict[str, Any]] = field(default_factory=dict)  # per stream
    lost: list[LostData] = field(default_factory=list)
    accuracy: dict[str, dict[str, float]] | None = None  # RMSE against the ground truth
    # per metric (Σ knots × RMSE², knots) of the parts so far
    squared_errors: dict[str, dict[str, tuple[float, int]]] | None = None


def estimate_chunked(
    config_path: Path,
    log_path: Path,
    settings: Settings,
    chunk_s: float,
    on_part: Callable[[Part], None],
    overlap_s: float = OVERLAP_S,
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ChunkedRun:
    """The log's estimate from chunks of `chunk_s` solved as Ray tasks, each part handed to
    `on_part` in time order as soon as it and those before it are done."""
    import ray

    start = time.perf_counter()
    check(settings, chunk_s, overlap_s)
    config = load_config(config_path)
    model = config.load_model()
    h = settings.h or float(model.opt.timestep)
    head_s = max(HEAD_S, settings.fit_softness_s + 2 * WINDOW_MARGIN_NS / 1e9)
    span = log_time_span(log_path)
    # (require=False: a required stream may start later or end sooner; it is checked over
    # the whole log once every part is in)
    head_end = span[0] + round(head_s * 1e9)
    head = read_log(log_path, config, log_time=(span[0], head_end), require=False)
    tail = read_log(
        log_path, config, log_time=(span[1] - round(HEAD_S * 1e9), span[1] + 1), require=False
    )
    t_ns = knot_grid(_joined(head.measurements, tail.measurements), h)
    settings, fitted = softness_fitted(config, head.measurements, settings, t_ns)
    clock = _clock_offsets(head.measurements, tail.measurements)  # a drift over the log too
    unanchored_base = free_base(model)[0] >= 0 and not _has_mocap(head, tail)
    del head, tail
    heap.release()  # the softness fit's window
    knots, n, margin = len(t_ns), max(8, round(chunk_s / h)), round(overlap_s / h)
    cuts = [(a, min(a + n, knots)) for a in range(0, knots, n)]
    # each chunk's share of the log's receive times: consecutive, together all of it
    shares = [span[0]] + [int(t_ns[a]) - clock[1] for a, _ in cuts[1:]] + [span[1] + 1]
    run = ChunkedRun(Summary(0.0, 0, h, 0, [], [], {}, [], 0.0))
    parts_done: list[Summary] = []
    previous: Estimate | None = None
    task = as_task(estimate_chunk, WORKER_ENV)
    with ray_session(workers, address):
        in_flight = max(1, int(ray.cluster_resources().get("CPU", 1))) + 1
        refs: dict[int, Any] = {}
        for i, (a, b) in enumerate(cuts):
            while len(refs) < in_flight and len(refs) + i < len(cuts):
                j = i + len(refs)
                refs[j] = _submit(task, config_path, log_path, settings, t_ns, cuts[j], margin,
                                  (shares[j], shares[j + 1]), clock, knots)  # fmt: skip
            try:
                part = ray.get(refs.pop(i))
            except ray.exceptions.RayError as err:  # the chunk's error, or its workers died
                cause = getattr(err, "cause", None) or err
                line = (str(cause).strip().splitlines() or [type(cause).__name__])[-1]
                when = f"{(t_ns[a] - t_ns[0]) / 1e9:.3f}–{(t_ns[b - 1] - t_ns[0]) / 1e9:.3f} s"
                raise PhysfuseError(f"chunk {i + 1} ({when} of the log): {line}") from None
            est = part.estimate
            if unanchored_base and previous is not None:  # continue the chunk before
                est = placed_after(model, est, 0, previous, previous.T - 1)
            # its last knot is the next chunk's first (a copy: not the part's arrays)
            previous = copy.deepcopy(est.at(slice(est.T - 1, est.T)))
            part.estimate = est.at(slice(0, b - a))
            _tally(run, part)
            on_part(part)
            parts_done.append(part.summary)
            del part, est
            heap.release()  # the part's many small arrays (contacts per knot)
            if progress:
                progress(i + 1, len(cuts))
    missing = [
        f"required stream {name!r}: no usable sample of topic {stream.topic!r} in the log"
        for name, stream in config.streams.items()
        if stream.required and not run.skipped.get(name, {}).get("kept")
    ]
    if missing:
        raise MissingTopicError(f"{log_path}: " + "; ".join(missing))
    run.summary = _summary(run, parts_done, fitted, cuts, margin, time.perf_counter() - start)
    if run.squared_errors is not None:  # RMSE over all parts' knots
        run.accuracy = {
            name: {m: float(np.sqrt(sq / max(n, 1))) for m, (sq, n) in metrics.items()}
            for name, metrics in run.squared_errors.items()
        }
    return run


def _submit(
    task: Any,
    config_path: Path,
    log_path: Path,
    settings: Settings,
    t_ns: np.ndarray,
    cut: tuple[int, int],
    margin: int,
    share: tuple[int, int],
    clock: tuple[int, int],
    knots: int,
) -> Any:
    """The Ray task of chunk `cut` (its own knots a … b − 1) seen `margin` knots past each
    end; `share`: the receive times it accounts for; `clock`: the streams' (min, max) stamp −
    receipt time."""
    a, b = cut
    lo, hi = max(0, a - margin), min(knots, b + margin)
    # receive times to read: the chunk's knots, a window's margin of samples and the streams'
    # clock offsets (stamp − receipt) either side
    reach = (
        int(t_ns[lo]) - WINDOW_MARGIN_NS - clock[1] - CLOCK_SLACK_NS,
        int(t_ns[hi - 1]) + WINDOW_MARGIN_NS - clock[0] + CLOCK_SLACK_NS,
    )
    trim = (TRIM if a == 0 else 0, TRIM if b == knots else 0)
    # the part returned: its own knots and the next chunk's first (where that one is placed)
    own = slice(a - lo, min(b + 1, hi) - lo)
    return task.remote(
        str(config_path), str(log_path), settings, t_ns[lo:hi], own, b - a, reach, share, trim
    )


def check(settings: Settings, chunk_s: float, overlap_s: float) -> None:
    """Raises ConfigError naming what --chunk cannot take."""
    if chunk_s <= 0 or overlap_s < 0:
        raise ConfigError(
            f"--chunk {chunk_s:g}, --chunk-overlap {overlap_s:g}: expected s > 0 and s ≥ 0"
        )
    if settings.method not in SMOOTHERS:
        raise ConfigError(
            f"--chunk cuts the smoothers' knot grid ({', '.join(SMOOTHERS)}); --method "
            f"{settings.method} estimates a log in one pass: leave --chunk out"
        )


def check_log(log: Path) -> None:
    """Raises ConfigError where --chunk cannot read a log in slices."""
    if str(log) == "-" or log.is_fifo():
        raise ConfigError(
            f"--chunk reads the log in time slices, which a stream ({log}) cannot give: "
            "record it to a file, or leave --chunk out"
        )


def estimate_chunk(
    config_path: str,
    log_path: str,
    settings: Settings,
    knots: np.ndarray,
    own: slice,
    count: int,
    reach: tuple[int, int],
    share: tuple[int, int],
    trim: tuple[int, int],
) -> Part:
    """One chunk, in a Ray worker: its slice of the log read (`reach`, receive times; `share`
    the part of it this chunk accounts for), the estimate on `knots`, its `own` knots (the
    first `count`, and the next chunk's first) returned with their accuracy against the log's
    ground truth (if any)."""
    heap.release()  # what the worker's task before this one freed
    config = load_config(config_path)
    log = _read_slice(Path(log_path), config, reach, share)
    measurements = {
        k: samples_within(m, int(knots[0]), int(knots[-1])) for k, m in log.measurements.items()
    }
    est, summary = estimate(config, measurements, settings, knots=np.asarray(knots))
    summary.warnings += _joins_in_gaps(measurements, knots, own.start, own.start + count)
    mine = est.at(own)
    counted = mine.at(slice(0, count))
    accuracy = _accuracy(Path(log_path), config, measurements, knots, own.start, counted, trim)
    kept = {
        k: int(np.count_nonzero((m.log_time_ns >= share[0]) & (m.log_time_ns < share[1])))
        for k, m in log.measurements.items()
    }
    drawn = {  # the measurements over its own knots, for the recording
        k: samples_within(m, int(counted.t_ns[0]), int(counted.t_ns[-1]))
        for k, m in log.measurements.items()
    }
    return Part(mine, summary, replace(log, measurements=drawn), accuracy, kept)


def _joins_in_gaps(
    measurements: Mapping[str, Measurement], knots: np.ndarray, first: int, end: int
) -> list[str]:
    """A line for each mocap stream with no sample in all the log a chunk sees past one of its
    joins (its own knots first … end − 1 of `knots`): a gap longer than the overlap, across
    which the estimate at the join is extrapolated from one side, where one process sees both."""
    from estimator.leg_odometry import MOCAP_KINDS

    seen = []  # (the join's knot, the farthest knot seen past it)
    if first > 0:
        seen.append((int(knots[first]), int(knots[0])))
    if end < len(knots):
        seen.append((int(knots[end - 1]), int(knots[-1])))
    lines = []
    for name, m in measurements.items():
        if m.kind not in MOCAP_KINDS or not len(m):
            continue
        for join, far in seen:
            lo, hi = min(join, far), max(join, far)
            if not np.any((m.t_ns > lo) & (m.t_ns < hi)):
                side = "before" if far < join else "after"
                lines.append(
                    f"stream {name!r} has no sample in the {(hi - lo) / 1e9:.2f} s this chunk "
                    f"sees {side} its join: the estimate there is extrapolated across the gap; "
                    "a --chunk-overlap longer than the gap sees across it"
                )
    return lines


def _read_slice(path: Path, config: Config, reach: tuple[int, int], share: tuple[int, int]) -> Log:
    """The log's messages received within `reach`, read as three pieces: before `share`,
    `share`, after it; the skipped-sample counts, damage and warnings are the share's."""
    middle = read_log(path, config, log_time=share, require=False)
    others = [
        read_log(path, config, log_time=piece, require=False)
        for piece in ((reach[0], share[0]), (share[1], reach[1]))
        if piece[0] < piece[1]
    ]
    measurements = {
        name: _concatenated([m, *(log.measurements[name] for log in others)], m)
        for name, m in middle.measurements.items()
    }
    return replace(middle, measurements=measurements)


def _concatenated(pieces: list[Measurement], counted: Measurement) -> Measurement:
    """One stream's pieces in time order (a stamp met twice kept once), `counted`'s bad-sample
    counts."""
    t = np.concatenate([m.t_ns for m in pieces])
    order = np.argsort(t, kind="stable")
    keep = np.r_[True, np.diff(t[order]) > 0] if len(t) else np.zeros(0, bool)
    order = order[keep]
    return replace(
        counted,
        t_ns=t[order],
        log_time_ns=np.concatenate([m.log_time_ns for m in pieces])[order],
        values=np.concatenate([m.values for m in pieces])[order],
    )


def _accuracy(
    path: Path,
    config: Config,
    measurements: Mapping[str, Measurement],
    knots: np.ndarray,
    first: int,
    est: Estimate,
    trim: tuple[int, int],
) -> dict[str, dict[str, tuple[float, int]]] | None:
    """Per metric (RMSE, knots) of the raw measurements and of the estimate on a part's own
    knots (`trim` knots off the log's ends), against the ground truth received over them (and
    a second either side); None without ground truth. The raw measurements are interpolated
    over `knots` (all the chunk's: a gap across its edge between the samples on both sides,
    as over the whole log), of which the part's begin at `first`."""
    model = config.load_model()
    around = (int(est.t_ns[0]) - CLOCK_SLACK_NS, int(est.t_ns[-1]) + CLOCK_SLACK_NS)
    try:
        truth = at_times(*read_ground_truth(path, model, around), est.t_ns)
    except LogError:
        return None
    raw = initial_trajectory(model, measurements, knots)[first : first + est.T]
    a, b = trim[0], est.T - trim[1]
    return {
        name: {
            metric: (value, max(0, b - a))
            for metric, value in trajectory_errors(model, q[a:b], truth[a:b], trim=0).items()
        }
        for name, q in (("raw", raw), ("estimate", est.qpos))
    }


def _tally(run: ChunkedRun, part: Part) -> None:
    """Add a part's reading and accuracy to the run's."""
    log = part.log
    for warning in log.warnings:
        if warning not in run.warnings:
            run.warnings.append(warning)
    run.lost += [x for x in log.lost if x not in run.lost]
    for name, m in log.measurements.items():
        entry = run.skipped.setdefault(name, {"kept": 0, "skipped": 0, "by_reason": {}})
        entry["kept"] += part.kept.get(name, 0)
        entry["skipped"] += m.bad.total
        for reason, count in m.bad.as_dict().items():
            if count:
                entry["by_reason"][reason] = entry["by_reason"].get(reason, 0) + count
    if part.accuracy is not None:
        if run.squared_errors is None:
            run.squared_errors = {"raw": {}, "estimate": {}}
        for name, metrics in part.accuracy.items():
            for metric, (rmse, n) in metrics.items():
                sq, count = run.squared_errors[name].get(metric, (0.0, 0))
                run.squared_errors[name][metric] = (sq + n * rmse**2, count + n)


def _summary(
    run: ChunkedRun,
    summaries: list[Summary],
    fitted: dict[str, float],
    cuts: list[tuple[int, int]],
    margin: int,
    wall_s: float,
) -> Summary:
    knots = cuts[-1][1]
    costs: dict[str, float] = {}
    for s in summaries:  # each chunk's own span, overlaps included
        for k, v in s.cost_by_type.items():
            costs[k] = costs.get(k, 0.0) + v
    h = run.summary.h
    residuals = sorted(  # each chunk's times from its first knot: made the log's
        (
            r | {"time_s": r["time_s"] + max(0, a - margin) * h}
            for (a, _), s in zip(cuts, summaries, strict=True)
            for r in s.largest_residuals
        ),
        key=lambda r: -abs(r["whitened"]),
    )
    return Summary(
        duration_s=(knots - 1) * h,
        knots=knots,
        h=h,
        windows=sum(s.windows for s in summaries),
        iterations=[i for s in summaries for i in s.iterations],
        converged=[c for s in summaries for c in s.converged],
        cost_by_type=costs,
        largest_residuals=residuals[:5],
        wall_time_s=wall_s,
        warnings=[f"chunk {i + 1}: {w}" for i, s in enumerate(summaries) for w in s.warnings],
        linearizations=sum(s.linearizations for s in summaries),
        evaluations=sum(s.evaluations for s in summaries),
        knots_linearized=sum(s.knots_linearized for s in summaries),
        knots_evaluated=sum(s.knots_evaluated for s in summaries),
        model_error_mean={
            k: float(np.mean([s.model_error_mean[k] for s in summaries]))
            for k in summaries[0].model_error_mean
        },
        kept_starts=[k for s in summaries for k in s.kept_starts],
        starts_tried=[k for s in summaries for k in s.starts_tried],
        softness_fit=fitted,
        window_starts=sorted(
            {
                max(0, a - margin) + w
                for (a, _), s in zip(cuts, summaries, strict=True)
                for w in s.window_starts
            }
        ),
    )


def _joined(
    head: Mapping[str, Measurement], tail: Mapping[str, Measurement]
) -> dict[str, Measurement]:
    """Each stream's first samples (head) and last (tail): what `knot_grid` spans."""
    return {name: _concatenated([head[name], tail[name]], head[name]) for name in head}


def _clock_offsets(*logs: Mapping[str, Measurement]) -> tuple[int, int]:
    """(min, max) over the streams of stamp − receipt time, ns (0, 0 without samples)."""
    offsets = [m.t_ns - m.log_time_ns for log in logs for m in log.values() if len(m)]
    if not offsets:
        return 0, 0
    return int(min(o.min() for o in offsets)), int(max(o.max() for o in offsets))


def _has_mocap(*logs: Log) -> bool:
    from estimator.leg_odometry import MOCAP_KINDS

    return any(m.kind in MOCAP_KINDS and len(m) for log in logs for m in log.measurements.values())


def placed_after(
    model: mujoco.MjModel, est: Estimate, k: int, prev: Estimate, k_prev: int
) -> Estimate:
    """`est` turned about world z by ψ and shifted horizontally by t so that its free base
    at knot k has prev's x, y and heading at knot k_prev: q ← R_z(ψ) ⊗ q, p ← R_z(ψ) p + t on
    every free joint, the free joints' world-frame rows (linear velocity, acceleration, force)
    and the contacts turned with them; the physics is unchanged (gravity along z, a level
    floor). σ of x, y and yaw grows by prev's there. (The whitened residuals stay as solved.)"""
    _, adr = free_base(model)
    psi = float(
        heading(prev.qpos[k_prev, adr + 3 : adr + 7]) - heading(est.qpos[k, adr + 3 : adr + 7])
    )
    c, s = np.cos(psi), np.sin(psi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = prev.qpos[k_prev, adr : adr + 3] - R @ est.qpos[k, adr : adr + 3]
    t[2] = 0.0
    q_z = np.array([np.cos(psi / 2), 0.0, 0.0, np.sin(psi / 2)])
    qpos, std = est.qpos.copy(), est.qpos_std.copy()
    qvel, qacc = est.qvel.copy(), est.qacc.copy()
    qfrc_inverse, qfrc_known = est.qfrc_inverse.copy(), est.qfrc_known.copy()
    base_dof = -1
    for j in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
        a, dof = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        base_dof = dof if a == adr else base_dof
        qpos[:, a : a + 3] = qpos[:, a : a + 3] @ R.T + t
        qpos[:, a + 3 : a + 7] = quat_mul(q_z, qpos[:, a + 3 : a + 7])
        # a free joint's translational dofs are in the world frame
        for x in (qvel, qacc, qfrc_inverse, qfrc_known):
            x[:, dof : dof + 3] = x[:, dof : dof + 3] @ R.T
        variance = std[:, dof : dof + 2] ** 2  # x, y: R diag(σ²) Rᵀ's diagonal
        std[:, dof : dof + 2] = np.sqrt(variance @ (R[:2, :2] ** 2).T)
    for d in (base_dof, base_dof + 1, base_dof + 5):  # x, y and (about the body z) yaw
        std[:, d] = np.hypot(std[:, d], prev.qpos_std[k_prev, d])
    constraints = tuple(
        replace(
            each,
            contacts=replace(
                each.contacts, pos=each.contacts.pos @ R.T + t, frame=each.contacts.frame @ R.T
            ),
        )
        for each in est.constraints
    )
    return replace(
        est,
        qpos=qpos,
        qvel=qvel,
        qacc=qacc,
        qfrc_inverse=qfrc_inverse,
        qfrc_known=qfrc_known,
        qpos_std=std,
        constraints=constraints,
    )

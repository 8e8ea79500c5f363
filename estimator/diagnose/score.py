"""Detected events against the truth of a simulated log (`disturbances` condition).

A detection matches a true event of its kind (`KIND_OF`: a push or a collision with an
obstacle not in the model is an unmodeled contact; a foot sliding on a low-friction patch a
slip) when their intervals, each widened by `TOLERANCE_S`, overlap (a sensor fault's true
interval: its start). Detections another explains (`Event.explained_by`) are left out: they
are reported as consequences. A true push (collision) counts as found when a detection of an
unmodeled contact matches it; isolated when that detection names its body (a sensor fault:
its stream and component); its force error is |‖F̂‖ − ‖F‖| / ‖F‖ (a slip's: of the
distance slid). A detection that matches no true event is a false alarm.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from estimator.diagnose.detect import Event

TOLERANCE_S = 0.05
# the simulated event → the kind of detection that finds it
KIND_OF = {
    "push": "unmodeled contact",
    "collision": "unmodeled contact",
    "imu bias step": "sensor fault",
    "encoder offset": "sensor fault",
    "slip": "slip",
}


def true_events(log: str | Path) -> list[dict[str, Any]]:
    """The `events` of a simulated log's `physfuse.condition` record ([] if none)."""
    with open(log, "rb") as f:
        for record in make_reader(f).iter_metadata():
            if record.name == "physfuse.condition" and "events" in record.metadata:
                return list(json.loads(record.metadata["events"]))
    return []


@dataclass
class Matched:
    """One true event and what the detector made of it."""

    truth: dict[str, Any]
    detection: Event | None = None

    @property
    def found(self) -> bool:
        return self.detection is not None

    @property
    def isolated(self) -> bool:
        d = self.detection
        return (
            d is not None
            and d.target == self.truth.get("body", self.truth.get("stream"))
            and ("component" not in self.truth or d.component == self.truth["component"])
        )

    @property
    def force_error(self) -> float:
        size = self.truth.get("force_n", self.truth.get("distance_m"))
        if self.detection is None or size is None:
            return float("nan")
        true = float(np.linalg.norm(size))
        return abs(self.detection.magnitude - true) / true

    @property
    def delay_s(self) -> float:
        if self.detection is None:
            return float("nan")
        return self.detection_delay_ns / 1e9

    @property
    def detection_delay_ns(self) -> int:
        assert self.detection is not None
        return self.detection.detected_ns - self.truth["start_ns"]


@dataclass
class Score:
    matched: list[Matched]
    false_alarms: list[Event] = field(default_factory=list)
    minutes: float = 0.0


def score(
    events: Sequence[Event], truth: Sequence[dict[str, Any]], t0_ns: int, duration_s: float
) -> Score:
    """Match `events` (log clock) to `truth` (seconds from t0_ns, the log's simulated start)."""
    tol = int(TOLERANCE_S * 1e9)
    events = [e for e in events if not e.explained_by]
    matched = []
    used: set[int] = set()
    for t in truth:
        start = t0_ns + round(t["start_s"] * 1e9)
        kind = KIND_OF[t["kind"]]
        end = start if kind == "sensor fault" else t0_ns + round(t["end_s"] * 1e9)
        entry = Matched(t | {"start_ns": start, "end_ns": end})
        for i, e in enumerate(events):
            overlaps = e.start_ns - tol <= end + tol and e.end_ns + tol >= start - tol
            if i not in used and e.kind == kind and overlaps:
                entry.detection = e
                used.add(i)
                break
        matched.append(entry)
    alarms = [e for i, e in enumerate(events) if i not in used]
    return Score(matched, alarms, duration_s / 60.0)

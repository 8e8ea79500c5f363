"""A diagnosis as the user reads it: events.json, the terminal table, and MCAP topics.

/diagnostics                           diagnostic_msgs/msg/DiagnosticArray, one message per
                                       event at its start: status name "physfuse/<kind>",
                                       hardware_id the body, contact or stream, level WARN (ERROR
                                       for a sensor fault), key/values: start_s, end_s,
                                       force_n (x y z) ± σ, component, score, explained_by
                                       (a slip: slid_m ± σ)
/diagnostics/events                    physfuse_msgs/msg/DiagnosticEvent, the same events
                                       typed (msgs/physfuse_msgs/msg/DiagnosticEvent.msg):
                                       kind, interval, target, size and its covariance
/diagnostics/unmodeled_force/<body>    geometry_msgs/msg/WrenchStamped per knot: the force
                                       on the body's centre of mass (world frame) that
                                       would explain the physics residual alone (the
                                       detector's windowed fit), frame_id "world"
"""

from __future__ import annotations

from typing import Any

import numpy as np

from estimator.diagnose.contact_model import MODEL_ERROR
from estimator.diagnose.detect import Event
from estimator.diagnose.diagnosis import Diagnosis
from estimator.diagnose.slip import SLIP
from estimator.io.logs import ros2_types
from estimator.io.mcap_writer import MessageSink, header, time_msg, vector3

DIAGNOSTICS = "/diagnostics"
EVENTS = "/diagnostics/events"
KINDS = {"unmodeled contact": 0, MODEL_ERROR: 1, "sensor fault": 2, SLIP: 3}  # .kind
UNMODELED_FORCE = "/diagnostics/unmodeled_force/"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
WARN, ERROR = 1, 2  # diagnostic_msgs/DiagnosticStatus levels


def event_dict(e: Event, t0_ns: int) -> dict[str, Any]:
    out: dict[str, Any] = {
        "kind": e.kind,
        "start_s": (e.start_ns - t0_ns) / 1e9,
        "end_s": (e.end_ns - t0_ns) / 1e9,
        "detected_s": (e.detected_ns - t0_ns) / 1e9,
        "target": e.target,
        "score": e.score,
    }
    if e.kind == "unmodeled contact":
        out["force_n"] = e.force.tolist()
        out["force_std_n"] = np.sqrt(np.diag(e.force_cov)).tolist()
        out["magnitude_n"] = e.magnitude
        out["magnitude_std_n"] = e.magnitude_std
        out["candidates"] = dict(sorted(e.candidates.items(), key=lambda kv: -kv[1])[:3])
        if e.point is not None:
            out["contact_point_m"] = e.point.tolist()
    elif e.kind == MODEL_ERROR and len(e.force) == 3:  # the contact's force off
        out["component"] = e.component
        out["contact_force_error_n"] = e.force.tolist()
        out["contact_force_error_std_n"] = np.sqrt(np.diag(e.force_cov)).tolist()
        if e.point is not None:
            out["contact_point_m"] = e.point.tolist()
    elif e.kind == MODEL_ERROR and e.component == "mass":
        out["component"] = e.component
        out["mass_error_kg"] = float(e.force[0])
        out["mass_error_std_kg"] = float(np.sqrt(e.force_cov[0, 0]))
        out["candidates"] = dict(sorted(e.candidates.items(), key=lambda kv: -kv[1])[:3])
    elif e.kind == MODEL_ERROR:
        out["component"] = e.component
        out["normal_force_error_n"] = float(e.force[0])
        out["normal_force_error_std_n"] = float(np.sqrt(e.force_cov[0, 0]))
    elif e.kind == SLIP:
        out["component"] = e.component
        out["slid_m"] = float(e.force[0])
        out["slid_std_m"] = float(np.sqrt(e.force_cov[0, 0]))
    else:
        out["component"] = e.component
        out["step_sigma"] = float(e.force[0])
    if e.explained_by:
        out["explained_by"] = e.explained_by
    if e.ongoing:
        out["ongoing"] = True
    return out


def events_json(diagnosis: Diagnosis, t0_ns: int) -> dict[str, Any]:
    det = diagnosis.detection
    return {
        "t0_ns": int(t0_ns),
        "settings": {
            "window_s": det.settings.window_s,
            "false_alarms_per_min": det.settings.false_alarms_per_min,
        },
        "threshold_chi2": det.threshold,
        "bodies": list(diagnosis.forces.bodies),
        "body_force_std_n": {
            b: np.sqrt(np.diag(c)).tolist()
            for b, c in zip(diagnosis.forces.bodies, det.cov, strict=True)
        },
        "body_force_offset_n": {
            b: m.tolist() for b, m in zip(diagnosis.forces.bodies, det.mean, strict=True)
        },
        "events": [event_dict(e, t0_ns) for e in diagnosis.events],
    }


def table(diagnosis: Diagnosis, t0_ns: int) -> str:
    """The terminal table: one line per event, consequences indented under their cause."""
    if not diagnosis.events:
        return "no events"
    lines = [f"{'start s':>8} {'end s':>7}  {'kind':<18} {'where':<34} {'size':<24} score"]
    for e in diagnosis.events:
        if e.kind == "unmodeled contact":
            size = f"{e.magnitude:.1f} ± {e.magnitude_std:.1f} N"
            where = e.target
        elif e.kind == MODEL_ERROR and len(e.force) == 3:
            size = f"force {e.magnitude:.1f} ± {e.magnitude_std:.1f} N"
            where = e.target
        elif e.kind == MODEL_ERROR and e.component == "mass":
            size = f"mass {e.force[0]:+.2f} ± {np.sqrt(e.force_cov[0, 0]):.2f} kg"
            where = e.target
        elif e.kind == MODEL_ERROR:
            size = f"normal {e.force[0]:+.1f} ± {np.sqrt(e.force_cov[0, 0]):.1f} N"
            where = e.target
        elif e.kind == SLIP:
            size = f"slid {100 * e.force[0]:.1f} ± {100 * np.sqrt(e.force_cov[0, 0]):.1f} cm"
            where = e.component
        else:
            size = f"step {e.force[0]:+.1f}σ"
            where = f"{e.target} {e.component}"
        kind = e.kind if not e.explained_by else f"  ({e.kind})"
        line = (
            f"{(e.start_ns - t0_ns) / 1e9:8.3f} {(e.end_ns - t0_ns) / 1e9:7.3f}  "
            f"{kind:<18} {where:<34} {size:<24} {e.score:.1f}"
        )
        if e.explained_by:
            line += f"  ← {e.explained_by}"
        lines.append(line)
    return "\n".join(lines)


def write_mcap(sink: MessageSink, diagnosis: Diagnosis) -> None:
    """The /diagnostics topics (module docstring) into an MCAP sink."""
    forces, det = diagnosis.forces, diagnosis.detection
    for e in diagnosis.events:
        write_event(sink, e, int(forces.t_ns[0]), e.start_ns)
    for b, body in enumerate(forces.bodies):
        topic = UNMODELED_FORCE + body
        for k in np.flatnonzero(np.isfinite(det.force[:, b]).all(axis=1)):
            t = int(forces.t_ns[k])
            fields = {
                "header": header(t, "world"),
                "wrench": {"force": vector3(det.force[k, b]), "torque": vector3(np.zeros(3))},
            }
            sink.write(topic, ros2_types.WRENCH_STAMPED, fields, t)


def write_event(sink: MessageSink, e: Event, t0_ns: int, log_time_ns: int) -> None:
    """One event on /diagnostics and /diagnostics/events (stamped at its start, written at
    `log_time_ns`: a live stream's at the knot that reported it)."""
    values = event_dict(e, t0_ns)
    status = {
        "level": ERROR if e.kind == "sensor fault" else WARN,
        "name": f"physfuse/{e.kind.replace(' ', '_')}",
        "message": message(e),
        "hardware_id": e.target,
        "values": [{"key": k, "value": _text(v)} for k, v in values.items()],
    }
    array = {"header": header(e.start_ns), "status": [status]}
    sink.write(DIAGNOSTICS, DIAGNOSTIC_ARRAY, array, log_time_ns)
    sink.write(EVENTS, ros2_types.DIAGNOSTIC_EVENT, event_message(e), log_time_ns)


def event_message(e: Event) -> dict[str, Any]:
    """physfuse_msgs/msg/DiagnosticEvent fields (msgs/physfuse_msgs/msg/DiagnosticEvent.msg)."""
    best = sorted(e.candidates.items(), key=lambda kv: -kv[1])[:3]
    return {
        "header": header(e.start_ns, "world"),
        "kind": KINDS[e.kind],
        "end": time_msg(e.end_ns),
        "detected": time_msg(e.detected_ns),
        "target": e.target,
        "component": e.component,
        "size": [float(v) for v in e.force],
        "size_covariance": [float(v) for v in np.ravel(e.force_cov)],
        "score": float(e.score),
        "explained_by": e.explained_by,
        "candidates": [name for name, _ in best],
        "candidate_likelihood_ratios": [float(r) for _, r in best],
        "ongoing": e.ongoing,
        "point": [] if e.point is None else [float(v) for v in e.point],
    }


def message(e: Event) -> str:
    """One line: what the event is, where and how big."""
    if e.kind == "unmodeled contact":
        text = f"{e.magnitude:.0f} N on {e.target}"
    elif e.kind == MODEL_ERROR and len(e.force) == 3:
        text = f"{e.target}: the model's contact force is off by {e.magnitude:.0f} N"
    elif e.kind == MODEL_ERROR and e.component == "mass":
        text = f"{e.target}: the model's mass is off by {e.force[0]:+.2f} kg"
    elif e.kind == MODEL_ERROR:
        text = f"{e.target}: the model's normal force is off by {e.force[0]:+.1f} N"
    elif e.kind == SLIP:
        text = f"{e.component} slid {100 * e.force[0]:.1f} cm where the model holds it"
    else:
        text = f"{e.target} {e.component} stepped {e.force[0]:+.1f} sigma"
    text += f" (explained by {e.explained_by})" if e.explained_by else ""
    return text + (" (ongoing)" if e.ongoing else "")


def _text(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return " ".join(_text(x) for x in v)
    if isinstance(v, dict):
        return ", ".join(f"{k} {_text(x)}" for k, x in v.items())
    return str(v)

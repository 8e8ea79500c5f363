"""`physfuse inspect LOG [--config CONFIG] [--json OUT.json]`: what is in a robot log.

Run it before estimating. Per topic: message type, count, rate (median interval), time span,
largest gap, bad samples by reason, and the sender's clock against the recorder's (median
header.stamp − log time). With a config: what each stream extracted, and a checklist of
every mapped topic, body, site, joint and actuator — found in the log and the model, or
MISSING. A truncated log gets a warning line and is still reported. Exit status 0 when
everything required is present, 2 (with one error line) otherwise. A config `physfuse
estimate` cannot run (a model option the engine does not support, an actuator commands
cannot drive, a bad [estimator] setting) is that error line before the log is read, as it
is for estimate (`estimator.model_checks.check_for_estimate`).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from estimator.config import ARRAY_KINDS, Config, NameCheck, check_model_names, load_config
from estimator.errors import ConfigError, MissingTopicError
from estimator.io.logs import ros2_types
from estimator.io.logs.measurements import BadSampleCounts, Measurement, TopicStats
from estimator.io.logs.reader import Log, read_log
from estimator.model_checks import (
    ActuatorRow,
    CommandCheck,
    ContactSetting,
    RestingDepth,
    actuator_rows,
    check_for_estimate,
    command_warnings,
    commands_against_efforts,
    contact_settings,
    resting_penetration,
)
from estimator.settings import Settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "log", type=Path, help="MCAP file, rosbag2 folder, FIFO, or - for standard input"
    )
    parser.add_argument(
        "--config", type=Path, help="config TOML: also check every mapped topic and name"
    )
    parser.add_argument("--json", type=Path, metavar="OUT.json", help="write the report as JSON")


@dataclass(frozen=True)
class CheckItem:
    """One checklist line: a mapped topic or name, where it was looked for, and the outcome."""

    what: str  # e.g. "topic /imu", "model body 'torso'", "joint 'knee_joint' in /joint_states"
    key: str  # config key path
    found: bool
    required: bool
    detail: str = ""


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config, check_names=False) if args.config else None
    if config is not None:  # what estimate would fail on, before the log is read
        check_for_estimate(config)
    log = read_log(args.log, config, decode_all=True, require=False)
    checks = _checklist(log, config) if config is not None else []
    model = _model_facts(log, config, checks) if config is not None else None

    lines = _report(log, config, checks)
    if model is not None:
        lines += _model_report(model)
    print("\n".join(lines))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = _as_json(log, config, checks)
        if model is not None:
            report["model"] = _model_json(model)
        args.json.write_text(json.dumps(report, indent=2))

    failed = [c for c in checks if c.required and not c.found]
    if config is not None and failed:
        model_names = [c for c in failed if c.what.startswith("model ")]
        summary = "; ".join(f"{c.what} ({c.key}) {c.detail or 'missing'}" for c in failed)
        error = ConfigError if len(model_names) == len(failed) else MissingTopicError
        raise error(f"{len(failed)} required item(s) missing: {summary}")
    return 0


# -- the checklist -----------------------------------------------------------------------------
def _checklist(log: Log, config: Config) -> list[CheckItem]:
    model_checks = {c.key: c for c in check_model_names(config, config.load_model())}
    items: list[CheckItem] = []
    for name, stream in config.streams.items():
        topic = log.topics.get(stream.topic)
        present = topic is not None and topic.count > 0
        key = f"streams.{name}.topic"
        items.append(
            CheckItem(
                f"topic {stream.topic}",
                key,
                present,
                stream.required,
                "" if present else "not in the log",
            )
        )
        if present and topic is not None:
            accepted = ros2_types.ACCEPTED_TYPES[stream.kind]
            if stream.kind == "command":
                accepted = (
                    (ros2_types.FLOAT64_MULTI_ARRAY,)
                    if stream.field is None
                    else (ros2_types.JOINT_TRAJECTORY,)
                )
            ok_type = topic.msg_type in accepted
            items.append(
                CheckItem(
                    f"type of {stream.topic}",
                    f"streams.{name}.type",
                    ok_type,
                    stream.required,
                    ""
                    if ok_type
                    else f"is {topic.msg_type or 'unknown'}, expected {' or '.join(accepted)}",
                )
            )
            usable = len(log.measurements[name]) > 0
            if ok_type:
                bad = log.measurements[name].bad
                items.append(
                    CheckItem(
                        f"usable samples on {stream.topic}",
                        f"streams.{name}",
                        usable,
                        stream.required,
                        "" if usable else f"none of {topic.count} ({_bad_text(bad)})",
                    )
                )
        seen = log.names_seen.get(name, frozenset())
        for i, (element_key, element) in enumerate(
            zip(stream.element_keys, stream.elements, strict=True)
        ):
            check: NameCheck = model_checks[element_key]
            what = f"model {stream.element_type} {element!r}"
            if stream.mount is not None:
                what = f"model {check.element_type} {check.name!r} (mounted: {element!r})"
            items.append(
                CheckItem(
                    what,
                    element_key,
                    check.found,
                    True,
                    ""
                    if check.found
                    else f"not in the model; valid: {', '.join(n for n in check.valid if n)}",
                )
            )
            if stream.sources is not None and present:
                source = stream.sources[i]
                what = _source_label(stream.kind, stream.field, source)
                source_key = (
                    f"streams.{name}.child_frame_id" if stream.kind == "tf" else element_key
                )
                items.append(
                    CheckItem(
                        f"{what} in {stream.topic}",
                        source_key,
                        source in seen,
                        stream.required,
                        "" if source in seen else "never in the log",
                    )
                )
    return items


def _source_label(kind: str, field: str | None, source: str) -> str:
    if kind in ARRAY_KINDS and field is None:
        return f"array entry {source}"
    return {
        "joint_state": "joint",
        "command": "trajectory joint",
        "rigid_bodies": "rigid body",
        "markers": "marker",
        "tf": "TF frame",
    }[kind] + f" {source!r}"


# -- the model: actuators, contact settings, commands against efforts -------------------------
@dataclass(frozen=True)
class ModelFacts:
    config: Config
    model: mujoco.MjModel
    overrides: dict[str, float]  # the config's softness settings replacing the model's own
    actuators: list[ActuatorRow]
    commanded: dict[str, str]  # actuator → the command stream that drives it
    contacts: list[ContactSetting]
    resting: list[RestingDepth]
    keyframe: str | None
    commands: list[CommandCheck]


def _model_facts(log: Log, config: Config, checks: list[CheckItem]) -> ModelFacts | None:
    """The model's facts, with the config's softness overrides applied (None when a name the
    config uses is missing: the checklist says which)."""
    if any(not c.found and c.what.startswith("model ") for c in checks):
        return None
    settings = Settings.from_config(config)
    model = config.load_model()
    # the softness as the estimate's, whose step is h (κ ≥ 2h: checked by check_for_estimate)
    timestep = model.opt.timestep
    model.opt.timestep = settings.h or timestep
    settings.apply_softness(model)
    model.opt.timestep = timestep
    overrides = {
        name: value
        for name in ("softness_eps", "softness_kappa")
        if (value := getattr(settings, name)) is not None
    }
    commanded = {
        actuator: name
        for name, stream in config.streams.items()
        if stream.kind == "command"
        for actuator in stream.elements
    }
    keyframe = 0 if model.nkey else None
    return ModelFacts(
        config,
        model,
        overrides,
        actuator_rows(model),
        commanded,
        contact_settings(model),
        resting_penetration(model, keyframe),
        (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_KEY, 0) or "#0") if model.nkey else None,
        commands_against_efforts(config, model, log.measurements),
    )


def _model_report(facts: ModelFacts) -> list[str]:
    m = facts.model
    cone = "elliptic" if m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC else "pyramidal"
    lines = [
        "",
        f"model: {facts.config.model_path}: nq {m.nq}, nv {m.nv}, nu {m.nu}, timestep "
        f"{m.opt.timestep:g} s, cone {cone}, impratio {m.opt.impratio:g}",
    ]
    if facts.actuators:
        lines += [
            "actuators (commands become forces through these, at each knot's state):",
            f"  {'name':<26} {'kind':<9} {'drives':<26} {'gear':>6} {'kp':>8} {'kv':>7} "
            f"{'ctrlrange':>17} {'forcerange':>17}  commands",
        ]
        for a in facts.actuators:
            stream = facts.commanded.get(a.name, "-")
            if a.unsupported and a.name in facts.commanded:
                stream += f" (cannot be used: {a.unsupported})"
            lines.append(
                f"  {a.name:<26} {a.kind:<9} {a.target:<26} {a.gear:>6g} {a.kp:>8g} {a.kv:>7g} "
                f"{_range_text(a.ctrlrange):>17} {_range_text(a.forcerange):>17}  {stream}"
            )
    source = (
        "the config's "
        + ", ".join(f"{k} = {v:g}" for k, v in facts.overrides.items())
        + " over the model's own"
        if facts.overrides
        else "the model's own"
    )
    lines += [
        f"contact settings in use ({source}):",
        f"  {'solref':>16} {'solimp d0, dwidth, width':>26} {'ε at d0, dwidth':>17} "
        f"{'friction':>22} {'condim':>6} {'margin':>7}  geoms",
    ]
    for c in facts.contacts:
        names = ", ".join(c.elements[:4]) + (
            f" +{len(c.elements) - 4}" if len(c.elements) > 4 else ""
        )
        lines.append(
            f"  {_numbers(c.solref[:2]):>16} {_numbers(c.solimp[:3]):>26} {_numbers(c.eps):>17} "
            f"{_numbers(c.friction):>22} {c.condim:>6} {c.margin:>7g}  {names}"
        )
    posture = f"keyframe {facts.keyframe!r}" if facts.keyframe else "qpos0"
    for r in facts.resting:
        lines.append(
            f"resting penetration under its weight ({posture} posture, at rest): {r.body} sinks "
            f"{1e3 * r.penetration_m:.2f} mm into its {r.contacts} contacts "
            f"(at z = {r.height_m:.4f} m)"
        )
    if facts.commands:
        lines.append("commands against the logged joint efforts (through the actuators):")
        for check in facts.commands:
            lines.append(
                f"  {check.actuator:<26} on {check.joint:<26} effort ≈ {check.gain:+.3g} × "
                f"commanded force, RMS apart {check.residual_rms:.3g} (effort RMS "
                f"{check.effort_rms:.3g}): {check.problem or 'consistent'}"
            )
    lines += [f"WARNING: {w}" for w in command_warnings(facts.commands)]
    return lines


def _gain(value: float) -> str:
    return f"{value:g}" if value else "-"


def _range_text(r: tuple[float, float] | None) -> str:
    return "-" if r is None else f"[{r[0]:g}, {r[1]:g}]"


def _numbers(values: tuple[float, ...]) -> str:
    return " ".join(f"{v:.4g}" for v in values)


def _model_json(facts: ModelFacts) -> dict[str, Any]:
    return {
        "path": str(facts.config.model_path),
        "impratio": float(facts.model.opt.impratio),
        "softness_overrides": facts.overrides,
        "actuators": [
            {**asdict(a), "commanded_by": facts.commanded.get(a.name)} for a in facts.actuators
        ],
        "contact_settings": [{**asdict(c), "eps": c.eps} for c in facts.contacts],
        "resting_penetration": [asdict(r) for r in facts.resting],
        "commands_against_efforts": [{**asdict(c), "problem": c.problem} for c in facts.commands],
    }


# -- the text report ---------------------------------------------------------------------------
def _report(log: Log, config: Config | None, checks: list[CheckItem]) -> list[str]:
    topics = list(log.topics.values())
    total = sum(t.count for t in topics)
    starts = [t.span_ns[0] for t in topics if t.span_ns]
    ends = [t.span_ns[1] for t in topics if t.span_ns]
    t0 = min(starts) if starts else 0
    span = (max(ends) - t0) / 1e9 if ends else 0.0
    lines = [
        f"log: {log.source}",
        f"  {len(topics)} topics, {total} messages, {span:.3f} s of log time",
    ]
    lines += [f"WARNING: {w}" for w in log.warnings]
    lines.append("")
    w_topic = max([len("topic"), *(len(s.topic) for s in topics)])
    w_type = max([len("type"), *(len(s.msg_type or "(no schema)") for s in topics)])
    header = (
        f"{'topic':<{w_topic}}  {'type':<{w_type}} {'msgs':>7} {'rate Hz':>8} {'start s':>8} "
        f"{'span s':>8} {'max gap ms':>10} {'at s':>7} {'stamp-log ms':>12}  bad samples"
    )
    lines += [header, "-" * len(header)]
    for s in topics:
        gap = s.largest_gap
        offset = s.clock_offset_ns
        first, last = s.span_ns or (t0, t0)
        lines.append(
            f"{s.topic:<{w_topic}}  {(s.msg_type or '(no schema)'):<{w_type}} {s.count:>7} "
            f"{s.rate_hz:>8.1f} {(first - t0) / 1e9:>8.3f} {(last - first) / 1e9:>8.3f} "
            f"{(gap[0] / 1e6 if gap else 0.0):>10.2f} "
            f"{((gap[1] - t0) / 1e9 if gap else 0.0):>7.3f} "
            f"{(f'{offset / 1e6:.2f}' if offset is not None else '-'):>12}  {_bad_text(s.bad)}"
        )
    offsets = {s.topic: s.clock_offset_ns for s in topics if s.clock_offset_ns is not None}
    if len(offsets) >= 2:
        lo = min(offsets, key=lambda k: offsets[k] or 0.0)
        hi = max(offsets, key=lambda k: offsets[k] or 0.0)
        lo_ms, hi_ms = (offsets[lo] or 0.0) / 1e6, (offsets[hi] or 0.0) / 1e6
        lines += [
            "",
            "clock offsets between streams (median header.stamp - log time): from "
            f"{lo_ms:.2f} ms ({lo}) to {hi_ms:.2f} ms ({hi}), {hi_ms - lo_ms:.2f} ms apart",
        ]
    if config is None:
        return lines
    lines += [
        "",
        f"config: {config.path} (model {config.model})",
        f"{'stream':<20} {'type':<13} {'topic':<28} {'samples':>8} {'rate Hz':>8} "
        f"{'max gap ms':>10} {'at s':>7}  skipped",
    ]
    for name, stream in config.streams.items():
        m = log.measurements[name]
        rate_hz, gap_ms, gap_at, dropout = _stream_timing(m, t0)
        lines.append(
            f"{name:<20} {stream.kind:<13} {stream.topic:<28} {len(m):>8} {rate_hz:>8.1f} "
            f"{gap_ms:>10.2f} {gap_at:>7.3f}  {_bad_text(m.bad)}"
            + (f"  (largest gap: {dropout}, while the stream went on)" if dropout else "")
        )
    lines += ["", "checklist:"]
    for c in checks:
        status = "found" if c.found else ("MISSING" if c.required else "missing (optional)")
        detail = f": {c.detail}" if c.detail else ""
        lines.append(f"  {status:<18} {c.what}  [{c.key}]{detail}")
    return lines


def _stream_timing(m: Measurement, t0: int) -> tuple[float, float, float, str | None]:
    """A stream's rate (Hz, median interval), its largest gap (ms) and when it began (s),
    over each of its elements' own samples (a TF child frame, a marker, a rigid body that
    drops out while the others go on); that element named where its gap is longer than the
    stream's own."""
    if len(m) < 2:
        return 0.0, 0.0, 0.0, None
    rate = 1e9 / float(np.median(np.diff(m.t_ns)))
    gap, at, element = 0, 0, ""
    for e, name in enumerate(m.elements):
        t = m.t_ns[np.isfinite(m.values[:, e]).any(axis=1)]
        if len(t) < 2:
            continue
        i = int(np.argmax(np.diff(t)))
        if t[i + 1] - t[i] > gap:
            gap, at, element = int(t[i + 1] - t[i]), int(t[i]), name
    stream_gap = int(np.max(np.diff(m.t_ns)))
    dropout = element if len(m.elements) > 1 and gap > 1.5 * stream_gap else None
    return rate, gap / 1e6, (at - t0) / 1e9, dropout


def _bad_text(bad: BadSampleCounts) -> str:
    parts = [f"{k}={v}" for k, v in bad.as_dict().items() if v]
    return " ".join(parts) if parts else "-"


# -- JSON ---------------------------------------------------------------------------------------
def _topic_json(s: TopicStats) -> dict[str, Any]:
    gap = s.largest_gap
    return {
        "topic": s.topic,
        "type": s.msg_type,
        "count": s.count,
        "rate_hz": s.rate_hz,
        "first_log_time_ns": s.span_ns[0] if s.span_ns else None,
        "last_log_time_ns": s.span_ns[1] if s.span_ns else None,
        "largest_gap_ns": gap[0] if gap else None,
        "largest_gap_at_ns": gap[1] if gap else None,
        "interval_std_ns": s.jitter_ns,
        "clock_offset_ns": s.clock_offset_ns,
        "bad": s.bad.as_dict(),
    }


def _as_json(log: Log, config: Config | None, checks: list[CheckItem]) -> dict[str, Any]:
    out: dict[str, Any] = {
        "log": log.source,
        "truncated": log.truncated,
        "warnings": list(log.warnings),
        "lost": [asdict(x) for x in log.lost],  # damaged or missing stretches (LostData)
        "topics": [_topic_json(s) for s in log.topics.values()],
    }
    if config is not None:
        out["config"] = str(config.path)
        out["streams"] = {
            name: {"samples": len(m), "bad": m.bad.as_dict()}
            for name, m in log.measurements.items()
        }
        out["checklist"] = [asdict(c) for c in checks]
    return out

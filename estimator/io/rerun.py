"""The Rerun recording a user opens to judge an estimate (`estimate.rrd`, a viewer, a web viewer).

    path = write_recording(estimate, model, log, path="out/estimate.rrd")
    write_recording(estimate, model, log, path=path, spawn=True)   # + a native viewer (display)
    write_recording(estimate, model, log, path=path, serve=True)   # + prints the web viewer URL
    serve_until_interrupted()                                       # keep serving until Ctrl-C
    show_recording(estimate, model, path, spawn=True)               # a written file, to a viewer

What the recording holds (entity paths; `time` is a duration timeline, seconds since the start
of the log, and the recording's start time is that instant in absolute time):

    world                                   Z up (MuJoCo's world frame), metres
      model/<body>                          Transform3D per knot: the body pose from qpos
        <geom>                              static primitive in the geom frame (Boxes3D,
                                            Capsules3D, Cylinders3D, Ellipsoids3D, Mesh3D)
      model/world/<geom>                    static world geoms; a plane is a thin box under z = 0
      measurements/<stream>/<element>       pose, tf, rigid_bodies: Transform3D per sample + axes
      measurements/<stream>                 markers: Points3D per sample, labelled by site
      contacts                              Arrows3D per knot from each contact point along the
                                            contact force (FORCE_SCALE_M_PER_WEIGHT m per body
                                            weight), coloured by Algorithm 5 branch
      contacts/points                       Points3D per knot at every contact, same colours
    plots/physics/<dof>                     whitened physics residual per dof (residuals["physics"])
    plots/sensors/<stream>/<i>              whitened residual component i of each other factor
    plots/contact_force/<body>              net normal contact force on the body, N
    plots/imu_bias/<stream>/{accel,gyro}/{x,y,z}   m/s², rad/s
    plots/uncertainty/<dof>                 qpos_std (free joint m / rad, hinge rad, slide m)

With a diagnosis (`physfuse diagnose`, estimator/diagnose):

    diagnostics/events                      TextLog at each event's start (report.message)
    world/diagnostics/<body>                Arrows3D along an unmodeled contact's fitted
                                            force, onto its contact point (fixed in the body)
                                            or from the body's centre of mass, its interval's
                                            knots (the contacts' scale)
    plots/diagnostics/<body>                the detector's statistic over its threshold per
                                            knot (> 1: alarm), plots/diagnostics/threshold at 1

Every per-knot array goes out in bulk with `send_columns`, RECORDING_PART_KNOTS knots at a
time, each part flushed; NaN samples (a knot without that factor) are left out of their
series. One blueprint: the 3D view on the left, tabs on the right (residuals, contact forces,
IMU biases, uncertainty). Only this module imports Rerun.
"""

from __future__ import annotations

import os
import socket
import sys
import time
import urllib.parse
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from estimator.diagnose.detect import Event
from estimator.diagnose.diagnosis import Diagnosis
from estimator.diagnose.report import message
from estimator.diagnose.slip import SLIP
from estimator.errors import PhysfuseError
from estimator.estimate import Estimate
from estimator.io.logs.reader import Log
from estimator.problem import dof_names
from estimator.rotations import xyzw
from physics.cone import Branch
from physics.model import weight as model_weight

# A contact force equal to the model's weight (total mass · |g|) is drawn this long, in metres.
FORCE_SCALE_M_PER_WEIGHT = 1.0
# Half extent of an infinite plane (MuJoCo plane size 0) drawn as the floor, m.
FLOOR_HALF_EXTENT_M = 10.0
FLOOR_THICKNESS_M = 0.01
# MuJoCo's viewer shows geom groups 0-2 by default; 3+ are usually collision-only duplicates.
VISIBLE_GEOM_GROUPS = 3

BRANCH_COLORS: Mapping[Branch, tuple[int, int, int]] = {
    Branch.STICKING: (46, 204, 113),
    Branch.SLIDING: (230, 126, 34),
    Branch.SEPARATING: (149, 165, 166),
}
XYZ_COLORS = ((231, 76, 60), (39, 174, 96), (52, 120, 219))
MEASUREMENT_COLORS = ((52, 152, 219), (155, 89, 182), (241, 196, 15), (26, 188, 156))
POSE_KINDS = ("pose", "tf", "rigid_bodies")

DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
LIVE_FLUSH_TIMEOUT_S = 60.0  # never wait forever on a viewer that went away
# knots sent between flushes: the SDK's buffers hold a part, not the recording (writing a
# 10-minute humanoid_push estimate with its log: RSS +222 MB at once, +52 MB in these parts)
RECORDING_PART_KNOTS = 6000

_G = mujoco.mjtGeom
_J = mujoco.mjtJoint
_SERVING: list[rr.RecordingStream] = []


class ViewerError(PhysfuseError):
    """A Rerun viewer cannot be spawned or served (no display, a port in use)."""


def write_recording(
    estimate: Estimate,
    model: mujoco.MjModel,
    log: Log | None = None,
    *,
    path: str | Path | None = None,
    spawn: bool = False,
    serve: bool = False,
    application_id: str = "physfuse",
    recording_id: str | None = None,
    host: str = "127.0.0.1",
    grpc_port: int = DEFAULT_GRPC_PORT,
    web_port: int = DEFAULT_WEB_PORT,
    open_browser: bool = False,
    diagnosis: Diagnosis | None = None,
) -> Path | None:
    """Write the estimate (and the log's mocap poses and markers) as a Rerun recording.

    estimate: on the grid of `model` (estimate.qpos has model.nq columns).
    log: the log the estimate came from; its pose, tf, rigid_bodies and markers streams are
        drawn beside the model (the other kinds show through their residuals and biases).
    path: the `.rrd` file to write (returned); None writes no file. It is written first, so
        that a viewer that cannot open (ViewerError) still leaves it complete.
    spawn: also start a native Rerun viewer (the `rerun` executable on PATH, and a display)
        listening on port 9876 (grpc_port + 1 when also serving) and send it the recording;
        returns once the viewer has it.
    serve: also serve the recording over gRPC on host:grpc_port and a web viewer on
        web_port, and print the viewer's URL. Returns once the data is served; the servers
        live until `stop_serving()` (or process exit), so keep the process alive, e.g. with
        `serve_until_interrupted()`. The web viewer's HTTP server cannot be stopped before the
        process exits (Rerun 0.41 has no call for it).
    recording_id: the recording's id (default: a new UUID), e.g. a run id shared with other
        outputs of the same run.
    diagnosis: `physfuse diagnose`'s events, forces and statistic drawn too (module docstring).
    Each call makes its own `rr.RecordingStream` (never the global one).
    """
    if estimate.qpos.shape != (estimate.T, model.nq):
        raise ValueError(
            f"estimate.qpos has shape {estimate.qpos.shape}, expected "
            f"({estimate.T}, {model.nq}) for model {estimate.model_name!r}"
        )
    if path is None and not spawn and not serve:
        raise ValueError("write_recording: give a path, spawn=True or serve=True")
    recording_id = recording_id or str(uuid.uuid4())
    blueprint = build_blueprint(estimate, model, diagnosis is not None)
    out = None if path is None else Path(path)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        rec = rr.RecordingStream(application_id, recording_id=recording_id)
        rec.set_sinks(rr.FileSink(str(out)), default_blueprint=blueprint)
        _log_all(rec, estimate, model, log)
        if diagnosis is not None:
            _log_diagnosis(rec, model, estimate, diagnosis, _start_ns(estimate, log))
        rec.flush()
        rec.disconnect()  # closes the file and writes its footer
    if spawn or serve:
        _check_viewer(spawn, serve, host, grpc_port, web_port)
        _show(
            estimate, model, log, out, blueprint, application_id, recording_id,
            spawn=spawn, serve=serve, host=host, grpc_port=grpc_port, web_port=web_port,
            open_browser=open_browser,
        )  # fmt: skip
    return out


def show_recording(
    estimate: Estimate,
    model: mujoco.MjModel,
    path: str | Path,
    *,
    spawn: bool = False,
    serve: bool = False,
    application_id: str = "physfuse",
    host: str = "127.0.0.1",
    grpc_port: int = DEFAULT_GRPC_PORT,
    web_port: int = DEFAULT_WEB_PORT,
    open_browser: bool = False,
) -> None:
    """Send a recording `write_recording` wrote to `path` to a viewer (spawn / serve as in
    `write_recording`), its chunks read back from the file; ViewerError when none can open."""
    _check_viewer(spawn, serve, host, grpc_port, web_port)
    (store,) = rr.chunk.RrdReader(Path(path)).recordings()
    _show(
        estimate, model, None, Path(path), build_blueprint(estimate, model), application_id,
        store.recording_id, spawn=spawn, serve=serve, host=host, grpc_port=grpc_port,
        web_port=web_port, open_browser=open_browser,
    )  # fmt: skip


def _check_viewer(spawn: bool, serve: bool, host: str, grpc_port: int, web_port: int) -> None:
    if spawn:
        _check_display()
    if serve:
        _check_port_free(host, grpc_port)
        _check_port_free("0.0.0.0", web_port)  # the web viewer's HTTP server binds everywhere


def _show(
    estimate: Estimate,
    model: mujoco.MjModel,
    log: Log | None,
    out: Path | None,
    blueprint: rrb.Blueprint,
    application_id: str,
    recording_id: str,
    *,
    spawn: bool,
    serve: bool,
    host: str,
    grpc_port: int,
    web_port: int,
    open_browser: bool,
) -> None:
    """The live part of `write_recording`: the file's chunks (`out`), else the estimate
    logged anew, to a spawned viewer and / or a served one."""
    live = rr.RecordingStream(application_id, recording_id=recording_id)
    sinks: list[rr.GrpcSink | rr.GrpcServerSink] = []
    if spawn:
        viewer_port = grpc_port + 1 if serve else DEFAULT_GRPC_PORT
        live.spawn(port=viewer_port, connect=False)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{viewer_port}/proxy"))
    server = rr.GrpcServerSink(host, grpc_port) if serve else None
    if server is not None:
        sinks.append(server)
    live.set_sinks(*sinks, default_blueprint=blueprint)
    if out is not None:  # the same chunks as the file, without logging them again
        live.send_chunks(rr.chunk.RrdReader(out).stream())
    else:
        _log_all(live, estimate, model, log)
    live.flush(timeout_sec=LIVE_FLUSH_TIMEOUT_S)
    if server is not None:
        try:
            rr.serve_web_viewer(web_port=web_port, open_browser=open_browser, connect_to=server.uri)
        except RuntimeError as err:
            live.disconnect()
            raise ViewerError(f"cannot serve the web viewer on port {web_port}: {err}") from err
        print(f"Rerun web viewer: {web_viewer_url(server.uri, host, web_port)}")
        print(f"Native viewer:    rerun {server.uri}")
        _SERVING.append(live)
    else:
        live.disconnect()


class LiveRecording:
    """A streaming run's estimate as a Rerun recording that grows with it: the model's geoms
    once, then each update's knots (body poses, contacts, contact forces, uncertainty) on
    the `time` timeline (seconds since the stream's first knot).

    to: a `.rrd` path (written as it goes; complete once `close`d), "spawn" (a native viewer
    on this machine), or "serve" (a gRPC server and a web viewer on localhost; the URLs are
    printed).

        live = LiveRecording(model, "out/live.rrd")     # a viewer that cannot open: here
        live.log(update.estimate, update.newest, t0_ns)  # t0_ns: the first call's is kept
        live.log_events(update.events)                   # `Stream(diagnose=...)`'s reports
        live.close()
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        to: str,
        recording_id: str | None = None,
        host: str = "127.0.0.1",
        diagnose: bool = False,
    ) -> None:
        self.model = model
        self.diagnose = diagnose  # the Diagnostics tab (events only)
        self.t0_ns: int | None = None
        self.rec = rr.RecordingStream("physfuse stream", recording_id=recording_id)
        if to == "spawn":
            _check_viewer(True, False, host, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT)
            self.rec.spawn(port=DEFAULT_GRPC_PORT)
        elif to == "serve":
            _check_viewer(False, True, host, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT)
            server = rr.GrpcServerSink(host, DEFAULT_GRPC_PORT)
            self.rec.set_sinks(server)
            rr.serve_web_viewer(web_port=DEFAULT_WEB_PORT, connect_to=server.uri)
            print(f"Rerun web viewer: {web_viewer_url(server.uri, host)}", file=sys.stderr)
        else:
            Path(to).parent.mkdir(parents=True, exist_ok=True)
            self.rec.set_sinks(rr.FileSink(to))
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        _log_geoms(self.rec, model)
        self.dofs = dof_names(model)
        self.bodies: set[int] = set()  # in contact in an update so far (`_log_contacts`)

    def log(self, estimate: Estimate, knots: range, t0_ns: int) -> None:
        """The estimate's knots `knots` (indices into it); t0_ns: the time origin (the
        stream's first knot; the first call's is kept)."""
        if not len(knots):
            return
        part = _knots_of(estimate, knots)
        if self.t0_ns is None:  # (the blueprint's tabs follow what the estimate holds)
            self.t0_ns = t0_ns
            self.rec.send_recording_start_time_nanos(t0_ns)
            self.rec.send_blueprint(
                build_blueprint(part, self.model, self.diagnose, statistic=False)
            )
        offsets = part.t_ns - np.int64(self.t0_ns)
        _log_body_poses(self.rec, self.model, part.qpos, offsets)
        _log_contacts(self.rec, self.model, part, offsets, self.bodies)
        _log_series_group(self.rec, "plots/uncertainty", self.dofs, part.qpos_std, offsets)

    def log_events(self, events: Sequence[Event]) -> None:
        """Diagnostic events as text on the timeline: an ongoing one at the knot that reported
        it, a final one at its start."""
        if self.t0_ns is None:
            return
        for e in events:
            at = e.detected_ns if e.ongoing else e.start_ns
            level = rr.TextLogLevel.ERROR if e.kind == "sensor fault" else rr.TextLogLevel.WARN
            self.rec.set_time("time", duration=np.timedelta64(at - self.t0_ns, "ns"))
            self.rec.log("diagnostics/events", rr.TextLog(f"{e.kind}: {message(e)}", level=level))

    def close(self) -> None:
        self.rec.flush(timeout_sec=LIVE_FLUSH_TIMEOUT_S)
        self.rec.disconnect()


def _knots_of(estimate: Estimate, knots: range) -> Estimate:
    """The estimate at some of its knots (no residuals)."""
    part = estimate.at(slice(knots.start, knots.stop))
    return replace(part, residuals={}, residual_labels={}, cost_by_type={})


def _check_display() -> None:
    """A native viewer needs a display; without one Rerun's viewer exits and the SDK waits."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise ViewerError(
            "--spawn needs a display (neither DISPLAY nor WAYLAND_DISPLAY is set); use --serve "
            "and open the printed URL in a browser, or open the .rrd with `rerun` elsewhere"
        )


def _check_port_free(host: str, port: int) -> None:
    """Rerun's gRPC server only logs a failed bind; find a taken port before it does."""
    with socket.socket() as probe:
        try:
            probe.bind((host, port))
        except OSError as err:
            raise ViewerError(
                f"cannot serve on {host}:{port}: {err.strerror}; choose another port"
            ) from err


def web_viewer_url(grpc_uri: str, host: str = "127.0.0.1", web_port: int = DEFAULT_WEB_PORT) -> str:
    """The address a browser opens to see the recording served at `grpc_uri`."""
    return f"http://{host}:{web_port}/?url={urllib.parse.quote(grpc_uri, safe='')}"


def stop_serving() -> None:
    """Shut down the gRPC servers of every `write_recording(serve=True)` of this process."""
    while _SERVING:
        _SERVING.pop().disconnect()


def serve_until_interrupted() -> None:
    """Block until Ctrl-C, then `stop_serving()` (for a CLI that served a recording)."""
    try:
        while _SERVING:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("stopping the Rerun servers", file=sys.stderr)
    finally:
        stop_serving()


def build_blueprint(
    estimate: Estimate, model: mujoco.MjModel, diagnosis: bool = False, statistic: bool = True
) -> rrb.Blueprint:
    """The layout: 3D view left; right, tabs of time series (only those with data), the
    diagnosis's first when there is one (its events, and the detector's statistic unless
    `statistic` is False: a live stream's)."""
    tabs: list[rrb.Container | rrb.View] = []
    if diagnosis:
        events = rrb.TextLogView(origin="diagnostics/events", name="Events")
        if statistic:
            plot = rrb.TimeSeriesView(
                origin="plots/diagnostics", name="Unmodeled-force statistic / threshold"
            )
            tabs.append(rrb.Vertical(events, plot, row_shares=[1, 2], name="Diagnostics"))
        else:
            tabs.append(rrb.Vertical(events, name="Diagnostics"))
    residual_views = []
    if "physics" in estimate.residuals:
        residual_views.append(
            rrb.TimeSeriesView(origin="plots/physics", name="Physics residuals (whitened)")
        )
    if any(key != "physics" for key in estimate.residuals):
        residual_views.append(
            rrb.TimeSeriesView(origin="plots/sensors", name="Sensor residuals (whitened)")
        )
    if residual_views:
        tabs.append(rrb.Vertical(*residual_views, name="Residuals"))
    tabs.append(rrb.TimeSeriesView(origin="plots/contact_force", name="Contact normal force [N]"))
    if estimate.imu_bias:
        streams = [_part(s) for s in estimate.imu_bias]
        tabs.append(
            rrb.Vertical(
                rrb.TimeSeriesView(
                    origin="plots/imu_bias",
                    contents=[f"$origin/{s}/accel/**" for s in streams],
                    name="Accelerometer bias [m/s²]",
                ),
                rrb.TimeSeriesView(
                    origin="plots/imu_bias",
                    contents=[f"$origin/{s}/gyro/**" for s in streams],
                    name="Gyro bias [rad/s]",
                ),
                name="IMU biases",
            )
        )
    tabs.append(rrb.TimeSeriesView(origin="plots/uncertainty", name="qpos std (m, rad)"))
    weight = model_weight(model)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                origin="world",
                name=f"{Path(estimate.model_name).stem} (contact arrows: "
                f"{FORCE_SCALE_M_PER_WEIGHT:g} m = "
                f"body weight, {weight:.0f} N)",
                eye_controls=_eye(model, estimate.qpos[0]) if estimate.T else None,
            ),
            rrb.Tabs(*tabs, name="Time series"),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="time", state="collapsed"),
    )


def contact_forces_world(estimate: Estimate, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(pos (n, 3), force (n, 3)) of the n contacts of knot k, world frame, m and N.

    force = frame.T @ (impulse / h)[:3]: normal and the two tangential components (torsional
    and rolling components are torques and not drawn); a condim-1 contact has only the normal.
    """
    c = estimate.constraints[k]
    n = len(c.contacts.pos)
    f_contact = np.zeros((n, 3))
    for i in range(n):
        impulse = c.contact_impulse(i)
        f_contact[i, : min(3, len(impulse))] = impulse[:3] / c.h
    force = np.einsum("nji,nj->ni", c.contacts.frame.reshape(n, 3, 3), f_contact)
    return c.contacts.pos.reshape(n, 3), force


# -- logging ----------------------------------------------------------------------------------
def _log_all(
    rec: rr.RecordingStream, estimate: Estimate, model: mujoco.MjModel, log: Log | None
) -> None:
    """The whole estimate, RECORDING_PART_KNOTS knots (and the log's samples from the part's
    first knot to the next part's) at a time, each part flushed to the sinks."""
    t0_ns = _start_ns(estimate, log)
    _log_static(rec, model, t0_ns)
    starts = range(0, max(estimate.T, 1), RECORDING_PART_KNOTS)
    bodies = _contact_bodies(model, estimate)  # (each part plots them all, as the whole would)
    for start in starts:
        stop = min(start + RECORDING_PART_KNOTS, estimate.T)
        part_log = log
        if log is not None and len(starts) > 1:  # its samples in [t_start, t_stop)
            t_start = int(estimate.t_ns[start]) if start else np.iinfo(np.int64).min
            t_stop = int(estimate.t_ns[stop]) if stop < estimate.T else np.iinfo(np.int64).max
            part_log = replace(
                log,
                measurements={s: m.between(t_start, t_stop) for s, m in log.measurements.items()},
            )
        _log_knots(rec, estimate.at(slice(start, stop)), model, part_log, t0_ns, bodies)
        rec.flush(timeout_sec=LIVE_FLUSH_TIMEOUT_S)


def _log_static(rec: rr.RecordingStream, model: mujoco.MjModel, t0_ns: int) -> None:
    """What a recording logs once: its start time, the world's axes, the geoms."""
    rec.send_recording_start_time_nanos(t0_ns)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_geoms(rec, model)


def _log_knots(
    rec: rr.RecordingStream,
    estimate: Estimate,
    model: mujoco.MjModel,
    log: Log | None,
    t0_ns: int,
    bodies: set[int],
) -> None:
    """The estimate's knots (and the log's mocap over them) on the timeline from t0_ns;
    bodies: of the contact force plots (`_log_contacts`)."""
    knots = estimate.t_ns - np.int64(t0_ns)  # (T,) int64 ns since the start
    _log_body_poses(rec, model, estimate.qpos, knots)
    _log_contacts(rec, model, estimate, knots, bodies)
    if log is not None:
        _log_measurements(rec, log, t0_ns)
    dofs = dof_names(model)
    _log_residuals(rec, estimate, dofs, knots)
    _log_imu_bias(rec, estimate, knots)
    _log_series_group(rec, "plots/uncertainty", dofs, estimate.qpos_std, knots)


class RecordingWriter:
    """An estimate written to a `.rrd` file part by part, in time order (a long log in
    chunks: `estimator.chunks`), as `write_recording` writes it whole. The file is complete
    once `close` has run.

        with RecordingWriter(path, model, t0_ns, run_id) as rrd:
            rrd.write(part, log_part)
    """

    def __init__(
        self, path: str | Path, model: mujoco.MjModel, t0_ns: int, recording_id: str
    ) -> None:
        self.path, self.model, self.t0_ns = Path(path), model, int(t0_ns)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("physfuse", recording_id=recording_id)
        self.started = False
        self.bodies: set[int] = set()  # in contact in a part so far (`_log_contacts`)

    def write(self, estimate: Estimate, log: Log | None = None) -> None:
        if not self.started:  # the layout from the first part (its residuals and streams)
            blueprint = build_blueprint(estimate, self.model)
            self.rec.set_sinks(rr.FileSink(str(self.path)), default_blueprint=blueprint)
            _log_static(self.rec, self.model, self.t0_ns)
            self.started = True
        _log_knots(self.rec, estimate, self.model, log, self.t0_ns, self.bodies)
        self.rec.flush()  # to the file: memory holds one part, not the recording

    def close(self) -> None:
        if self.started:
            self.rec.flush()
            self.rec.disconnect()  # closes the file and writes its footer

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _log_diagnosis(
    rec: rr.RecordingStream,
    model: mujoco.MjModel,
    estimate: Estimate,
    diagnosis: Diagnosis,
    t0_ns: int,
) -> None:
    """The events as text, unmodeled contacts as arrows, slips as their paths, the detector's
    statistic as plots."""
    det = diagnosis.detection
    knots = estimate.t_ns - np.int64(t0_ns)
    for e in diagnosis.events:
        level = rr.TextLogLevel.ERROR if e.kind == "sensor fault" else rr.TextLogLevel.WARN
        rec.set_time("time", duration=np.timedelta64(e.start_ns - t0_ns, "ns"))
        rec.log("diagnostics/events", rr.TextLog(f"{e.kind}: {message(e)}", level=level))
    rec.reset_time()
    for b, body in enumerate(det.forces.bodies):
        _log_series(
            rec, f"plots/diagnostics/{_part(body)}", body, det.d2[:, b] / det.threshold, knots
        )
    _log_series(
        rec, "plots/diagnostics/threshold", "threshold", np.ones(estimate.T), knots, (0, 0, 0)
    )
    scale = FORCE_SCALE_M_PER_WEIGHT / max(model_weight(model), 1e-9)
    d = mujoco.MjData(model)
    contacts = [e for e in diagnosis.events if e.kind == "unmodeled contact"]
    for body in dict.fromkeys(e.target for e in contacts):
        b = model.body(body).id
        counts = np.zeros(estimate.T, dtype=np.int64)
        origins, vectors, labels = [], [], []
        for k in range(estimate.T):
            on = [
                e
                for e in contacts
                if e.target == body and e.start_ns <= estimate.t_ns[k] <= e.end_ns
            ]
            if not on:
                continue
            d.qpos[:] = estimate.qpos[k]
            mujoco.mj_kinematics(model, d)
            counts[k] = 1
            vector = on[0].force * scale
            if on[0].point is None:  # from the centre of mass
                origins.append(d.xipos[b].copy())
            else:  # onto the contact point, fixed in the body
                point = _in_body(model, estimate, on[0], b)
                origins.append(d.xpos[b] + d.xmat[b].reshape(3, 3) @ point - vector)
            vectors.append(vector)
            labels.append(f"{on[0].magnitude:.1f} ± {on[0].magnitude_std:.1f} N unmodeled")
        rec.send_columns(
            f"world/diagnostics/{_body_name(model, b, escape=True)}",
            indexes=[_time(knots)],
            columns=rr.Arrows3D.columns(
                origins=np.reshape(origins, (-1, 3)),
                vectors=np.reshape(vectors, (-1, 3)),
                labels=labels,
            ).partition(counts),
        )
        rec.log(
            f"world/diagnostics/{_body_name(model, b, escape=True)}",
            rr.Arrows3D.from_fields(radii=0.015, colors=[(192, 57, 43)]),
            static=True,
        )
    _log_slips(rec, model, estimate, diagnosis, t0_ns)


def _log_slips(
    rec: rr.RecordingStream,
    model: mujoco.MjModel,
    estimate: Estimate,
    diagnosis: Diagnosis,
    t0_ns: int,
) -> None:
    """Each slip as the path its body's origin takes over it (orange), shown from the slip's
    start to its end."""
    d = mujoco.MjData(model)
    for e in diagnosis.events:
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, e.target)
        if e.kind != SLIP or b < 0:
            continue
        path = []
        for k in np.flatnonzero((estimate.t_ns >= e.start_ns) & (estimate.t_ns <= e.end_ns)):
            d.qpos[:] = estimate.qpos[k]
            mujoco.mj_kinematics(model, d)
            path.append(d.xpos[b].copy())
        entity = f"world/diagnostics/slip/{_body_name(model, b, escape=True)}"
        rec.set_time("time", duration=np.timedelta64(e.start_ns - t0_ns, "ns"))
        rec.log(
            entity,
            rr.LineStrips3D(
                [np.reshape(path, (-1, 3))],
                radii=0.006,
                colors=[(230, 126, 34)],
                labels=[f"slip {100 * e.force[0]:.1f} cm"],
            ),
        )
        rec.set_time("time", duration=np.timedelta64(e.end_ns - t0_ns, "ns"))
        rec.log(entity, rr.LineStrips3D([], radii=[], colors=[], labels=[]))  # gone
    rec.reset_time()


def _log_geoms(rec: rr.RecordingStream, model: mujoco.MjModel) -> None:
    for g in _visible_geoms(model):
        entity = f"{_body_path(model, int(model.geom_bodyid[g]))}/{_geom_name(model, g)}"
        shape = _geom_archetype(model, g)
        if shape is None:
            continue
        rec.log(
            entity,
            rr.Transform3D(
                translation=model.geom_pos[g],
                quaternion=rr.Quaternion(xyzw=xyzw(model.geom_quat[g])),
            ),
            shape,
            static=True,
        )


def _log_body_poses(
    rec: rr.RecordingStream, model: mujoco.MjModel, qpos: np.ndarray, knots: np.ndarray
) -> None:
    bodies = sorted({int(model.geom_bodyid[g]) for g in _visible_geoms(model)})
    xpos, xquat = _body_poses(model, qpos)
    for b in bodies:
        if b == 0:
            continue
        if model.body_weldid[b] == 0:  # welded to the world: one static pose
            rec.log(
                _body_path(model, b),
                rr.Transform3D(
                    translation=xpos[0, b], quaternion=rr.Quaternion(xyzw=xyzw(xquat[0, b]))
                ),
                static=True,
            )
            continue
        rec.send_columns(
            _body_path(model, b),
            indexes=[_time(knots)],
            columns=rr.Transform3D.columns(translation=xpos[:, b], quaternion=xyzw(xquat[:, b])),
        )


def _log_contacts(
    rec: rr.RecordingStream,
    model: mujoco.MjModel,
    estimate: Estimate,
    knots: np.ndarray,
    bodies: set[int],
) -> None:
    """Contact arrows and points per knot, and the net normal force on each body in contact
    and each of `bodies` (zero out of contact), which those in contact join: a recording
    written in parts plots a body at every knot from its first contact on, not across a gap."""
    scale = FORCE_SCALE_M_PER_WEIGHT / max(model_weight(model), 1e-9)
    counts = np.zeros(estimate.T, dtype=np.int64)
    origins, vectors, colors, labels = [], [], [], []
    normal_force = {b: np.zeros(estimate.T) for b in bodies}
    for k, c in enumerate(estimate.constraints):
        pos, force = contact_forces_world(estimate, k)
        counts[k] = len(pos)
        for i in range(len(pos)):
            branch = c.contact_branch(i)
            pair = [int(model.geom_bodyid[g]) for g in c.contacts.geom[i]]
            f_n = float(c.contact_impulse(i)[0] / c.h)  # normal component, N
            for b in set(pair) - {0}:
                normal_force.setdefault(b, np.zeros(estimate.T))[k] += f_n
            names = "–".join(_body_name(model, b) for b in pair if b != 0) or "world"
            origins.append(pos[i])
            vectors.append(force[i] * scale)
            colors.append(BRANCH_COLORS[branch])
            labels.append(f"{names} {np.linalg.norm(force[i]):.0f} N {branch.name.lower()}")
    p_world = np.reshape(origins, (-1, 3))
    rgb = np.reshape(colors, (-1, 3)).astype(np.uint8)
    rec.send_columns(
        "world/contacts",
        indexes=[_time(knots)],
        columns=rr.Arrows3D.columns(
            origins=p_world,
            vectors=np.reshape(vectors, (-1, 3)),
            colors=rgb,
            labels=labels,
        ).partition(counts),
    )
    rec.send_columns(
        "world/contacts/points",
        indexes=[_time(knots)],
        columns=rr.Points3D.columns(positions=p_world, colors=rgb).partition(counts),
    )
    rec.log("world/contacts", rr.Arrows3D.from_fields(radii=0.008), static=True)
    rec.log("world/contacts/points", rr.Points3D.from_fields(radii=0.015), static=True)
    bodies.update(normal_force)
    for b in sorted(normal_force):
        _log_series(
            rec,
            f"plots/contact_force/{_body_name(model, b, escape=True)}",
            _body_name(model, b),
            normal_force[b],
            knots,
        )


def _contact_bodies(model: mujoco.MjModel, estimate: Estimate) -> set[int]:
    """The bodies (not the world) in contact at some knot of the estimate."""
    geoms = [np.reshape(c.contacts.geom, -1) for c in estimate.constraints]
    return {int(b) for b in model.geom_bodyid[np.concatenate([*geoms, []]).astype(int)]} - {0}


def _log_measurements(rec: rr.RecordingStream, log: Log, t0_ns: int) -> None:
    """Mocap poses as moving axes, markers as points, on their own sample times."""
    for n, m in enumerate(log.measurements.values()):
        if not len(m) or m.kind not in (*POSE_KINDS, "markers"):
            continue
        color = MEASUREMENT_COLORS[n % len(MEASUREMENT_COLORS)]
        base = f"world/measurements/{_part(m.stream)}"
        if m.kind == "markers":
            finite = np.all(np.isfinite(m.values), axis=2)  # (N, E)
            element = np.broadcast_to(np.arange(len(m.elements)), finite.shape)[finite]
            rec.send_columns(
                base,
                indexes=[_time(m.t_ns - t0_ns)],
                columns=rr.Points3D.columns(
                    positions=m.values[finite], labels=[m.elements[e] for e in element]
                ).partition(finite.sum(axis=1)),
            )
            rec.log(base, rr.Points3D.from_fields(radii=0.012, colors=color), static=True)
            continue
        for e, name in enumerate(m.elements):
            values = m.values[:, e, :]
            keep = np.all(np.isfinite(values), axis=1)
            if not keep.any():
                continue
            entity = f"{base}/{_part(name)}"
            rec.send_columns(
                entity,
                indexes=[_time(m.t_ns[keep] - t0_ns)],
                columns=rr.Transform3D.columns(
                    translation=values[keep, :3], quaternion=xyzw(values[keep, 3:7])
                ),
            )
            rec.log(entity, rr.TransformAxes3D(0.1), static=True)


def _log_residuals(
    rec: rr.RecordingStream, estimate: Estimate, dofs: Sequence[str], knots: np.ndarray
) -> None:
    for factor, r in estimate.residuals.items():
        r = np.asarray(r).reshape(estimate.T, -1)
        labels = estimate.residual_labels.get(factor)
        if not labels or len(labels) != r.shape[1]:
            labels = list(dofs) if r.shape[1] == len(dofs) else _indexed("r", r.shape[1])
        if factor == "physics":
            _log_series_group(rec, "plots/physics", labels, r, knots)
        else:
            entity = f"plots/sensors/{_part(factor)}"
            for i, label in enumerate(labels):
                _log_series(rec, f"{entity}/{i}", f"{factor} {label}", r[:, i], knots)


def _log_imu_bias(rec: rr.RecordingStream, estimate: Estimate, knots: np.ndarray) -> None:
    for stream, bias in estimate.imu_bias.items():
        bias = np.asarray(bias).reshape(estimate.T, 6)
        for j, quantity in enumerate(("accel", "gyro")):
            for i, axis in enumerate("xyz"):
                _log_series(
                    rec,
                    f"plots/imu_bias/{_part(stream)}/{quantity}/{axis}",
                    f"{stream} {quantity} {axis}",
                    bias[:, 3 * j + i],
                    knots,
                    color=XYZ_COLORS[i],
                )


def _log_series_group(
    rec: rr.RecordingStream,
    root: str,
    names: Sequence[str],
    values: np.ndarray,
    knots: np.ndarray,
) -> None:
    """One series per column of values (T, len(names)), at `root/<name>`."""
    for i, name in enumerate(names):
        _log_series(rec, f"{root}/{_part(name)}", name, values[:, i], knots)


def _log_series(
    rec: rr.RecordingStream,
    entity: str,
    name: str,
    values: np.ndarray,
    knots: np.ndarray,
    color: tuple[int, int, int] | None = None,
) -> None:
    """A scalar series (T,) on the knot times, NaN knots left out."""
    keep = np.isfinite(values)
    if not keep.any():
        return
    rec.send_columns(
        entity, indexes=[_time(knots[keep])], columns=rr.Scalars.columns(scalars=values[keep])
    )
    rec.log(entity, rr.SeriesLines(names=name, colors=color), static=True)


# -- geometry ---------------------------------------------------------------------------------
def _geom_archetype(model: mujoco.MjModel, g: int) -> rr.AsComponents | None:
    """The geom as a Rerun primitive in its own frame (None for hfields and SDFs)."""
    size = model.geom_size[g]
    color = _geom_color(model, g)
    kind = model.geom_type[g]
    if kind == _G.mjGEOM_PLANE:
        half = [s if s > 0 else FLOOR_HALF_EXTENT_M for s in size[:2]]
        return rr.Boxes3D(
            half_sizes=[[half[0], half[1], FLOOR_THICKNESS_M / 2]],
            centers=[[0.0, 0.0, -FLOOR_THICKNESS_M / 2]],
            colors=[color],
            fill_mode="solid",
        )
    if kind == _G.mjGEOM_BOX:
        return rr.Boxes3D(half_sizes=[size], colors=[color], fill_mode="solid")
    if kind == _G.mjGEOM_SPHERE:
        return rr.Ellipsoids3D(half_sizes=[[size[0]] * 3], colors=[color], fill_mode="solid")
    if kind == _G.mjGEOM_ELLIPSOID:
        return rr.Ellipsoids3D(half_sizes=[size], colors=[color], fill_mode="solid")
    if kind == _G.mjGEOM_CAPSULE:  # Rerun's capsule runs from its origin along +z
        return rr.Capsules3D(
            lengths=[2 * size[1]],
            radii=[size[0]],
            translations=[[0.0, 0.0, -size[1]]],
            colors=[color],
        )
    if kind == _G.mjGEOM_CYLINDER:
        return rr.Cylinders3D(
            lengths=[2 * size[1]], radii=[size[0]], colors=[color], fill_mode="solid"
        )
    if kind == _G.mjGEOM_MESH:
        mesh = model.geom_dataid[g]
        v0, nv = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        f0, nf = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
        return rr.Mesh3D(
            vertex_positions=model.mesh_vert[v0 : v0 + nv],
            triangle_indices=model.mesh_face[f0 : f0 + nf],
            albedo_factor=color,
        )
    return None


def _geom_color(model: mujoco.MjModel, g: int) -> tuple[int, int, int, int]:
    rgba = model.geom_rgba[g]
    mat = model.geom_matid[g]
    if mat >= 0 and np.allclose(rgba, (0.5, 0.5, 0.5, 1.0)):  # MuJoCo's default: use material
        rgba = model.mat_rgba[mat]
    r, gr, b, a = (round(255 * float(np.clip(x, 0, 1))) for x in rgba)
    return r, gr, b, a


def _visible_geoms(model: mujoco.MjModel) -> list[int]:
    return [
        g
        for g in range(model.ngeom)
        if model.geom_group[g] < VISIBLE_GEOM_GROUPS and model.geom_rgba[g][3] > 0
    ]


def _eye(model: mujoco.MjModel, qpos: np.ndarray) -> rrb.EyeControls3D:
    """The 3D view's camera on the robot at `qpos` (the floor would frame a robot a few pixels
    tall): from the front right and above, three sizes of the robot away."""
    xpos = _body_poses(model, qpos[None])[0][0, 1:]
    centre = (xpos.min(axis=0) + xpos.max(axis=0)) / 2
    size = max(float(np.ptp(xpos, axis=0).max()), 0.3)
    return rrb.EyeControls3D(
        kind="Orbital", position=centre + size * np.array([2.0, -2.0, 1.2]), look_target=centre
    )


def _body_poses(model: mujoco.MjModel, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(xpos (T, nbody, 3), xquat (T, nbody, 4) w, x, y, z) of every body, world frame."""
    d = mujoco.MjData(model)
    n = len(qpos)
    xpos = np.empty((n, model.nbody, 3))
    xquat = np.empty((n, model.nbody, 4))
    for k in range(n):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, d)
        xpos[k] = d.xpos
        xquat[k] = d.xquat
    return xpos, xquat


# -- names, times, conventions ----------------------------------------------------------------
def _in_body(model: mujoco.MjModel, estimate: Estimate, e: Event, b: int) -> np.ndarray:
    """An event's contact point (world, at its middle knot: `contact_point`) in body b's
    frame."""
    knots = np.flatnonzero((estimate.t_ns >= e.start_ns) & (estimate.t_ns <= e.end_ns))
    d = mujoco.MjData(model)
    d.qpos[:] = estimate.qpos[knots[len(knots) // 2]]
    mujoco.mj_kinematics(model, d)
    assert e.point is not None
    return d.xmat[b].reshape(3, 3).T @ (e.point - d.xpos[b])


def _body_name(model: mujoco.MjModel, b: int, *, escape: bool = False) -> str:
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}"
    return _part(name) if escape else name


def _body_path(model: mujoco.MjModel, b: int) -> str:
    return f"world/model/{_body_name(model, b, escape=True)}"


def _geom_name(model: mujoco.MjModel, g: int) -> str:
    return _part(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}")


def _part(name: str) -> str:
    """One entity-path part (model and stream names may hold '/', spaces, dots)."""
    return rr.escape_entity_path_part(name)


def _indexed(prefix: str, n: int) -> list[str]:
    return [f"{prefix}{i}" for i in range(n)]


def _start_ns(estimate: Estimate, log: Log | None) -> int:
    """The time origin: the earliest knot or log sample, int ns."""
    starts = [int(estimate.t_ns[0])] if estimate.T else []
    if log is not None:
        starts += [int(m.t_ns[0]) for m in log.measurements.values() if len(m)]
    return min(starts) if starts else 0


def _time(offset_ns: np.ndarray) -> rr.TimeColumn:
    """The `time` timeline from int ns offsets since the start (exact; shown in seconds)."""
    return rr.TimeColumn("time", duration=np.asarray(offset_ns, np.int64).astype("timedelta64[ns]"))

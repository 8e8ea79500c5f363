"""`estimate.rrd`: written from a real humanoid estimate, read back with Rerun's own reader.

The estimate is a 1 s MuJoCo simulation of the humanoid collapsing from its "home" keyframe
(feet on the floor, then hands, knees and hips), with the analytic inverse's forces and
impulses at every knot; the measurements come from a real ROS 2 MCAP log read by
`estimator.io.logs.read_log`.
"""

from __future__ import annotations

import socket
import time
import urllib.request
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np
import pyarrow as pa
import pytest
import rerun as rr
import ros2_logs as rl

from estimator.config import load_config
from estimator.estimate import Estimate
from estimator.io import rerun as visualize
from estimator.io.logs import read_log
from estimator.io.logs import ros2_types as t
from physics.cone import Branch
from physics.dynamics import make_dynamics
from physics.model import load_model

SECONDS = 1.0
MARKER_SITES = {"torso": "torso_marker", "head": "head_marker"}
CONFIG = """\
model = "humanoid"

[streams.mocap_torso]
type = "pose"
topic = "/mocap/torso"
body = "torso"

[streams.markers]
type = "markers"
topic = "/mocap/markers"
markers = { torso = "torso_marker", head = "head_marker" }
"""


# -- a real estimate --------------------------------------------------------------------------
def simulate_estimate(model: mujoco.MjModel, seconds: float, t0_ns: int = rl.T0) -> Estimate:
    """MuJoCo's own trajectory from the home keyframe, put in the Estimate's conventions."""
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, 0)
    h = float(model.opt.timestep)
    T = round(seconds / h)
    qpos = np.empty((T, model.nq))
    for k in range(T):
        qpos[k] = d.qpos
        mujoco.mj_step(model, d)
    qvel = np.zeros((T, model.nv))  # v_k = (q_k ⊖ q_{k−1})/h, v_0 = v_1
    for k in range(1, T):
        mujoco.mj_differentiatePos(model, qvel[k], h, qpos[k - 1], qpos[k])
    qvel[0] = qvel[1]
    qacc = np.zeros((T, model.nv))
    qacc[:-1] = np.diff(qvel, axis=0) / h
    dyn = make_dynamics(model, "native")
    inverse = [dyn.inverse(qpos[k], qvel[k], qacc[k]) for k in range(T)]
    qfrc = np.array([r.qfrc_inverse for r in inverse])
    k = np.arange(T)
    physics = qfrc / 10.0
    physics[0] = np.nan  # no physics factor at the first knot
    sensor = np.stack([np.sin(0.1 * k), np.cos(0.1 * k), 0.01 * k], axis=1)
    sensor[::7, 1] = np.nan
    bias = np.outer(1 + 0.01 * k, [0.01, -0.02, 0.03, 1e-3, -2e-3, 3e-3])
    return Estimate(
        t_ns=t0_ns + k.astype(np.int64) * round(h * 1e9),
        h=h,
        qpos=qpos,
        qvel=qvel,
        qacc=qacc,
        qfrc_inverse=qfrc,
        qfrc_known=np.zeros_like(qfrc),
        qpos_std=np.full((T, model.nv), 1e-3) * (1 + k[:, None]),
        constraints=tuple(r.constraints for r in inverse),
        model_name="humanoid",
        imu_bias={"imu": bias},
        residuals={"physics": physics, "imu": sensor},
    )


# -- reading a recording back -----------------------------------------------------------------
@dataclass
class Entity:
    """One entity of a recording: static components, and temporal rows on `time` (ns)."""

    static: dict[str, list] = field(default_factory=dict)
    time_ns: list[int] = field(default_factory=list)
    rows: dict[str, list] = field(default_factory=lambda: defaultdict(list))

    def single(self, component: str) -> np.ndarray:
        """(rows, ...) the one instance each row of a single-instance component holds."""
        assert all(len(row) == 1 for row in self.rows[component]), component
        return np.array([row[0] for row in self.rows[component]])


def read_recording(path: Path) -> dict[str, Entity]:
    entities: dict[str, Entity] = defaultdict(Entity)
    chunks = sorted(
        rr.chunk.RrdReader(path).stream().collect().stream().to_chunks(),
        key=lambda c: c.entity_path,
    )
    for chunk in chunks:
        batch = chunk.to_record_batch()
        entity = entities[chunk.entity_path]
        components = [n for n in batch.schema.names if ":" in n]
        if chunk.is_static:
            for name in components:
                entity.static[name] = batch.column(name).to_pylist()[-1]
            continue
        assert "time" in chunk.timeline_names, chunk.entity_path
        entity.time_ns += batch.column("time").cast(pa.int64()).to_pylist()
        for name in components:
            entity.rows[name] += batch.column(name).to_pylist()
    for entity in entities.values():  # chunks of one entity may come in any order
        order = np.argsort(entity.time_ns, kind="stable")
        entity.time_ns = [entity.time_ns[i] for i in order]
        for name, rows in entity.rows.items():
            entity.rows[name] = [rows[i] for i in order]
    return dict(entities)


def blueprint_views(path: Path) -> dict[str, str]:
    """display name → space origin of every view in the file's blueprint."""
    reader = rr.chunk.RrdReader(path)
    (store,) = reader.blueprints()
    views = {}
    for chunk in reader.stream(store=store).to_chunks():
        batch = chunk.to_record_batch()
        if "ViewBlueprint:display_name" in batch.schema.names:
            name = batch.column("ViewBlueprint:display_name").to_pylist()[-1][0]
            origin = batch.column("ViewBlueprint:space_origin").to_pylist()[-1][0]
            views[name] = origin
    return views


def body_poses(model: mujoco.MjModel, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = mujoco.MjData(model)
    xpos, xquat = [], []
    for q in qpos:
        d.qpos[:] = q
        mujoco.mj_forward(model, d)
        xpos.append(d.xpos.copy())
        xquat.append(d.xquat.copy())
    return np.array(xpos), np.array(xquat)


def xyzw(q_wxyz) -> np.ndarray:
    return np.asarray([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]])


# -- fixtures ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def humanoid():
    model = load_model("humanoid")
    return model, simulate_estimate(model, SECONDS)


@pytest.fixture(scope="module")
def recording(humanoid, tmp_path_factory):
    model, estimate = humanoid
    path = visualize.write_recording(
        estimate, model, path=tmp_path_factory.mktemp("rrd") / "estimate.rrd"
    )
    assert path is not None
    return path, read_recording(path)


@pytest.fixture(scope="module")
def mocap(humanoid, tmp_path_factory):
    """A real MCAP of the torso pose (200 Hz) and two markers (100 Hz), stamped on the
    estimate's clock, read with the config: (truth, log, recording read back)."""
    model, estimate = humanoid
    folder = tmp_path_factory.mktemp("mocap")
    d = mujoco.MjData(model)
    messages, truth = [], {"pose": [], "markers": []}
    times = np.arange(estimate.t_ns[0], estimate.t_ns[-1], 5_000_000)  # 200 Hz
    for n, t_ns in enumerate(times):
        k = int(np.searchsorted(estimate.t_ns, t_ns, side="right") - 1)
        d.qpos[:] = estimate.qpos[k]
        mujoco.mj_kinematics(model, d)
        pos, quat = d.xpos[1].copy() + 0.01, d.xquat[1].copy()  # offset: visibly a measurement
        messages.append(
            rl.Msg(
                "/mocap/torso", t.POSE_STAMPED, int(t_ns) + 1000, rl.pose_stamped(t_ns, pos, quat)
            )
        )
        truth["pose"].append((int(t_ns), pos, quat))
        if n % 2:
            continue
        entries = [
            (rl.USE_NAME, i, name, d.site(site).xpos.copy())
            for i, (name, site) in enumerate(MARKER_SITES.items())
        ]
        messages.append(
            rl.Msg("/mocap/markers", t.MARKERS, int(t_ns) + 1000, rl.markers(t_ns, entries))
        )
        truth["markers"].append((int(t_ns), entries))
    path = folder / "mocap.mcap"
    rl.write_mcap(path, sorted(messages, key=lambda m: m.log_time_ns))
    (folder / "config.toml").write_text(CONFIG)
    log = read_log(path, load_config(folder / "config.toml"))
    out = visualize.write_recording(estimate, model, log, path=folder / "estimate.rrd")
    assert out is not None
    return truth, log, read_recording(out)


# -- the model and its motion -----------------------------------------------------------------
def test_every_geom_is_logged_once_in_its_body_frame(humanoid, recording):
    model, _ = humanoid
    _, entities = recording
    for g in range(model.ngeom):
        body = model.body(model.geom_bodyid[g]).name
        entity = entities[f"/world/model/{body}/{model.geom(g).name}"]
        assert entity.time_ns == []  # static only
        np.testing.assert_allclose(entity.static["Transform3D:translation"][0], model.geom_pos[g])
        np.testing.assert_allclose(
            entity.static["Transform3D:quaternion"][0], xyzw(model.geom_quat[g]), atol=1e-7
        )
    chest = entities["/world/model/torso/chest"].static  # fromto capsule, 0.14 long, r 0.07
    np.testing.assert_allclose(chest["Capsules3D:lengths"], [0.14], rtol=1e-6)
    np.testing.assert_allclose(chest["Capsules3D:radii"], [0.07], rtol=1e-6)
    np.testing.assert_allclose(chest["Capsules3D:translations"], [[0, 0, -0.07]], atol=1e-7)
    head = entities["/world/model/torso/head"].static
    np.testing.assert_allclose(head["Ellipsoids3D:half_sizes"], [[0.09] * 3], rtol=1e-6)
    floor = entities["/world/model/world/floor"].static  # plane → thin box, top at z = 0
    np.testing.assert_allclose(floor["Boxes3D:half_sizes"], [[10, 10, 0.005]], rtol=1e-6)
    np.testing.assert_allclose(floor["Boxes3D:centers"], [[0, 0, -0.005]], atol=1e-7)


def test_bodies_move_with_the_estimate_at_every_knot(humanoid, recording):
    model, estimate = humanoid
    _, entities = recording
    xpos, xquat = body_poses(model, estimate.qpos)
    offsets = (estimate.t_ns - estimate.t_ns[0]).tolist()
    for b in range(1, model.nbody):
        entity = entities[f"/world/model/{model.body(b).name}"]
        assert entity.time_ns == offsets
        np.testing.assert_allclose(entity.single("Transform3D:translation"), xpos[:, b], atol=1e-6)
        quat = entity.single("Transform3D:quaternion")
        np.testing.assert_allclose(quat, xquat[:, b][:, [1, 2, 3, 0]], atol=1e-6)
    assert xpos[-1, 1, 2] < xpos[0, 1, 2] - 0.3  # the torso did fall


def test_time_is_seconds_since_the_log_start_and_the_start_is_recorded(humanoid, recording):
    _, estimate = humanoid
    _, entities = recording
    torso = entities["/world/model/torso"]
    assert torso.time_ns[0] == 0 and torso.time_ns[1] == 10_000_000  # h = 10 ms exactly
    start = entities["/__properties"].static["RecordingInfo:start_time"][0]
    assert start == estimate.t_ns[0]


# -- contacts ---------------------------------------------------------------------------------
def test_contact_arrows_start_at_the_contact_point_along_the_force(humanoid, recording):
    model, estimate = humanoid
    _, entities = recording
    arrows = entities["/world/contacts"]
    offsets = (estimate.t_ns - estimate.t_ns[0]).tolist()
    assert arrows.time_ns == offsets
    scale = visualize.FORCE_SCALE_M_PER_WEIGHT / (
        model.body_subtreemass[0] * np.linalg.norm(model.opt.gravity)
    )
    counts = [len(c.contacts.pos) for c in estimate.constraints]
    assert min(counts) == 0 and max(counts) >= 8  # knots without contact, knots with many
    upward = 0
    for k, c in enumerate(estimate.constraints):
        origins = np.array(arrows.rows["Arrows3D:origins"][k]).reshape(-1, 3)
        vectors = np.array(arrows.rows["Arrows3D:vectors"][k]).reshape(-1, 3)
        colors = arrows.rows["Arrows3D:colors"][k]
        assert len(origins) == counts[k]
        for i in range(counts[k]):
            np.testing.assert_allclose(origins[i], c.contacts.pos[i], atol=1e-6)
            impulse = c.contact_impulse(i)
            f = np.zeros(3)
            f[: min(3, len(impulse))] = impulse[:3] / c.h
            force = sum(f[j] * c.contacts.frame[i][j] for j in range(3))  # rows n, t1, t2
            np.testing.assert_allclose(vectors[i], force * scale, rtol=1e-5, atol=1e-7)
            r, g, b = visualize.BRANCH_COLORS[c.contact_branch(i)]
            assert colors[i] == (r << 24) | (g << 16) | (b << 8) | 0xFF
            if 0 in c.contacts.geom[i] and f[0] > 1.0:  # against the floor: pushes up
                assert vectors[i][2] > 0
                upward += 1
    assert upward > 20
    labels = arrows.rows["Arrows3D:labels"][0]
    assert any(
        label.startswith("right_foot ") and label.endswith(" N sticking") for label in labels
    )


def test_contact_normal_force_per_body_sums_the_normal_impulses(humanoid, recording):
    model, estimate = humanoid
    _, entities = recording
    expected: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(estimate.T))
    for k, c in enumerate(estimate.constraints):
        for i in range(len(c.contacts.pos)):
            for body in {int(model.geom_bodyid[g]) for g in c.contacts.geom[i]} - {0}:
                expected[model.body(body).name][k] += c.contact_impulse(i)[0] / c.h
    assert {"left_foot", "right_foot"} <= set(expected)
    for body, force in expected.items():
        series = entities[f"/plots/contact_force/{body}"]
        np.testing.assert_allclose(np.ravel(series.rows["Scalars:scalars"]), force, rtol=1e-12)
        assert series.static["SeriesLines:names"] == [body]
    weight = model.body_subtreemass[0] * 9.81
    standing = expected["left_foot"][1] + expected["right_foot"][1]
    assert 0.5 * weight < standing < 2 * weight  # the feet carry the body at the start


def test_branch_colors_cover_what_the_inverse_produced(humanoid):
    _, estimate = humanoid
    seen = {c.contact_branch(i) for c in estimate.constraints for i in range(len(c.contacts.pos))}
    assert Branch.STICKING in seen and seen <= set(visualize.BRANCH_COLORS)


# -- time series ------------------------------------------------------------------------------
def test_time_series_hold_the_logged_arrays_without_their_nan_knots(humanoid, recording):
    model, estimate = humanoid
    _, entities = recording
    offsets = estimate.t_ns - estimate.t_ns[0]
    dofs = visualize.dof_names(model)
    assert dofs[:7] == ["root_x", "root_y", "root_z", "root_rx", "root_ry", "root_rz", "abdomen_z"]
    assert len(dofs) == model.nv == len(set(dofs))
    for j in (0, 5, 6, model.nv - 1):
        series = entities[f"/plots/physics/{dofs[j]}"]
        assert series.time_ns == offsets[1:].tolist()  # knot 0 is NaN
        np.testing.assert_array_equal(
            np.ravel(series.rows["Scalars:scalars"]), estimate.residuals["physics"][1:, j]
        )
        assert series.static["SeriesLines:names"] == [dofs[j]]
        std = entities[f"/plots/uncertainty/{dofs[j]}"]
        np.testing.assert_array_equal(
            np.ravel(std.rows["Scalars:scalars"]), estimate.qpos_std[:, j]
        )
    sensor = estimate.residuals["imu"]
    for i in range(3):
        series = entities[f"/plots/sensors/imu/{i}"]
        keep = np.isfinite(sensor[:, i])
        assert series.time_ns == offsets[keep].tolist()
        np.testing.assert_array_equal(np.ravel(series.rows["Scalars:scalars"]), sensor[keep, i])
    bias = estimate.imu_bias["imu"]
    for j, quantity in enumerate(("accel", "gyro")):
        for i, axis in enumerate("xyz"):
            series = entities[f"/plots/imu_bias/imu/{quantity}/{axis}"]
            np.testing.assert_array_equal(
                np.ravel(series.rows["Scalars:scalars"]), bias[:, 3 * j + i]
            )
            assert series.static["SeriesLines:names"] == [f"imu {quantity} {axis}"]


def test_the_blueprint_puts_the_3d_view_beside_tabs_of_plots(recording):
    path, _ = recording
    views = blueprint_views(path)
    origins = sorted(views.values())
    assert origins == sorted(
        [
            "world",
            "plots/physics",
            "plots/sensors",
            "plots/contact_force",
            "plots/imu_bias",
            "plots/imu_bias",
            "plots/uncertainty",
        ]
    )
    (name_3d,) = [name for name, origin in views.items() if origin == "world"]
    assert name_3d.startswith("humanoid (contact arrows: 1 m = body weight, 397 N")


# -- measurements from a real MCAP log --------------------------------------------------------
def test_mocap_poses_and_markers_from_an_mcap_log_appear_under_measurements(humanoid, mocap):
    _, estimate = humanoid
    truth, log, entities = mocap
    assert len(log.measurements["mocap_torso"]) == len(truth["pose"])
    t0 = int(estimate.t_ns[0])
    pose = entities["/world/measurements/mocap_torso/torso"]
    assert pose.time_ns == [t_ns - t0 for t_ns, _, _ in truth["pose"]]
    translation = pose.single("Transform3D:translation")
    np.testing.assert_allclose(translation, [p for _, p, _ in truth["pose"]], atol=1e-6)
    quat = pose.single("Transform3D:quaternion")
    np.testing.assert_allclose(quat, [xyzw(q) for _, _, q in truth["pose"]], atol=1e-7)
    np.testing.assert_allclose(pose.static["TransformAxes3D:axis_length"], [0.1], rtol=1e-6)

    markers = entities["/world/measurements/markers"]
    assert markers.time_ns == [t_ns - t0 for t_ns, _ in truth["markers"]]
    for row, (_, entries) in enumerate(truth["markers"]):
        assert markers.rows["Points3D:labels"][row] == list(MARKER_SITES.values())  # sites
        positions = [p for _, _, _, p in entries]
        np.testing.assert_allclose(markers.rows["Points3D:positions"][row], positions, atol=1e-6)
    assert entities["/world/model/torso"].time_ns[0] == 0  # the model, on the same clock


def test_markers_missing_from_a_sample_are_left_out_of_it(humanoid, mocap, tmp_path):
    """NaN marks a marker the sample did not carry (the Measurement convention)."""
    model, estimate = humanoid
    _, log, _ = mocap
    markers = log.measurements["markers"]
    values = markers.values.copy()
    values[::5, 1] = np.nan  # the head marker occluded in every 5th sample
    values[3, :] = np.nan  # no marker at all in sample 3
    occluded = replace(log, measurements={"markers": replace(markers, values=values)})
    path = visualize.write_recording(estimate, model, occluded, path=tmp_path / "occluded.rrd")
    rows = read_recording(path)["/world/measurements/markers"].rows
    for n in range(len(markers)):
        keep = [] if n == 3 else [0] if n % 5 == 0 else [0, 1]
        assert rows["Points3D:labels"][n] == [markers.elements[e] for e in keep]
        np.testing.assert_allclose(
            np.reshape(rows["Points3D:positions"][n], (-1, 3)), values[n, keep], atol=1e-6
        )


def test_a_recording_sent_in_parts_holds_what_one_sent_whole_holds(
    humanoid, mocap, tmp_path, monkeypatch
):
    """A long estimate goes to Rerun a part at a time (its buffers hold a part); the knots and
    the log's samples of every part, none twice, none lost at a part's edge."""
    model, estimate = humanoid
    _, log, whole = mocap
    monkeypatch.setattr(visualize, "RECORDING_PART_KNOTS", 7)  # (not a divisor of T)
    assert estimate.T > 3 * 7 and estimate.T % 7
    path = visualize.write_recording(estimate, model, log, path=tmp_path / "parts.rrd")
    parts = read_recording(path)
    assert parts.keys() == whole.keys()
    for name, entity in whole.items():
        assert parts[name].time_ns == entity.time_ns, name
        assert parts[name].rows == entity.rows, name
        assert parts[name].static == entity.static, name


# -- other geoms, inputs, serving -------------------------------------------------------------
SHAPES_XML = """\
<mujoco>
  <option cone="elliptic"/>
  <asset>
    <mesh name="tet" vertex="0 0 0  .1 0 0  0 .1 0  0 0 .1"/>
    <material name="red" rgba="1 0 0 1"/>
  </asset>
  <worldbody>
    <geom name="ground" type="plane" size="2 3 .1"/>
    <geom name="post" type="box" size=".1 .1 .5" pos="1 0 .5"/>
    <geom name="hidden" type="box" size=".1 .1 .1" group="3"/>
    <body name="shelf" pos="0 1 .2">
      <geom name="board" type="box" size=".3 .1 .01"/>
    </body>
    <body name="thing" pos="0 0 1">
      <freejoint/>
      <geom name="ball" type="sphere" size=".1"/>
      <geom name="egg" type="ellipsoid" size=".1 .2 .3" pos=".3 0 0"/>
      <geom name="can" type="cylinder" size=".05 .2" pos="0 .3 0" material="red"/>
      <geom name="tet" type="mesh" mesh="tet" pos="0 0 .3"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_every_primitive_geom_type_becomes_a_rerun_shape(tmp_path):
    model = mujoco.MjModel.from_xml_string(SHAPES_XML)
    estimate = simulate_estimate(model, 0.05)
    path = visualize.write_recording(estimate, model, path=tmp_path / "shapes.rrd")
    assert path is not None
    entities = read_recording(path)
    ground = entities["/world/model/world/ground"].static
    np.testing.assert_allclose(ground["Boxes3D:half_sizes"], [[2, 3, 0.005]], rtol=1e-6)
    post = entities["/world/model/world/post"].static
    np.testing.assert_allclose(post["Boxes3D:half_sizes"], [[0.1, 0.1, 0.5]], rtol=1e-6)
    np.testing.assert_allclose(post["Transform3D:translation"], [[1, 0, 0.5]])
    assert "/world/model/world/hidden" not in entities  # group 3: collision only
    egg = entities["/world/model/thing/egg"].static
    np.testing.assert_allclose(egg["Ellipsoids3D:half_sizes"], [[0.1, 0.2, 0.3]], rtol=1e-6)
    can = entities["/world/model/thing/can"].static
    np.testing.assert_allclose(can["Cylinders3D:lengths"], [0.4], rtol=1e-6)
    assert can["Cylinders3D:colors"] == [0xFF0000FF]  # the material's red
    tet = entities["/world/model/thing/tet"].static
    vertices = np.array(tet["Mesh3D:vertex_positions"])
    faces = np.array(tet["Mesh3D:triangle_indices"])
    assert vertices.shape == (4, 3) and faces.shape == (4, 3)
    assert len(entities["/world/model/thing"].time_ns) == estimate.T
    shelf = entities["/world/model/shelf"]  # welded to the world: one static pose
    assert shelf.time_ns == []
    np.testing.assert_allclose(shelf.static["Transform3D:translation"], [[0, 1, 0.2]])


def test_the_timestep_of_the_time_column_is_exact_for_long_logs(humanoid, tmp_path):
    """Knots 1e9 s after the epoch keep their int-ns spacing (no float seconds on the way)."""
    model, estimate = humanoid
    late = Estimate(**{**estimate.__dict__, "t_ns": estimate.t_ns + 3_000_000_000_123})
    entities = read_recording(visualize.write_recording(late, model, path=tmp_path / "a.rrd"))
    assert entities["/world/model/torso"].time_ns == (estimate.t_ns - estimate.t_ns[0]).tolist()


def test_bad_inputs_are_rejected_with_a_message(humanoid, tmp_path):
    model, estimate = humanoid
    with pytest.raises(ValueError, match="give a path, spawn=True or serve=True"):
        visualize.write_recording(estimate, model)
    with pytest.raises(ValueError, match=r"estimate.qpos has shape \(100, 28\), expected"):
        visualize.write_recording(estimate, load_model("quadruped"), path=tmp_path / "x.rrd")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_serve_starts_a_grpc_server_and_a_web_viewer_on_localhost_and_stops(
    humanoid, tmp_path, capsys
):
    """The web viewer's HTTP server stays up until the test process exits (Rerun 0.41 has no
    call to stop it); the gRPC server that holds the data stops with stop_serving()."""
    model, estimate = humanoid
    grpc_port, web_port = _free_port(), _free_port()
    path = visualize.write_recording(
        estimate,
        model,
        path=tmp_path / "served.rrd",
        serve=True,
        grpc_port=grpc_port,
        web_port=web_port,
    )
    try:
        assert path is not None and path.is_file()
        assert _listening(grpc_port)
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=5) as page:
            assert page.status == 200 and b"<html" in page.read(4096).lower()
        out = capsys.readouterr().out
        uri = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        assert visualize.web_viewer_url(uri, "127.0.0.1", web_port) in out
    finally:
        visualize.stop_serving()
    # the server shuts down on its own thread once disconnected: within 10 s, even on a busy
    # machine (a full `make test` once saw it still listening right after stop_serving())
    deadline = time.monotonic() + 10.0
    while _listening(grpc_port) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _listening(grpc_port)
    assert "/world/contacts" in read_recording(path)  # the file is complete too


def test_spawn_without_a_display_says_so_instead_of_waiting(humanoid, monkeypatch):
    model, estimate = humanoid
    monkeypatch.setattr(visualize.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(visualize.ViewerError, match="--spawn needs a display"):
        visualize.write_recording(estimate, model, spawn=True)


def test_serve_on_a_taken_port_names_the_port(humanoid):
    model, estimate = humanoid
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(visualize.ViewerError, match=f"cannot serve on 127.0.0.1:{port}"):
            visualize.write_recording(estimate, model, serve=True, grpc_port=port)

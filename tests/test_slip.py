"""Slips: a low-friction patch under a foot in the simulated world (its truth, the slide it
measured) and the slip detector on the estimate of its log (found on the foot, sized, the
physics residual it leaves explained by it, and the model's own slides left alone), in
batch and online."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from diagnosed import diagnosed, streamed

from estimator.config import load_config
from estimator.diagnose import Event
from estimator.diagnose.diagnosis import on_slips
from estimator.diagnose.report import KINDS, event_dict, event_message, message
from estimator.diagnose.score import true_events
from estimator.diagnose.slip import SLIP, STICKING, slides
from estimator.io.logs import read_log
from estimator.io.rerun import write_recording
from estimator.simulate import simulate
from estimator.simulate.model_scenario import model_scenario
from estimator.simulate.patch import Patch, feet
from estimator.simulate.simulation import T0_NS, scenario_config
from physics.model import load_model, weight

ROOT = Path(__file__).resolve().parents[1]
GO2 = ROOT / "physics" / "models" / "menagerie" / "go2.xml"


def _go2_on_a_patch(friction: float, start_s: float = 1.0):
    """Go2 standing; its rear right foot's friction `friction` for 0.6 s from `start_s`."""
    go2 = model_scenario(GO2)
    geoms = dict(feet(load_model(GO2), go2.keyframe))["RR_calf"]
    patch = Patch("RR_calf", start_s, 0.6, (0.0, 0.0, 0.0), geoms, friction)
    return replace(go2, pushes=lambda rng, duration: (patch,), condition="disturbances")


def test_a_foot_on_a_low_friction_patch_slides_and_the_truth_is_the_slide(tmp_path):
    """Go2 standing, its rear right foot's friction 0.02 for 0.6 s from 1.0 s: the truth is a
    slip of that foot within the patch, centimetres long; the same patch with the foot's own
    friction is no slip; the simulated model is left as it was."""
    model = load_model(GO2)
    assert [b for b, _ in feet(model, "home")] == ["FL_calf", "FR_calf", "RL_calf", "RR_calf"]
    result = simulate(_go2_on_a_patch(0.02), tmp_path / "s.mcap", seed=0, duration_s=2.0)
    (slip,) = [e for e in true_events(tmp_path / "s.mcap") if e["kind"] == "slip"]
    assert slip["body"] == "RR_calf" and slip["friction"] == 0.02
    assert 1.0 <= slip["start_s"] < slip["end_s"] <= 1.6 + 1e-6
    assert 0.01 < slip["distance_m"] < 0.5
    simulated, geoms = result.trajectory.model, list(dict(feet(model, "home"))["RR_calf"])
    assert (simulated.geom_friction[geoms, 0] > 0.1).all()  # restored
    front = list(dict(feet(model, "home"))["FL_calf"])
    np.testing.assert_array_equal(simulated.geom_priority[geoms], simulated.geom_priority[front])
    own = float(model.geom_friction[dict(feet(model, "home"))["RR_calf"][0], 0])
    simulate(_go2_on_a_patch(own), tmp_path / "n.mcap", seed=0, duration_s=2.0)
    assert not [e for e in true_events(tmp_path / "n.mcap") if e["kind"] == "slip"]


def test_a_slip_is_found_on_its_foot_sized_and_explains_the_residual_there(tmp_path):
    """Estimated and diagnosed with the defaults, the slip is the one slip event: on the
    rear right foot, over the truth's interval, its distance within 30% of the truth's;
    what the physics residual shows on that foot meanwhile is explained by it; the other
    feet, which slide a little with the model's own friction, are no slip; events.json and
    /diagnostics/events carry it; Rerun draws the foot's path over it."""
    config, log, _, est, diagnosis = diagnosed(_go2_on_a_patch(0.02), tmp_path, 2.5)
    (truth,) = [e for e in true_events(log) if e["kind"] == "slip"]
    (e,) = [e for e in diagnosis.events if e.kind == SLIP]
    assert e.target == "RR_calf" and e.component == "contact RR_calf–world"
    start, end = (e.start_ns - T0_NS) / 1e9, (e.end_ns - T0_NS) / 1e9
    assert start < truth["end_s"] and end > truth["start_s"]
    assert abs(start - truth["start_s"]) < 0.15 and abs(end - truth["end_s"]) < 0.15
    assert e.force[0] == pytest.approx(truth["distance_m"], rel=0.3)
    on_foot = [x for x in diagnosis.events if x is not e and "RR_calf" in x.target]
    assert all(x.explained_by == "slip RR_calf" for x in on_foot)
    # on the patch the motion asks for a fraction of the model's friction (0.8 μ_model)
    model = config.load_model()
    found = slides(model, est, weight(model))
    rr = found.pairs.index((model.body("RR_calf").id, 0))
    during = found.touching[:, rr] & (est.t_ns >= e.start_ns) & (est.t_ns <= e.end_ns)
    assert found.friction[during, rr].mean() < STICKING and found.sliding[during, rr].mean() > 0.5
    written = event_dict(e, T0_NS)
    assert written["slid_m"] == pytest.approx(e.force[0]) and written["component"] == e.component
    assert event_message(e)["kind"] == KINDS[SLIP] == 3
    assert message(e).startswith("contact RR_calf–world slid ")
    json.dumps(written)
    # Rerun: the foot's path over the slip, from its start, cleared at its end
    from test_visualize import read_recording

    read = read_log(log, config)
    drawn = write_recording(est, model, read, path=tmp_path / "d.rrd", diagnosis=diagnosis)
    path = read_recording(drawn)["/world/diagnostics/slip/RR_calf"]
    t0 = min(int(est.t_ns[0]), *(int(m.t_ns[0]) for m in read.measurements.values()))
    assert path.time_ns == [e.start_ns - t0, e.end_ns - t0]
    (strip,) = path.rows["LineStrips3D:strips"][0]
    data = mujoco.MjData(model)
    data.qpos[:] = est.qpos[np.searchsorted(est.t_ns, e.end_ns)]
    mujoco.mj_kinematics(model, data)
    np.testing.assert_allclose(strip[-1], data.xpos[model.body("RR_calf").id], atol=1e-6)
    assert path.rows["LineStrips3D:labels"] == [[f"slip {100 * e.force[0]:.1f} cm"], []]
    assert path.rows["LineStrips3D:strips"][1] == []  # gone at the slip's end


def test_the_stream_reports_a_slip_online_while_it_lasts_and_again_when_it_ends(tmp_path):
    """The patch after the online detectors' calibration (from 2.5 s), the log through
    `Stream(diagnose=...)` with the node's settings: the slip is reported on the rear right
    foot while it lasts, within 0.3 s of its start, then final, over the truth's interval
    to 0.15 s; no other slip."""
    log, config_path = tmp_path / "s.mcap", tmp_path / "s.toml"
    scenario = _go2_on_a_patch(0.02, start_s=2.5)
    simulate(scenario, log, seed=0, duration_s=3.6)
    config_path.write_text(scenario_config(scenario, config_path))
    config = load_config(config_path)
    _, events = streamed(config, log, min_knots=25)
    (truth,) = [e for e in true_events(log) if e["kind"] == "slip"]
    start_ns = T0_NS + round(truth["start_s"] * 1e9)
    slid = [e for e in events if e.kind == SLIP]
    assert [e.ongoing for e in slid] == [True, False]
    first, final = slid
    assert first.target == final.target == "RR_calf"
    assert 0 <= first.detected_ns - start_ns <= 0.3e9
    assert abs(final.start_ns - start_ns) <= 0.15e9
    assert abs(final.end_ns - T0_NS - truth["end_s"] * 1e9) <= 0.15e9


def test_a_slip_explains_what_the_residual_shows_on_its_body_and_the_next_across_a_joint():
    """Go2: a slip of RR_calf explains an unmodeled contact on RR_calf or RR_thigh (its
    parent) that overlaps it, not one on FL_calf, nor one on RR_thigh after it."""
    model = load_model(GO2)

    def event(kind: str, target: str, start_s: float, end_s: float) -> Event:
        ns = round(start_s * 1e9), round(end_s * 1e9)
        return Event(kind, *ns, ns[0], target, np.zeros(3), np.eye(3), 2.0)

    slip = event(SLIP, "RR_calf", 1.0, 1.5)
    contacts = [
        event("unmodeled contact", "RR_thigh", 1.2, 1.3),
        event("model error", "contact RR_calf–floor", 1.4, 1.6),
        event("unmodeled contact", "FL_calf", 1.2, 1.3),
        event("unmodeled contact", "RR_thigh", 1.6, 1.7),
    ]
    marked = [e.explained_by for e in on_slips(model, contacts, [slip])]
    assert marked == ["slip RR_calf", "slip RR_calf", "", ""]

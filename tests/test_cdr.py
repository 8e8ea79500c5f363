"""The planned CDR encoders (`estimator.io.cdr`) write mcap_ros2's bytes for every message
physfuse writes: the simulator's sensors and ground truth, and an estimate's topics."""

from __future__ import annotations

import io

import numpy as np
import pytest
from mcap_ros2._dynamic import serialize_dynamic

from estimator.io import cdr, mcap_writer
from estimator.io.logs import ros2_types
from estimator.io.mcap_writer import imu_bias_message
from estimator.simulate import simulate


def reference(msg_type: str):
    return serialize_dynamic(msg_type, ros2_types.message_definition(msg_type))[msg_type]


@pytest.mark.parametrize("scenario", ["humanoid_push", "quadruped_trot", "arm_box"])
def test_every_message_of_a_recording_encodes_as_mcap_ros2_does(scenario, monkeypatch):
    written: list[tuple[str, dict]] = []
    original = mcap_writer.Message.encoded  # the simulator encodes each message as it makes it

    def capture(self):
        written.append((self.msg_type, self.fields))
        return original(self)

    monkeypatch.setattr(mcap_writer.Message, "encoded", capture)
    simulate(scenario, io.BytesIO(), duration_s=0.05)
    types = {t for t, _ in written}
    # (ground truth's contacts: nested sequences; arm_box has no IMU, the legged robots no F/T)
    assert {ros2_types.JOINT_STATE, mcap_writer.ODOMETRY, ros2_types.CONTACT_ARRAY} <= types
    for msg_type, fields in written:
        assert cdr.encoder(msg_type)(fields) == reference(msg_type)(fields), msg_type


def test_defaults_empty_sequences_and_odd_alignments():
    bias = imu_bias_message("/estimate", "imu", 12_345, "imu_site", np.arange(6.0))
    for msg_type, fields in [
        (bias.msg_type, bias.fields),
        (ros2_types.JOINT_STATE, {"header": {"frame_id": "x"}, "name": ["a", "bc"]}),
        (ros2_types.JOINT_STATE, {"name": [], "position": [], "velocity": [1.0], "effort": []}),
        (ros2_types.CONTACT_ARRAY, {"timestep": 0.002, "contacts": []}),
        (
            ros2_types.DIAGNOSTIC_EVENT,
            {
                "kind": 2,
                "end": {"sec": 3, "nanosec": 7},
                "target": "imu",
                "size": [1.5],
                "size_covariance": [0.25],
                "candidates": ["imu", "torso"],
                "candidate_likelihood_ratios": [9.0, 1.0],
                "point": [0.1, -0.2, 0.3],
            },
        ),
        (
            ros2_types.TF_MESSAGE,
            {"transforms": [{"child_frame_id": "torso", "transform": {"rotation": {"w": 1.0}}}]},
        ),
        (
            ros2_types.CONTACT_ARRAY,
            {
                "contacts": [
                    {"body1": "a", "dim": 3, "impulse": [1.0] * 6, "force": [2.0] * 6},
                    {"geom2": "floor!", "branch": 4, "impulse": [0.0] * 6, "force": [0.0] * 6},
                ]
            },
        ),
    ]:
        assert cdr.encoder(msg_type)(fields) == reference(msg_type)(fields), msg_type
    with pytest.raises(ValueError, match="expected 6 values"):
        cdr.encoder(ros2_types.CONTACT_ARRAY)({"contacts": [{"impulse": [1.0]}]})

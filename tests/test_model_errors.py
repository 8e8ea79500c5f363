"""A body's mass off: a payload the model does not have found on its body and weighed; the
simulated 5% mass errors, below what the residual can tell, not reported."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np
from diagnosed import diagnosed

from estimator.diagnose.report import event_dict, message
from estimator.simulate.mismatch import Mismatch, MismatchRecord
from estimator.simulate.model_scenario import model_scenario

ROOT = Path(__file__).resolve().parents[1]
PANDA = ROOT / "physics" / "models" / "menagerie" / "panda_box.xml"
KNOTS = "h = 0.002"  # 2 ms knots (the model steps at 0.5 ms)


@dataclass(frozen=True)
class Payload(Mismatch):
    """The simulated robot is the model with `kg` more on `body` (its inertia scaled)."""

    body: str = "hand"
    kg: float = 0.5

    def apply(self, model, rng, softness=None, *, own_softness=False):
        true, true_softness, _ = Mismatch.none().apply(
            model, rng, softness, own_softness=own_softness
        )
        b = model.body(self.body).id
        scale = (model.body_mass[b] + self.kg) / model.body_mass[b]
        true.body_mass[b] *= scale
        true.body_inertia[b] *= scale
        mujoco.mj_setConst(true, mujoco.MjData(true))
        record = MismatchRecord({self.body: (float(model.body_mass[b]), float(true.body_mass[b]))})
        return true, true_softness, record


def test_a_payload_in_the_hand_is_the_hand_s_mass_off_by_its_weight(tmp_path):
    """Panda (excited by 0.2 rad) with 0.5 kg in its hand that the model lacks, 3 s: one mass
    error, on the hand, +0.5 kg within 2σ (σ < 0.1 kg); the bodies next to it on the chain
    explain the residual almost as well and are its candidates."""
    panda = replace(model_scenario(PANDA, excitation_rad=0.2), mismatch=Payload())
    _, _, _, _, diagnosis = diagnosed(panda, tmp_path, 3.0, estimator=KNOTS)
    (e,) = [e for e in diagnosis.events if e.component == "mass"]
    sigma = float(np.sqrt(e.force_cov[0, 0]))
    assert e.target == "hand" and abs(e.force[0] - 0.5) < 2.0 * sigma < 0.2, (e.force, sigma)
    assert {"link7", "link6"} <= set(e.candidates)
    assert min(e.candidates[b] for b in ("link7", "link6")) > 0.95 * e.candidates["hand"]
    written = event_dict(e, 0)
    assert written["mass_error_kg"] == e.force[0] and "hand" in written["candidates"]
    assert message(e).startswith("hand: the model's mass is off by +0.")


def test_the_simulated_five_percent_mass_errors_are_not_reported(tmp_path):
    """The same arm with the default mismatch (every body's mass off by 5% RMS: up to 0.16 kg),
    no payload: no mass error."""
    panda = model_scenario(PANDA, excitation_rad=0.2)
    _, _, _, _, diagnosis = diagnosed(panda, tmp_path, 3.0, estimator=KNOTS)
    assert not [e for e in diagnosis.events if e.component == "mass"]

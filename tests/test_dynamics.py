"""The reference path (the paper in numpy) against the native path (MuJoCo's C engine)."""

import mujoco
import numpy as np
import pytest
from physics_states import random_states

from physics.cone import Branch
from physics.constraints import constraint_space
from physics.dynamics import make_dynamics
from physics.errors import InvalidStateError, UnsupportedModelError
from physics.model import bundled_models, load_model
from physics.softness import Softness

MODELS = bundled_models()


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    scale = max(float(np.max(np.abs(b))) if b.size else 0.0, 1e-300)
    return float(np.max(np.abs(a - b))) / scale if a.size else 0.0


def test_every_model_is_bundled() -> None:
    assert {"single_joint", "humanoid", "all_constraints"} <= set(MODELS)


@pytest.mark.parametrize("name", MODELS)
def test_reference_inverse_matches_native(name: str) -> None:
    rng = np.random.default_rng(1)
    native = reference = None
    types_seen: set[int] = set()
    for m, qpos, qvel, _ in random_states(name, 30, seed=2):
        if native is None:
            native, reference = make_dynamics(m, "native"), make_dynamics(m, "reference")
        qacc = rng.normal(0.0, 5.0, m.nv)
        a = native.inverse(qpos, qvel, qacc)
        b = reference.inverse(qpos, qvel, qacc)
        assert rel_err(b.qfrc_inverse, a.qfrc_inverse) < 1e-9
        assert rel_err(b.constraints.efc_impulse, a.constraints.efc_impulse) < 1e-9
        np.testing.assert_array_equal(b.constraints.efc_type, a.constraints.efc_type)
        np.testing.assert_array_equal(b.constraints.efc_state, a.constraints.efc_state)
        types_seen |= set(a.constraints.efc_type.tolist())
    assert types_seen, f"{name}: no constraint was active in any sampled state"


def test_all_constraint_types_are_exercised() -> None:
    m = load_model("all_constraints")
    types, dims = set(), set()
    native = make_dynamics(m, "native")
    for _, qpos, qvel, _ in random_states("all_constraints", 10, seed=3):
        inv = native.inverse(qpos, qvel, np.zeros(m.nv))
        types |= set(inv.constraints.efc_type.tolist())
        dims |= set(inv.constraints.contacts.dim.tolist())
    T = mujoco.mjtConstraint
    expected = {
        T.mjCNSTR_EQUALITY,
        T.mjCNSTR_FRICTION_DOF,
        T.mjCNSTR_LIMIT_JOINT,
        T.mjCNSTR_LIMIT_TENDON,
        T.mjCNSTR_CONTACT_FRICTIONLESS,
        T.mjCNSTR_CONTACT_ELLIPTIC,
    }
    assert {int(t) for t in expected} <= types
    assert {1, 3, 4, 6} <= dims


@pytest.mark.parametrize("name", MODELS)
def test_reference_forward_matches_native_once_converged(name: str) -> None:
    native = reference = None
    for m, qpos, qvel, ctrl in random_states(name, 4, seed=4, steps_between=25):
        if native is None:
            native, reference = make_dynamics(m, "native"), make_dynamics(m, "reference")
            native.set_solver("newton", iterations=200, tolerance=1e-15)
        a = native.forward(qpos, qvel, ctrl)
        a = native.forward(qpos, qvel, ctrl, warmstart=a.qacc)  # Newton can stop early once
        b = reference.forward(qpos, qvel, ctrl, iterations=20_000, tolerance=1e-12)
        assert b.converged
        assert rel_err(b.qacc, a.qacc) < 1e-8
        assert rel_err(b.constraints.efc_impulse, a.constraints.efc_impulse) < 1e-8


@pytest.mark.parametrize("path", ["native", "reference"])
@pytest.mark.parametrize("name", MODELS)
def test_inverse_of_forward_recovers_the_control(name: str, path: str) -> None:
    dyn = None
    rng = np.random.default_rng(5)
    for m, qpos, qvel, ctrl in random_states(name, 3, seed=6, steps_between=25):
        if dyn is None:
            dyn = make_dynamics(m, path)
            if path == "native":
                dyn.set_solver("newton", iterations=200, tolerance=1e-15)
        qfrc_applied = rng.normal(0.0, 1.0, m.nv)
        if path == "native":
            fwd = dyn.forward(qpos, qvel, ctrl, qfrc_applied)
            fwd = dyn.forward(qpos, qvel, ctrl, qfrc_applied, warmstart=fwd.qacc)
        else:
            fwd = dyn.forward(qpos, qvel, ctrl, qfrc_applied, iterations=20_000, tolerance=1e-12)
        u = dyn.data.qfrc_actuator + qfrc_applied  # u of eq. 12: every non-passive force
        inv = dyn.inverse(qpos, qvel, fwd.qacc)
        scale = max(float(np.max(np.abs(u))), 1.0)
        assert np.max(np.abs(inv.qfrc_inverse - u)) / scale < 1e-7
        assert rel_err(inv.constraints.efc_impulse, fwd.constraints.efc_impulse) < 1e-7


@pytest.mark.parametrize("name", MODELS)
def test_regularizer_and_reference_velocity_match_mujoco(name: str) -> None:
    """Eq. 27-28 and 22 from our Softness give MuJoCo's efc_R and J v + h·efc_aref."""
    native = None
    for m, qpos, qvel, ctrl in random_states(name, 10, seed=7):
        if native is None:
            native = make_dynamics(m, "native", Softness(eps=0.08, kappa=0.03, impratio=3.0))
        native.forward(qpos, qvel, ctrl)
        mm, d = native.model, native.data
        space = constraint_space(mm, d, native.softness)
        if not space.nefc:
            continue
        np.testing.assert_allclose(space.R, d.efc_R[: d.nefc], rtol=1e-12)
        vstar_mujoco = space.J @ d.qvel + mm.opt.timestep * d.efc_aref[: d.nefc]
        np.testing.assert_allclose(space.vstar, vstar_mujoco, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(d.efc_KBIP[: d.nefc, 1], native.softness.B, rtol=1e-12)


def test_softness_maps_to_and_from_mujoco() -> None:
    s = Softness(eps=0.1, kappa=0.05, impratio=2.0)
    assert s.d == pytest.approx(1 / 1.1)
    again = Softness.from_mujoco(s.solref(), s.solimp(), impratio=2.0)
    assert again.eps == pytest.approx(s.eps) and again.kappa == s.kappa
    # B and K·d of MuJoCo (mj_makeImpedance) equal eq. 28's B and K
    assert 2 / (s.d * s.kappa) == pytest.approx(s.B)
    assert s.d / (s.d**2 * s.kappa**2) == pytest.approx(s.K)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"eps": 0.0}, "eps=0.0 is outside"),
        ({"eps": 1e5}, "eps=100000.0 is outside"),
        ({"kappa": -1.0}, "kappa=-1.0 must be finite"),
        ({"impratio": float("nan")}, "impratio=nan must be finite"),
    ],
)
def test_bad_softness_is_rejected(kwargs: dict, message: str) -> None:
    with pytest.raises(UnsupportedModelError, match=message):
        Softness(**kwargs)


def test_kappa_below_two_timesteps_is_rejected() -> None:
    m = load_model("humanoid")  # h = 0.01
    with pytest.raises(UnsupportedModelError, match="below 2\\*timestep"):
        make_dynamics(m, "native", Softness(kappa=0.015))


def test_solref_without_paper_meaning_is_rejected() -> None:
    with pytest.raises(UnsupportedModelError, match="expected \\(kappa > 0, 1\\)"):
        Softness.from_mujoco([0.02, 0.5], [0.9, 0.9, 0.001, 0.5, 2])
    with pytest.raises(UnsupportedModelError, match="flat impedance"):
        Softness.from_mujoco([0.02, 1.0], [0.9, 0.95, 0.001, 0.5, 2])


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: setattr(m.opt, "cone", mujoco.mjtCone.mjCONE_PYRAMIDAL), "pyramidal"),
        (lambda m: setattr(m.opt, "integrator", mujoco.mjtIntegrator.mjINT_RK4), "rk4"),
        (lambda m: setattr(m.opt, "noslip_iterations", 3), "noslip_iterations=3"),
    ],
)
@pytest.mark.parametrize("path", ["native", "reference"])
def test_unsupported_model_options_are_rejected(edit, message: str, path: str) -> None:
    m = load_model("single_joint")
    edit(m)
    with pytest.raises(UnsupportedModelError, match=message):
        make_dynamics(m, path)


def test_reference_path_rejects_implicit_damping() -> None:
    m = load_model("single_joint")
    m.dof_damping[0] = 0.5
    with pytest.raises(UnsupportedModelError, match=r"has damping 0\.5"):
        make_dynamics(m, "reference")
    make_dynamics(m, "native")  # mj_inverse's discrete-time mode handles it


def test_native_path_rejects_another_r_min() -> None:
    with pytest.raises(UnsupportedModelError, match=r"r_min=0\.001"):
        make_dynamics(load_model("single_joint"), "native", Softness(r_min=1e-3))


def test_unknown_path_is_rejected() -> None:
    with pytest.raises(UnsupportedModelError, match="path='fast'"):
        make_dynamics(load_model("single_joint"), "fast")  # type: ignore[arg-type]


@pytest.mark.parametrize("path", ["native", "reference"])
def test_bad_states_raise_clear_errors(path: str) -> None:
    m = load_model("humanoid")
    dyn = make_dynamics(m, path)
    qpos, qvel = m.qpos0.copy(), np.zeros(m.nv)
    bad = qvel.copy()
    bad[4] = np.nan
    with pytest.raises(InvalidStateError, match="qacc\\[4\\] is nan"):
        dyn.inverse(qpos, qvel, bad)
    with pytest.raises(InvalidStateError, match="qvel has shape \\(3,\\), expected \\(27,\\)"):
        dyn.forward(qpos, np.zeros(3))
    inf = qpos.copy()
    inf[0] = np.inf
    with pytest.raises(InvalidStateError, match="qpos\\[0\\] is inf"):
        dyn.inverse(inf, qvel, qvel)


def test_contacts_report_frame_branch_and_owner() -> None:
    """Humanoid standing at rest: its feet stick, nothing slides, owners name the geoms."""
    m = load_model("humanoid")
    native = make_dynamics(m, "native")
    for _, qpos, _qvel, _ in random_states("humanoid", 1, seed=0, steps_between=1):
        inv = native.inverse(qpos, np.zeros(m.nv), np.zeros(m.nv))
        c = inv.constraints
        assert len(c.contacts.pos) > 0
        for i in range(len(c.contacts.pos)):
            f = c.contact_impulse(i)
            branch = c.contact_branch(i)
            if branch == Branch.STICKING:
                assert f[0] > 0
            frame = c.contacts.frame[i]
            np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-9)
        owners = [c.owner(native.model, r) for r in range(len(c.efc_impulse))]
        assert any(o.startswith("contact '") for o in owners)

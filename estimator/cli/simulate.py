"""`physfuse simulate SCENARIO --out LOG.mcap [--seed N]`: a realistic robot log with ground truth.
`physfuse simulate --model MODEL.xml --out LOG.mcap [...]`: the same for any MJCF model with a
keyframe (estimator/simulate/model_scenario.py, docs/simulate_model.md).

Runs a bundled model under a controller (with a seeded model mismatch) and writes the MCAP
a real robot could have produced — rosbag2 layout: profile `ros2`, `ros2msg` schemas, `cdr`
messages, QoS metadata — with imperfect sensor topics and the true state under
`/ground_truth/...` (see estimator/io/mcap_writer.py for the layout). `--config-out` writes
the config that maps the sensor topics onto the model. `--condition` simulates the scenario
under one of the conditions of estimator/simulate/conditions.py (nominal, occlusion, outliers,
mismatch, no_commands). The same seed gives the same file.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from dataclasses import replace
from pathlib import Path

import mujoco

from estimator.io.outputs import OutputFile
from estimator.simulate import SCENARIOS, SimulationError, scenario_config, simulate
from estimator.simulate.conditions import CONDITIONS, with_condition
from estimator.simulate.controllers import short_of_holding, unstable_under_euler
from estimator.simulate.disturbances import FALLEN, fall_time
from estimator.simulate.model_scenario import EXCITATION_RAD, model_scenario
from estimator.simulate.scenarios import Scenario, get_scenario
from estimator.simulate.sensors import FootContacts, Trajectory
from physics.model import load_model

# the options of --model, by argparse dest
MODEL_OPTIONS = {
    "keyframe": "--keyframe",
    "mocap": "--mocap",
    "markers": "--markers",
    "imu": "--imu",
    "pushes": "--pushes",
    "excitation": "--excitation",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scenario", nargs="?", metavar="SCENARIO", help=f"one of: {', '.join(SCENARIOS)}"
    )
    model = parser.add_argument_group("any MJCF model with a keyframe (instead of SCENARIO)")
    model.add_argument(
        "--model", type=Path, metavar="MODEL.xml", help="simulate this model holding a keyframe"
    )
    model.add_argument("--keyframe", metavar="NAME", help="the keyframe (default: the first)")
    model.add_argument(
        "--mocap",
        nargs="+",
        metavar="BODY_OR_SITE",
        help="mocap poses of these (default: every free-joint body, at its *_marker site)",
    )
    model.add_argument(
        "--markers", nargs="+", default=(), metavar="SITE", help="mocap markers at these sites"
    )
    model.add_argument("--imu", metavar="SITE", help="IMU site (default: site 'imu' if any)")
    model.add_argument("--pushes", metavar="BODY", help="push this body at random")
    model.add_argument(
        "--excitation",
        type=float,
        metavar="AMPLITUDE",
        help=f"amplitude of the random joint targets [rad] (default {EXCITATION_RAD})",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="LOG.mcap", help="output log")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--duration", type=float, metavar="S", help="simulated seconds (default: the scenario's)"
    )
    parser.add_argument(
        "--config-out",
        type=Path,
        metavar="CONFIG.toml",
        help="also write the config mapping the log's sensor topics onto the model",
    )
    parser.add_argument(
        "--ground-truth-every",
        type=int,
        metavar="N",
        help="write ground truth every N simulation steps (default: every step)",
    )
    parser.add_argument(
        "--no-mismatch", action="store_true", help="simulate the nominal model exactly"
    )
    parser.add_argument(
        "--condition",
        metavar="NAME",
        help=(  # argparse formats help with %: escape the percentages
            "simulate under a condition: "
            + "; ".join(f"{name}: {text}" for name, text in CONDITIONS.items())
            + " (default: the scenario as its sample recording)"
        ).replace("%", "%%"),
    )
    parser.add_argument(
        "--contact-flags",
        nargs="+",
        metavar="BODY",
        help="also log binary foot-contact flags of these bodies (std_msgs/Float64MultiArray on "
        "/foot_contacts: 1 where the body's contact normal force exceeds 5 N), and map them in "
        "--config-out as a contact_flags stream",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars or summary")


def run(args: argparse.Namespace) -> int:
    scenario = _scenario(args)
    if args.condition is not None:
        if args.condition == "mismatch" and args.no_mismatch:
            raise SimulationError("--condition mismatch contradicts --no-mismatch")
        scenario = with_condition(scenario, args.condition)
    if args.ground_truth_every is not None:
        if args.ground_truth_every < 1:
            raise SimulationError(
                f"--ground-truth-every {args.ground_truth_every}: expected a step count >= 1"
            )
        scenario = replace(scenario, ground_truth_decimation=args.ground_truth_every)
    if args.contact_flags:
        model = load_model(scenario.model)
        for body in args.contact_flags:
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body) <= 0:
                raise SimulationError(
                    f"--contact-flags {body}: {scenario.model} has no (moving) body {body!r}"
                )
        flags = FootContacts(tuple(args.contact_flags))
        scenario = replace(scenario, sensors=(*scenario.sensors, flags))
    if args.duration is not None and not args.duration > 0:
        raise SimulationError(f"--duration {args.duration}: expected a positive number of seconds")
    # checked before simulating; each file put in place only once complete
    with contextlib.ExitStack() as outputs:
        log = outputs.enter_context(OutputFile(args.out, create_folder=False))
        config_out = None
        if args.config_out is not None:
            new_config = OutputFile(args.config_out, "--config-out", create_folder=False)
            config_out = outputs.enter_context(new_config)
        result = simulate(
            scenario,
            log,
            seed=args.seed,
            duration_s=args.duration,
            mismatch=not args.no_mismatch,
            progress=not args.quiet and sys.stderr.isatty(),
        )
        if config_out is not None:  # model paths relative to where it goes, not to `config_out`
            config_out.write_text(scenario_config(scenario, args.config_out), encoding="utf-8")
    if not args.quiet:
        size = args.out.stat().st_size / 1e6
        print(
            f"{args.out}: {scenario.name}, seed {args.seed}, {result.duration_s:g} s simulated, "
            f"{result.message_count} messages on {len(result.topics)} topics, {size:.2f} MB"
        )
        if args.config_out is not None:
            print(f"{args.config_out}: config for its sensor topics")
    if args.model is not None:
        for warning in _hold_warnings(scenario, result.trajectory):
            print(f"physfuse simulate: warning: {warning}", file=sys.stderr)
    return 0


def _hold_warnings(scenario: Scenario, trajectory: Trajectory) -> list[str]:
    """What a user of --model should know about the keyframe hold: servos too stiff for the
    Euler step (`unstable_under_euler`), actuators that cannot give the force that holds it
    (`short_of_holding`), and a fall (the free body below `FALLEN` of
    its starting height): the log records it."""
    model = load_model(scenario.model)
    key = scenario.keyframe
    if isinstance(key, str):
        key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key)
    out = []
    unstable = unstable_under_euler(model, key)
    if unstable:
        h, worst = model.opt.timestep, max(unstable.values())
        out.append(
            f"the Euler step at timestep {h:g} s cannot integrate the servo feedback of "
            f"{', '.join(unstable)} (h kv/m or h √(kp/m) up to {worst:.2g}, stable below 2): a "
            f'<option timestep="{h * 2.0 / worst:.2g}"/> or smaller would (the analytic '
            "inverse needs the Euler step, not the implicit integrators such servos are "
            "written for)"
        )
    short = short_of_holding(model, key)
    if short:
        out.append(
            f"keyframe {scenario.keyframe!r} takes more than the model's actuators give "
            f"(actuator force, N or N m): {', '.join(short)}"
        )
    fell = fall_time(trajectory)
    if fell is not None:
        out.append(
            f"the robot fell {fell:.2f} s in (its free body below {FALLEN:.0%} of its starting "
            f"height): the model's own actuators did not hold keyframe {scenario.keyframe!r}; "
            "the log records the fall"
        )
    return out


def _scenario(args: argparse.Namespace) -> Scenario:
    """The bundled SCENARIO, or the scenario of --model; one of them, and --model's options
    only with --model."""
    if args.scenario is not None and args.model is not None:
        raise SimulationError(f"give SCENARIO ({args.scenario}) or --model, not both")
    if args.scenario is not None:
        given = [f for dest, f in MODEL_OPTIONS.items() if getattr(args, dest) not in (None, ())]
        if given:
            raise SimulationError(f"{given[0]} applies to --model MODEL.xml, not to a SCENARIO")
        return get_scenario(args.scenario)
    if args.model is None:
        raise SimulationError(f"give a SCENARIO ({', '.join(SCENARIOS)}) or --model MODEL.xml")
    return model_scenario(
        args.model,
        keyframe=args.keyframe,
        mocap=args.mocap,
        markers=args.markers,
        imu=args.imu,
        pushes=args.pushes,
        excitation_rad=EXCITATION_RAD if args.excitation is None else args.excitation,
    )

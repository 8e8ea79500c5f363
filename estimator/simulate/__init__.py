"""Simulated robot logs with ground truth: `physfuse simulate SCENARIO --out LOG.mcap`.

    result = simulate("humanoid_push", "run.mcap", seed=0)      # the log + what was true
    print(scenario_config("humanoid_push"))                     # its config TOML
    simulate(model_scenario("robot.xml"), "robot.mcap")        # any MJCF model with a keyframe

Layout: `scenarios` (model, controller, pushes, sensors of each scenario), `controllers`
(what runs on the simulated robot), `mismatch` (the simulated robot vs the model),
`sensors` (imperfect sensors sampling the true trajectory), `writer` (rosbag2-layout MCAP
writer and the `/ground_truth` = `/estimate` topic layout), `simulation` (the run itself),
`model_scenario` (the scenario of any MJCF model: `physfuse simulate --model`).
"""

from estimator.io.mcap_writer import Ros2Writer as Ros2Writer
from estimator.io.mcap_writer import StateLayout as StateLayout
from estimator.io.mcap_writer import state_data as state_data
from estimator.io.mcap_writer import write_state as write_state
from estimator.simulate.errors import SimulationError as SimulationError
from estimator.simulate.mismatch import Mismatch as Mismatch
from estimator.simulate.mismatch import MismatchRecord as MismatchRecord
from estimator.simulate.model_scenario import model_scenario as model_scenario
from estimator.simulate.scenarios import SCENARIOS as SCENARIOS
from estimator.simulate.scenarios import Scenario as Scenario
from estimator.simulate.scenarios import get_scenario as get_scenario
from estimator.simulate.simulation import GROUND_TRUTH as GROUND_TRUTH
from estimator.simulate.simulation import SimulationResult as SimulationResult
from estimator.simulate.simulation import scenario_config as scenario_config
from estimator.simulate.simulation import simulate as simulate

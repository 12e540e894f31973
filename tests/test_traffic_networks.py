"""The traffic env on networks nobody here wrote: sumo-rl's shipped networks (used from the installed ``sumo-rl``
package, never copied), more than two green phases, the phase-choice actions, the objective menu, ``begin_time``,
actuated programs derived from any network, and MA-SFOLS through the CLI on the 2x2 grid."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

libsumo = pytest.importorskip("libsumo")
traci = pytest.importorskip("traci")

from sfgpi_envs.traffic import EPISODE_METRIC_KEYS, TrafficSignalEnv, run_program_episode  # noqa: E402

from sb3_sfgpi import MASFOLS  # noqa: E402
from sb3_sfgpi.cli import main  # noqa: E402
from sb3_sfgpi.evaluation_jobs import EvaluationJob, run_job  # noqa: E402
from sb3_sfgpi.gpi import GPIPolicy  # noqa: E402

_SPEC = importlib.util.find_spec("sumo_rl")  # located, not imported: importing sumo_rl needs SUMO_HOME
if _SPEC is None or _SPEC.origin is None:
    pytest.skip("sumo-rl is not installed (its networks are the test data)", allow_module_level=True)
NETS = Path(_SPEC.origin).parent / "nets"
GRID = {"net_file": str(NETS / "2x2grid" / "2x2.net.xml"), "route_file": str(NETS / "2x2grid" / "2x2.rou.xml")}
TWO = ["vehicle_waiting", "co2"]


@pytest.fixture
def make_env():
    """Factory of environments that are all closed at teardown."""
    envs: list[TrafficSignalEnv] = []

    def factory(**kwargs) -> TrafficSignalEnv:
        env = TrafficSignalEnv(**{"num_seconds": 100, "objectives": TWO, **GRID, **kwargs})
        envs.append(env)
        return env

    yield factory
    for env in envs:
        env.close()


@pytest.mark.parametrize("action_mode", ["change", "phase"])
def test_grid_passes_pettingzoos_api_test(make_env, action_mode):
    env = make_env(seed=0, action_mode=action_mode)
    assert env.possible_agents == ["1", "2", "5", "6"]
    for agent in env.possible_agents:  # 4 green phases + tau + density and queue of 8 lanes
        assert env.observation_space(agent).shape == (4 + 1 + 16,)
        assert env.action_space(agent).n == (2 if action_mode == "change" else 4)
        assert env.reward_space(agent).shape == (2,)
    parallel_api_test(env, num_cycles=15)


def test_phase_actions_show_the_green_asked_for_after_its_yellow(make_env):
    env = make_env(seed=1, action_mode="phase", min_green=10, yellow_time=3, delta_time=5)
    env.reset()
    tl = env.sim.api.trafficlight
    greens = env._programs["1"].greens
    assert len(greens) == 4
    env.step({"1": 2})  # t = 0: before min green, ignored
    env.step({"1": 0})
    assert env.sim_time == 10 and tl.getRedYellowGreenState("1") == greens[0]
    obs, *_ = env.step({"1": 2})  # t = 10: min green reached; over green 1 to green 2, through a derived yellow
    assert env.sim_time == 15 and tl.getRedYellowGreenState("1") == greens[2]
    np.testing.assert_array_equal(obs["1"][:4], [0, 0, 1, 0])
    with pytest.raises(ValueError, match="a green phase in 0..3"):
        env.step({"1": 4})


def test_change_actions_cycle_through_all_greens(make_env):
    env = make_env(seed=2, min_green=5, max_green=50, yellow_time=3, delta_time=5)
    env.reset()
    seen = []
    while env.agents:
        _, _, _, _, infos = env.step(dict.fromkeys(env.agents, 1))
        if not infos["1"]["yellow"] and (not seen or seen[-1] != infos["1"]["green_phase"]):
            seen.append(infos["1"]["green_phase"])
    assert seen[:5] == [0, 1, 2, 3, 0]


class LaneRecorder(traci.StepListener):
    """Halting vehicles and CO2 on the controlled incoming lanes, read from SUMO every simulated second."""

    def __init__(self, api, layouts):
        super().__init__()
        self.api, self.lanes = api, {j: lay.vehicle_lanes for j, lay in layouts.items()}
        self.co2_mg = dict.fromkeys(self.lanes, 0.0)

    def step(self, t):
        for j, lanes in self.lanes.items():
            self.co2_mg[j] += sum(self.api.lane.getCO2Emission(lane) for lane in lanes)
        return True

    def halting(self, j):
        return sum(self.api.lane.getLastStepHaltingNumber(lane) for lane in self.lanes[j])


def test_queue_and_co2_rewards_are_what_sumo_measures(make_env, listen):
    env = make_env(seed=3, objectives=["vehicle_queue", "co2", "vehicle_waiting"], reward_scale={"co2": 0.5})
    env.reset()
    rec = LaneRecorder(env.sim.api, env.layouts)
    listen(env.sim.api, rec)
    prev = dict.fromkeys(env.possible_agents, 0.0)
    rng = np.random.default_rng(0)
    while env.agents:
        _, rewards, _, _, infos = env.step({a: int(rng.integers(2)) for a in env.agents})
        for j in env.possible_agents:
            assert rewards[j][0] == -rec.halting(j)
            assert rewards[j][1] == pytest.approx(-0.5 * (rec.co2_mg[j] - prev[j]) / 1000, rel=1e-5, abs=1e-4)
            assert infos[j]["co2_g"] == pytest.approx(rec.co2_mg[j] / 1000)
            prev[j] = rec.co2_mg[j]
    assert sum(rec.co2_mg.values()) > 0
    episode = infos[env.possible_agents[0]]["episode"]  # the grid has no crossings: no pedestrians' metrics
    assert episode["co2_emitted_kg"] == pytest.approx(sum(rec.co2_mg.values()) / 1e6, rel=1e-5)
    assert set(episode) == set(EPISODE_METRIC_KEYS) | {"co2_emitted_kg"}


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"objectives": ["vehicle_waiting", "pedestrian_waiting"]}, "needs signalised pedestrian crossings"),
        ({"objectives": ["noise"]}, "unknown objective 'noise'"),
        ({"objectives": ["co2", "co2"]}, "distinct"),
        ({"objectives": "co2"}, "non-empty list"),
        ({"reward_scale": {"nox": 1.0}}, "unknown objective 'nox'"),
        ({"reward_scale": {"co2": -1.0}}, "positive finite"),  # not selected, still wrong
        ({"reward_scale": [1.0, 2.0, 3.0]}, "2 of them"),
        ({"action_mode": "choose"}, "action_mode"),
        ({"begin_time": -1}, "begin_time"),
    ],
)
def test_bad_arguments_are_refused_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrafficSignalEnv(**{"objectives": TWO, **GRID, **kwargs})


def test_begin_time_starts_where_the_demand_does():
    cologne = NETS / "RESCO" / "cologne1"
    files = {"net_file": str(cologne / "cologne1.net.xml"), "route_file": str(cologne / "cologne1.rou.xml")}
    at_zero = run_program_episode("fixed-time", seed=0, num_seconds=120, objectives=TWO, **files)
    at_seven = run_program_episode("fixed-time", seed=0, num_seconds=120, begin_time=25200, objectives=TWO, **files)
    assert at_zero["vehicles_departed"] == 0  # the demand begins at 7:00
    assert at_seven["vehicles_departed"] > 10 and at_seven["sim_time"] == 120


@pytest.mark.parametrize("program", ["fixed-time", "actuated", "max-pressure"])
def test_sumo_programs_run_on_any_network(program):
    metrics = run_program_episode(program, seed=0, num_seconds=300, objectives=TWO, **GRID)
    assert metrics["vehicles_departed"] > 50 and metrics["vehicle_waiting_time_mean"] > 0


COLOGNE3 = {
    "net_file": str(NETS / "RESCO" / "cologne3" / "cologne3.net.xml"),
    "route_file": str(NETS / "RESCO" / "cologne3" / "cologne3.rou.xml"),
    "objectives": TWO,
    "begin_time": 25200,
    "num_seconds": 60,
}


def test_lights_with_different_spaces_are_refused_by_masfols_naming_the_padding():
    env = TrafficSignalEnv(**COLOGNE3)
    try:
        with pytest.raises(ValueError, match="same spaces.*observation_fn='padded'"):
            MASFOLS(env, policy="MlpPolicy")
    finally:
        env.close()


def _unpadded(padded: np.ndarray, env: TrafficSignalEnv, agent: str) -> np.ndarray:
    """Eq. 22's observation of ``agent`` read back from the padded layout (and its absent slots checked to be 0)."""
    layout, fn = env.layouts[agent], env.observation_fn
    n_greens = int(padded[fn.max_greens : 2 * fn.max_greens].sum())
    v, p = len(layout.vehicle_lanes), len(layout.pedestrian_edges)
    g_max, v_max, p_max = fn.max_greens, fn.max_vehicle_lanes, fn.max_pedestrian_edges
    green, tau = padded[:g_max], padded[2 * g_max]
    vehicles = padded[2 * g_max + 1 : 2 * g_max + 1 + 3 * v_max].reshape(3, v_max)
    pedestrians = padded[2 * g_max + 1 + 3 * v_max :].reshape(3, p_max)
    assert not green[n_greens:].any() and not vehicles[:, v:].any() and not pedestrians[:, p:].any()
    assert vehicles[2, :v].all() and pedestrians[2, :p].all()  # the "exists" flags of the light's own lanes
    densities = np.concatenate([vehicles[0, :v], pedestrians[0, :p]])
    queues = np.concatenate([vehicles[1, :v], pedestrians[1, :p]])
    return np.concatenate([green[:n_greens], [tau], densities, queues]).astype(np.float32)


def test_padded_observations_give_lights_that_differ_one_layout_and_masfols_trains():
    plain = TrafficSignalEnv(**COLOGNE3, backend="traci")  # libsumo runs one simulation per process
    padded = TrafficSignalEnv(**COLOGNE3, observation_fn="padded")
    assert len({plain.observation_space(a).shape for a in plain.possible_agents}) > 1  # the lights differ
    first = padded.observation_space(padded.possible_agents[0])
    assert all(padded.observation_space(a) == first for a in padded.possible_agents)
    (obs_plain, _), (obs_padded, _) = plain.reset(seed=0), padded.reset(seed=0)
    for step in range(12):
        for agent in plain.possible_agents:
            np.testing.assert_array_equal(_unpadded(obs_padded[agent], padded, agent), obs_plain[agent])
        actions = {a: step % 2 for a in plain.possible_agents}
        obs_plain, obs_padded = plain.step(actions)[0], padded.step(actions)[0]
    plain.close()
    learner = {"learning_starts": 10, "batch_size": 8, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16]}}
    masfols = MASFOLS(padded, policy="MlpPolicy", steps_per_iteration=30, learner_kwargs=learner, seed=0)
    try:
        masfols.learn(max_iterations=1)
        for agent, observation in padded.reset(seed=1)[0].items():
            assert masfols.policy_set.predict(observation, [0.5, 0.5])[0] in (0, 1), agent
    finally:
        masfols.close()


def test_padded_phase_actions_are_masked_and_no_masked_green_is_ever_shown():
    """
    cologne3's lights have 3, 4 and 4 greens: padded, each chooses among 4 with ``info["action_mask"]``, and the env
    refuses a green a light lacks, so training, value estimates and GPI's evaluation fail if one is ever chosen.
    """
    env = TrafficSignalEnv(**COLOGNE3, observation_fn="padded", action_mode="phase")
    greens = {a: len(env._programs[a].greens) for a in env.possible_agents}
    assert sorted(greens.values()) == [3, 4, 4]
    assert all(env.action_space(a).n == 4 for a in env.possible_agents)
    _, infos = env.reset(seed=0)
    for agent, info in infos.items():
        np.testing.assert_array_equal(info["action_mask"], np.arange(4) < greens[agent])
    short = min(greens, key=greens.get)
    with pytest.raises(ValueError, match="action mask forbids"):
        env.step({a: 3 for a in env.possible_agents} | {short: 3})
    learner = {"learning_starts": 5, "batch_size": 8, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16]}}
    masfols = MASFOLS(
        env, policy="MlpPolicy", steps_per_iteration=40, learner_kwargs=learner, seed=0,
        test_weights=[[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]], eval_episodes=1,
    )  # fmt: skip
    try:
        masfols.learn(max_iterations=1)
        assert len(masfols.policy_set) >= 1
        observations, infos = env.reset(seed=1)
        for w in ([1.0, 0.0], [0.0, 1.0]):
            batch = np.stack([observations[a] for a in env.possible_agents])
            masks = np.stack([infos[a]["action_mask"] for a in env.possible_agents])
            actions, _ = masfols.policy_set.predict(batch, w, action_masks=masks)
            assert masks[np.arange(3), actions].all()
    finally:
        masfols.close()
    for program in ("max-pressure", "actuated"):  # compare's baselines on the masked env (they send no actions)
        baseline = TrafficSignalEnv(**COLOGNE3, observation_fn="padded", action_mode="phase", signal_control=program)
        try:
            result = run_job(baseline, EvaluationJob(1000, None, 1, None, record_infos=True), gamma=0.99)
            assert set(result.final_infos[0]) == set(env.possible_agents)
        finally:
            baseline.close()


def test_masfols_trains_on_the_grid_through_the_cli(tmp_path, capsys):
    out = tmp_path / "grid"
    env_args = [f"net_file={GRID['net_file']}", f"route_file={GRID['route_file']}", f"objectives={json.dumps(TWO)}"]
    argv = ["train", "traffic", "--out", str(out), "--iterations", "2", "--steps-per-iteration", "40",
            "--set", "n_test_weights=3", "--set", "eval_workers=0", "--no-progress", "--seed", "0",
            "--env", "num_seconds=100", *[arg for env_arg in env_args for arg in ("--env", env_arg)],
            "--learner", "learning_starts=20", "--learner", "batch_size=8",
            "--set", "validation_weights=0"]  # fmt: skip
    assert main(argv) == 0
    evaluation = json.loads((out / "evaluation.json").read_text())
    assert [row["iteration"] for row in evaluation] == [1, 2]
    assert all(np.isfinite(row["mean_return"]) and len(row["test"]) == 3 for row in evaluation)
    policy_set = GPIPolicy.load(out / "policy_set")
    assert policy_set.reward_dim == 2 and {info.agent for info in policy_set.infos} <= {"1", "2", "5", "6"}
    checkpoint = json.loads((out / "checkpoint.json").read_text())
    assert checkpoint["n_policies"] == len(policy_set) == evaluation[-1]["n_policies"] >= 4
    assert main(["evaluate", str(out), "--w", "0.5", "0.5"]) == 0
    assert "objectives: vehicle_waiting, co2" in capsys.readouterr().out
    output = tmp_path / "compare.json"  # the columns the grid has: vehicles' waiting and CO2, no pedestrians'
    assert main(["compare", str(out), "--w", "1", "0", "--episodes", "1", "--workers", "0", "-o", str(output)]) == 0
    compare = json.loads(output.read_text())
    assert [key for key, _ in compare["episode_metrics"]] == ["vehicle_waiting_time_mean", "co2_emitted_kg"]
    assert "| method | mean vehicle waiting time [s] | CO2 emitted [kg] |" in capsys.readouterr().out
    assert all(row["episode_metrics"]["co2_emitted_kg"]["mean"] > 0 for row in compare["rows"])


def test_the_cli_refuses_a_network_that_is_not_there(tmp_path, capsys):
    argv = ["train", "traffic", "--out", str(tmp_path / "r"), "--env", f"net_file={tmp_path / 'none.net.xml'}"]
    assert main(argv) == 2
    assert "does not exist" in capsys.readouterr().err

"""Users' own objectives and observations in TrafficSignalEnv, and sumo-rl's MDP by one switch (real SUMO)."""

from __future__ import annotations

import functools
import pickle

import numpy as np
import pytest
from gymnasium import spaces

pytest.importorskip("libsumo")

from sfgpi_envs.traffic import MDP_DEFAULTS, LightView, Objective, SumoRLObservation, TrafficSignalEnv  # noqa: E402

SECONDS = 120


def mean_speed(light: LightView) -> float:
    """A user's objective through the SUMO handle: mean speed over the light's vehicle lanes."""
    speeds = [light.sumo.lane.getLastStepMeanSpeed(lane) for lane in light.layout.vehicle_lanes]
    return float(np.mean(speeds))


def minus_halting(light: LightView) -> float:
    """A user's copy of the menu's ``vehicle_queue``, from the view's measurement."""
    return -float(light.current.halting)


class WithTime:
    """A user's observation: the env's own, plus the time of day as a fraction of an hour."""

    def space(self, layout, n_greens: int) -> spaces.Box:
        return spaces.Box(0.0, 1.0, shape=(n_greens + 2 + 2 * layout.n_lanes,), dtype=np.float32)

    def __call__(self, light: LightView) -> np.ndarray:
        return np.append(light.default_observation(), np.float32((light.time % 3600) / 3600))


def _episode(env: TrafficSignalEnv, seed: int = 0) -> list[tuple[dict, dict]]:
    """(observations, rewards) of every step of one episode of constant actions (the first of each space)."""
    obs, _ = env.reset(seed=seed)
    steps = [(obs, {})]
    while env.agents:
        obs, rewards, *_ = env.step({a: 0 for a in env.agents})
        steps.append((obs, rewards))
    env.close()
    return steps


def test_a_users_objective_gets_the_measurements_and_the_sumo_handle():
    objectives = ["vehicle_queue", Objective("halting", "halting vehicles", minus_halting),
                  Objective("speed", "mean speed [m/s]", mean_speed)]  # fmt: skip
    env = TrafficSignalEnv(num_seconds=SECONDS, objectives=objectives, seed=0)
    assert env.objective_names == ("vehicle_queue", "halting", "speed")
    obs, _ = env.reset(seed=0)
    speeds = []
    while env.agents:
        obs, rewards, *_ = env.step({a: 1 for a in env.agents})
        api = env.sim.api
        for agent, reward in rewards.items():
            lanes = env.layouts[agent].vehicle_lanes
            expected = np.float32(np.mean([api.lane.getLastStepMeanSpeed(lane) for lane in lanes]))
            assert reward[0] == reward[1] and reward[2] == expected
            speeds.append(reward[2])
    env.close()
    assert max(speeds) > 1.0  # vehicles moved: the handle read the live simulation


def test_default_objectives_and_observations_are_those_of_before():
    """The menu through the view: the paper's rewards and Eq. 22's observation, the same with an explicit `mdp`."""
    plain = _episode(TrafficSignalEnv(num_seconds=SECONDS, seed=3))
    explicit = _episode(TrafficSignalEnv(num_seconds=SECONDS, seed=3, mdp="paper", yellow_time=3, min_green=10))
    for (obs_a, rew_a), (obs_b, rew_b) in zip(plain, explicit, strict=True):
        assert all(np.array_equal(obs_a[a], obs_b[a]) for a in obs_a)
        assert all(np.array_equal(rew_a[a], rew_b[a]) for a in rew_a)
    assert any(np.any(r != 0) for _, rewards in plain for r in rewards.values())


def test_an_observation_function_sets_the_space_and_the_observation():
    own = _episode(TrafficSignalEnv(num_seconds=SECONDS), seed=1)
    env = TrafficSignalEnv(num_seconds=SECONDS, observation_fn=WithTime())
    for agent in env.possible_agents:
        assert env.observation_space(agent).shape == (TrafficSignalEnv().observation_space(agent).shape[0] + 1,)
    for (obs_own, _), (obs_hook, _) in zip(own, _episode(env, seed=1), strict=True):
        for agent, o in obs_hook.items():
            assert env.observation_space(agent).contains(o)
            np.testing.assert_array_equal(o[:-1], obs_own[agent])


def test_hooks_pickle_for_the_workers_and_unpicklable_ones_are_refused():
    env_fn = functools.partial(TrafficSignalEnv, num_seconds=SECONDS, observation_fn=WithTime(),
                               objectives=["vehicle_waiting", Objective("speed", "speed", mean_speed)])  # fmt: skip
    copy = pickle.loads(pickle.dumps(env_fn))()
    assert copy.objective_names == ("vehicle_waiting", "speed") and isinstance(copy.observation_fn, WithTime)
    copy.close()
    with pytest.raises(ValueError, match="reward of objective 'x' must be picklable"):
        TrafficSignalEnv(objectives=[Objective("x", "x", lambda light: 0.0)])
    with pytest.raises(ValueError, match="an objective is a menu name"):
        TrafficSignalEnv(objectives=[mean_speed])
    with pytest.raises(ValueError, match="distinct names"):
        TrafficSignalEnv(objectives=["co2", Objective("co2", "mine", mean_speed)])
    with pytest.raises(ValueError, match="observation_fn must be None, 'padded', or have space"):
        TrafficSignalEnv(observation_fn=lambda light: light.default_observation())
    with pytest.raises(ValueError, match="mdp must be one of"):
        TrafficSignalEnv(mdp="resco")


def test_a_users_objective_is_scaled_by_its_name():
    objectives = ["vehicle_waiting", Objective("speed", "mean speed [m/s]", mean_speed)]
    env = TrafficSignalEnv(objectives=objectives, reward_scale={"speed": 0.5, "co2": 0.1})
    np.testing.assert_array_equal(env.reward_scale, [1.0, 0.5])
    with pytest.raises(ValueError, match="unknown objective 'sped'"):
        TrafficSignalEnv(objectives=objectives, reward_scale={"sped": 0.5})


def test_the_sumo_rl_switch_gives_its_defaults_and_its_observation():
    env = TrafficSignalEnv(num_seconds=SECONDS, mdp="sumo-rl", seed=0)
    assert (env.yellow_time, env.min_green, env.max_green, env.delta_time) == (2, 5, 50, 5)
    assert env.action_mode == "phase" and env.objective_names == ("vehicle_waiting",)
    assert isinstance(env.observation_fn, SumoRLObservation)
    agent = env.possible_agents[0]
    n_greens, n_lanes = env.action_space(agent).n, len(env.layouts[agent].vehicle_lanes)
    assert env.observation_space(agent).shape == (n_greens + 1 + 2 * n_lanes,)
    obs, _ = env.reset(seed=0)
    flags, changed = [obs[agent][n_greens]], []
    while env.agents:
        previous = obs[agent][:n_greens]
        obs, _, _, _, infos = env.step({a: 0 for a in env.agents})  # ask for green 0; max green forces changes
        assert env.observation_space(agent).contains(obs[agent])
        assert obs[agent][infos[agent]["green_phase"]] == 1.0 and obs[agent][:n_greens].sum() == 1.0
        flags.append(obs[agent][n_greens])
        changed.append(not np.array_equal(previous, obs[agent][:n_greens]))
    env.close()
    assert flags[0] == 0.0 and max(flags) == 1.0 and any(changed)
    assert all(flag == 0.0 for flag, change in zip(flags[1:], changed, strict=True) if change)  # green just began
    overridden = TrafficSignalEnv(mdp="sumo-rl", yellow_time=3, objectives=["vehicle_waiting", "co2"])
    assert overridden.yellow_time == 3 and overridden.min_green == MDP_DEFAULTS["sumo-rl"]["min_green"]

"""Regressions of issue 45: NaN/inf stopped where it appears, and one-line errors where tracebacks or silent wrong
answers were. Each failed on the code before the fix."""

from __future__ import annotations

import json
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import FIG1_TABULAR_KWARGS
from momdp import Fig1MOMDP
from parallel_chain import CHAIN_LEARNER, ParallelChainEnv

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.cli import main
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.gpi import MANIFEST, CorruptPolicySetError, GPIPolicy
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.sfdqn import SFDQN

LEARNER_KWARGS = {k: v for k, v in CHAIN_LEARNER.items() if k != "policy"}


class TurnsBad(gym.Wrapper):
    """From its ``at``-th step on, the env's reward (or observation) holds ``value``."""

    def __init__(self, env: gym.Env, at: int, value: float, where: str = "reward"):
        super().__init__(env)
        self.reward_space = env.reward_space
        self.at, self.value, self.where, self.steps = at, value, where, 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.steps >= self.at:
            if self.where == "reward":
                reward = np.array([reward[0], self.value], dtype=np.float32)
            else:
                obs = np.full_like(obs, self.value)
        return obs, reward, terminated, truncated, info


@pytest.mark.parametrize(("value", "where"), [(np.nan, "reward"), (np.inf, "reward"), (np.nan, "observation")])
def test_sfdqn_refuses_a_non_finite_reward_or_observation_at_its_step(value, where):
    model = SFDQN("MlpPolicy", TurnsBad(Fig1MOMDP(one_hot=True), 7, value, where), **FIG1_TABULAR_KWARGS, seed=0)
    with pytest.raises(ValueError, match=rf"Fig1MOMDP, agent env 0, step 7: the {where} is not finite"):
        model.learn(100)
    assert model.replay_buffer.size() == 6  # the bad step was not stored
    assert np.isfinite(model.successor_features(np.eye(5, dtype=np.float32))).all()


class BadChain(ParallelChainEnv):
    """The chain, with one thing wrong from the ``at``-th step on (``reset_count`` counts resets)."""

    def __init__(self, fault: str, at: int = 1, **kwargs):
        super().__init__(2, **kwargs)
        self.fault, self.at, self.total = fault, at, 0

    def reset(self, seed=None, options=None):
        obs, infos = super().reset(seed, options)
        if self.fault == "intruder":
            obs["intruder"], infos["intruder"], self.agents = 0, {}, [*self.agents, "intruder"]
        return obs, infos

    def step(self, actions):
        obs, rewards, terminations, truncations, infos = super().step(
            {a: v for a, v in actions.items() if a != "intruder"}
        )
        self.total += 1
        if self.total >= self.at and self.fault == "nan":
            rewards["agent_1"] = np.array([np.nan, 0.0], dtype=np.float32)
        if self.total == self.at and self.fault == "comeback":
            self.agents = [a for a in self.agents if a != "agent_1"]  # agent_1 vanishes ...
        if self.total == self.at + 1 and self.fault == "comeback":
            self.agents = [*self.agents, "agent_1"]  # ... and comes back
            obs["agent_1"], rewards["agent_1"] = 2, np.zeros(2, dtype=np.float32)
            terminations["agent_1"] = truncations["agent_1"] = False
            infos["agent_1"] = {}
        return obs, rewards, terminations, truncations, infos


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("nan", r"parallel_chain_v0, agent 'agent_1', step 6: the reward is not finite"),
        ("comeback", r"parallel_chain_v0, agent 'agent_1', step 7: in the step's results but it did not act"),
        ("intruder", r"parallel_chain_v0, agent 'intruder', step 0 \(reset of copy 0\): not one of the env's"),
    ],
)
def test_masfols_stops_at_the_step_a_bad_reward_or_agent_appears(fault, message):
    model = MASFOLS(
        BadChain(fault, at=6),
        steps_per_iteration=300,
        learner_kwargs=LEARNER_KWARGS,
        test_weights=2,
    )
    with pytest.raises(ValueError, match=message):
        model.learn(1)
    assert model.runner.num_timesteps < 10  # not after the whole iteration


@pytest.mark.parametrize("fault", ["intruder", "comeback", "nan"])
def test_evaluation_rollouts_name_a_bad_agent_or_reward(fault):
    env = BadChain(fault, at=2)
    with pytest.raises(ValueError, match="parallel_chain_v0, agent '(intruder|agent_1)', step"):
        run_episodes(env, lambda obs: dict.fromkeys(obs, 0), 1, 1.0)


def mlp_set(make_random_mlp) -> GPIPolicy:
    policy_set = GPIPolicy()
    policy_set.add(make_random_mlp(0), weights=[1, 0, 0], value=[1.0, 0.0, 0.0])
    return policy_set


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_mlp_gpi_refuses_non_finite_observations_as_tables_do(make_random_mlp, bad):
    policy_set = mlp_set(make_random_mlp)
    observation = np.array([0.1, bad, 0.0, 0.0], dtype=np.float32)
    for call in (policy_set.predict, policy_set.q_values):
        with pytest.raises(ValueError, match="observations must be finite numbers, got NaN or inf"):
            call(observation, [1, 0, 0])


def test_gpi_save_refuses_what_load_would_refuse(make_random_mlp, tmp_path):
    policy_set = mlp_set(make_random_mlp)
    with th.no_grad():
        next(policy_set.networks[0].parameters()).fill_(np.nan)
    with pytest.raises(ValueError, match=r"cannot save policy 0 \(agent None, iteration None\): its network holds NaN"):
        policy_set.save(tmp_path / "set")
    assert not (tmp_path / "set").exists()


@pytest.mark.parametrize("version", [True, 1.0, "1"])
def test_a_manifest_version_must_be_the_integer_1(make_random_mlp, tmp_path, version):
    mlp_set(make_random_mlp).save(tmp_path / "set")
    manifest = json.loads((tmp_path / "set" / MANIFEST).read_text())
    (tmp_path / "set" / MANIFEST).write_text(json.dumps({**manifest, "version": version}))
    with pytest.raises(CorruptPolicySetError, match="unsupported policy-set version"):
        GPIPolicy.load(tmp_path / "set")


@pytest.mark.parametrize("observation", [7, -1, 1.5, np.nan])
def test_successor_features_of_a_table_refuse_observations_outside_its_space(make_tabular_sfdqn, observation):
    model = make_tabular_sfdqn()
    with pytest.raises(ValueError, match="is outside the observation space|must be finite"):
        model.successor_features(np.array(observation))
    assert model.successor_features(np.array(2)).shape == (1, 3, 2)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"buffer_size": 0}, "buffer_size must be a positive integer"),
        ({"exploration_fraction": -1}, r"exploration_fraction must be a number in \(0, 1\]"),
        ({"exploration_fraction": 0}, r"exploration_fraction must be a number in \(0, 1\]"),
        ({"target_update_interval": 0}, "target_update_interval must be a positive integer"),
        ({"train_freq": 0}, "train_freq must be a positive integer"),
        ({"train_freq": (1, "fortnight")}, "train_freq must be a positive integer or"),
        ({"gradient_steps": 0}, "gradient_steps must be a positive integer or -1"),
        ({"learning_starts": -1}, "learning_starts must be an integer >= 0"),
        ({"tau": 1.5}, r"tau must be a number in \[0, 1\]"),
        ({"exploration_final_eps": 2}, r"exploration_final_eps must be a number in \[0, 1\]"),
        ({"max_grad_norm": 0}, "max_grad_norm must be a positive number"),
        ({"exploration_steps": "50k"}, "exploration_steps must be a positive number of steps or None, got '50k'"),
    ],
)
def test_sizes_and_intervals_sb3_accepts_silently_are_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        SFDQN("TabularPolicy", Fig1MOMDP(), **{**FIG1_TABULAR_KWARGS, **overrides})


def test_train_freq_0_on_the_cli_is_one_line_and_leaves_no_run_directory(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "four-room", "--learner", "train_freq=0", "--no-progress", "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "train_freq must be a positive integer" in error and len(error.strip().splitlines()) == 1
    assert not out.exists()


def test_sfdqn_load_of_an_sb3_dqn_file_is_one_line(tmp_path):
    from stable_baselines3 import DQN

    DQN("MlpPolicy", "CartPole-v1", buffer_size=100, learning_starts=10).save(tmp_path / "dqn.zip")
    with pytest.raises(ValueError, match="is not an SFDQN model"):
        SFDQN.load(tmp_path / "dqn.zip")


def test_predict_takes_weights_as_a_tensor_that_requires_grad(make_tabular_sfdqn, make_random_mlp):
    model = make_tabular_sfdqn()
    w = th.tensor([0.3, 0.7], requires_grad=True)
    assert model.predict(np.array(1), deterministic=True, w=w)[0] == model.predict(np.array(1), True, w=[0.3, 0.7])[0]
    policy_set = mlp_set(make_random_mlp)
    observation = np.zeros(4, dtype=np.float32)
    w3 = th.tensor([0.2, 0.3, 0.5], requires_grad=True)
    assert policy_set.predict(observation, w3)[0] == policy_set.predict(observation, [0.2, 0.3, 0.5])[0]


def test_a_failed_checkpoint_write_names_the_iteration_that_failed(tmp_path, capsys, monkeypatch):
    write = RunDirectory.write_iteration

    def fail_second(self, history, checkpoint):
        if checkpoint["iteration"] == 2:
            raise OSError(28, "No space left on device")
        write(self, history, checkpoint)

    monkeypatch.setattr(RunDirectory, "write_iteration", fail_second)
    argv = ["train", "four-room", "--iterations", "3", "--steps-per-iteration", "100", "--set", "n_test_weights=2"]
    assert main([*argv, "--set", "validation_weights=0", "--no-progress", "--out", str(tmp_path / "run")]) == 1
    error = capsys.readouterr().err
    assert "training stopped in iteration 2 (OSError" in error and "(1 done)" in error


@pytest.fixture
def traffic_env_class():
    pytest.importorskip("libsumo")
    from sfgpi_envs.traffic import TrafficSignalEnv
    from sfgpi_envs.traffic.scenario import NET_FILE

    return TrafficSignalEnv, NET_FILE


def test_a_route_file_without_traffic_warns(traffic_env_class, tmp_path):
    env_class, net_file = traffic_env_class
    empty = tmp_path / "empty.rou.xml"
    empty.write_text('<routes><vType id="car"/><route id="r" edges="x"/></routes>')
    with pytest.warns(UserWarning, match="holds no vehicle, trip, person or flow: no traffic, every reward is 0"):
        env_class(route_file=empty).close()
    with pytest.warns(UserWarning, match=r"its root is <net>: a network file\?"):
        env_class(route_file=net_file).close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env_class().close()  # the scenario's own demand: no warning

"""SFOLS + GPI on single-agent MO-Gymnasium envs: the adapter, MASFOLS with one agent, the command line, optimism
relative to the reward scale, and the envs that are refused."""

from __future__ import annotations

import functools
import json

import gymnasium as gym
import numpy as np
import pytest

from sb3_sfgpi import MASFOLS, SFDQN, GPIPolicy
from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.gym_domains import gym_preset
from sb3_sfgpi.common.single_agent import AGENT, SingleAgentParallelEnv
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.sfdqn.options import optimistic_value

mo = pytest.importorskip("mo_gymnasium")

DST = "deep-sea-treasure-v0"
#: The tabular learners of the command line's preset for small integer observations, with a shorter planning period.
LEARNER = dict(
    learning_rate=0.1, gamma=0.99, learning_starts=0, train_freq=1, exploration_fraction=0.5, planning_sweeps=30,
    planning_interval=2_000, optimistic_init="rmax_1.25",
)  # fmt: skip


def best_expected_utility(test_weights: np.ndarray) -> float:
    """EU*: the mean over the test weights of the best w·(discounted return) on DST's true front."""
    front = np.array(mo.make(DST).unwrapped.pareto_front(0.99))
    return float(np.mean((test_weights @ front.T).max(axis=1)))


def test_the_adapter_is_a_parallel_env_of_one_agent():
    env = SingleAgentParallelEnv(mo.make(DST))
    assert env.possible_agents == [AGENT] and env.agents == []
    assert env.reward_space(AGENT).shape == (2,)
    observations, infos = env.reset(seed=0)
    assert list(observations) == [AGENT] and list(infos) == [AGENT] and env.agents == [AGENT]
    _, rewards, terminations, truncations, _ = env.step({AGENT: 1})  # down: the first treasure, the episode ends
    assert rewards[AGENT].dtype == np.float32 and rewards[AGENT].tolist() == pytest.approx([0.7, -1.0])
    assert terminations[AGENT] and not truncations[AGENT] and env.agents == []
    with pytest.raises(ValueError, match="one agent 'agent_0'"):
        env.step({"agent_1": 0})


def test_scalar_reward_and_turn_based_envs_are_refused_in_one_line():
    with pytest.raises(ValueError, match="reward_space"):
        MASFOLS(gym.make("CartPole-v1"))
    moconnect4_v0 = pytest.importorskip("momaland.envs.connect4.moconnect4_v0")
    with pytest.raises(ValueError, match=r"turn-based \(AEC\) env.*takes turns"):
        MASFOLS(moconnect4_v0.env())


def test_sfols_reaches_the_true_front_of_deep_sea_treasure():
    """Two iterations of 10,000 steps: GPI over the set reaches the exact optimum on 20 test weights (EU/EU* ≥ 0.99)."""
    test_weights = random_weights(2, 20, rng=0)
    model = MASFOLS(mo.make(DST), steps_per_iteration=10_000, learner_kwargs=LEARNER, test_weights=test_weights)
    model.learn(max_iterations=2)
    returns = np.array([test["agents"][AGENT]["discounted"] for test in model.history[-1]["test"]])
    assert returns.shape == (20, 2)
    expected_utility = np.mean(np.sum(test_weights * returns, axis=1))
    assert expected_utility == pytest.approx(model.history[-1]["mean_return"])
    assert expected_utility / best_expected_utility(test_weights) >= 0.99
    # the set acts on the env's own observations, as GPIPolicy.predict does for any agent
    observation, _ = mo.make(DST).reset(seed=0)
    action, _ = model.policy_set.predict(observation, w=[0.9, 0.1])
    assert 0 <= int(action) < 4


def test_sfdqn_takes_an_mo_gymnasium_id():
    model = SFDQN("TabularPolicy", DST, learning_starts=0, seed=0).learn(200)
    assert model.reward_dim == 2 and model.num_timesteps == 200
    assert model.get_env().get_attr("reward_space")[0].shape == (2,)


def test_relative_optimism_is_read_from_the_reward_space():
    model = SFDQN("TabularPolicy", mo.make(DST), planning_sweeps=1, optimistic_init="rmax_2")
    assert model.optimistic_value == pytest.approx(2 * 23.7, rel=1e-6)  # DST's largest treasure
    assert optimistic_value("rmax_1.25", [0.0, 0.0], [1.0, 1.0]) == 1.25  # Four-Room's preset: the same 1.25
    with pytest.raises(ValueError, match="optimistic_init must be a finite number or 'rmax_X'"):
        SFDQN("TabularPolicy", mo.make(DST), planning_sweeps=1, optimistic_init="rmax_x")
    with pytest.raises(ValueError, match="finite bounds"):
        optimistic_value("rmax_1", [-np.inf], [1.0])


def test_copies_of_a_gymnasium_env_train_in_their_processes():
    model = MASFOLS(
        mo.make(DST), steps_per_iteration=400, learner_kwargs=dict(learning_starts=50), test_weights=2,
        n_envs=2, env_fn=functools.partial(mo.make, DST),
    )  # fmt: skip
    try:
        model.learn(max_iterations=1)
    finally:
        model.close()
    assert model.runner.learners[AGENT].num_timesteps == 800  # two copies, 400 joint steps


def test_the_command_line_trains_an_mo_gymnasium_id(tmp_path, capsys):
    out = tmp_path / "dst"
    assert main(["train", DST, "--iterations", "2", "--steps-per-iteration", "3000", "--out", str(out)]) == 0
    assert capsys.readouterr().out.startswith(f"sb3-sfgpi train {DST}: ma-sfols, seed 0")
    assert main(["evaluate", str(out), "--w", "0.3", "0.7"]) == 0
    assert "agent_0: return" in capsys.readouterr().out
    policy_set = GPIPolicy.load(out / "policy_set")
    assert policy_set.reward_dim == 2 and len(policy_set) >= 1
    # the tabular preset pools its replay (docs: known fronts): what each iteration added is kept for resume
    assert json.loads((out / "run.json").read_text())["pool_replay"] is True
    assert sorted(p.name for p in (out / "experience").iterdir()) == ["iteration_001.npz", "iteration_002.npz"]


def test_the_command_line_trains_a_deep_id_with_one_conditioned_learner_and_resumes_it(tmp_path, capsys):
    """Minecart (continuous observations): the deep preset's one ψ(s, a, w) for the run, its state kept for resume."""
    out = tmp_path / "minecart"
    short = ["--steps-per-iteration", "150", "--set", "n_test_weights=1", "--set", "value_episodes=1"]
    short += ["--set", "validation_weights=2"]  # the preset's 200 validation episodes would be most of the test
    short += ["--env", "max_episode_steps=100"]  # an idle cart's evaluation episodes end at 100 steps, not 1,000
    assert main(["train", "minecart-v0", "--iterations", "1", *short, "--out", str(out), "--no-progress"]) == 0
    config = json.loads((out / "run.json").read_text())
    assert config["policy"] == "ConditionedMlpPolicy" and config["learner_kwargs"]["exploration_steps"] == 50_000
    assert config["prune"] and config["learner_kwargs"]["buffer_size"] == 200_000  # not cut
    assert config["episode_weights"] == "support"  # each episode acts for a weight of the support
    assert gym_preset("minecart-v0")["validation_weights"] == 200
    assert [p.name for p in (out / "learners").iterdir()] == ["iteration_001.pt"]
    resumed = ["train", "minecart-v0", "--iterations", "2", *short, "--out", str(out), "--resume", "--no-progress"]
    assert main(resumed) == 0
    assert [p.name for p in (out / "learners").iterdir()] == ["iteration_002.pt"]
    assert len(json.loads((out / "evaluation.json").read_text())) == 2
    assert GPIPolicy.load(out / "policy_set").networks[0].member_weights.shape == (3,)
    capsys.readouterr()


@pytest.mark.parametrize(
    "domain, message", [("no-such-env-v0", "unknown domain 'no-such-env-v0'"), ("CartPole-v1", "reward_space")]
)
def test_the_command_line_refuses_ids_it_cannot_train(tmp_path, cli_exit, domain, message):
    code, stderr = cli_exit(["train", domain, "--out", str(tmp_path / "x")])
    assert code == 2 and message in stderr and len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()

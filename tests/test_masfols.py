"""MASFOLS: learn, the exact CCS on the parallel chain, run.json, continuing a run, fixed weights."""

from __future__ import annotations

import gc
import json
import weakref

import numpy as np
import pytest
import torch as th
from momdp import REWARDS, TERMINAL
from parallel_chain import CHAIN_LEARNER, ParallelChainEnv, optimal_value
from stable_baselines3.common.logger import TensorBoardOutputFormat
from tensorboard_scalars import scalar_steps

from sb3_sfgpi import masfols
from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.run_settings import RunSettings

#: The chain's tabular learner settings, without the policy (MASFOLS takes it apart).
LEARNER_KWARGS = {k: v for k, v in CHAIN_LEARNER.items() if k != "policy"}
TEST_WEIGHTS = random_weights(2, 5, rng=0)
OBS = np.arange(5)


def make(steps: int = 300, n_agents: int = 2, test_weights=TEST_WEIGHTS, **kwargs) -> MASFOLS:
    """MASFOLS on the chain, evaluated on ``test_weights``."""
    return MASFOLS(
        ParallelChainEnv(n_agents),
        policy="TabularPolicy",
        steps_per_iteration=steps,
        learner_kwargs=LEARNER_KWARGS,
        test_weights=test_weights,
        **kwargs,
    )


def chain_return(policies: GPIPolicy, w) -> np.ndarray:
    """The undiscounted vector return on one chain of an agent acting by GPI over ``policies`` for ``w``."""
    total = np.zeros(2)
    for state in range(TERMINAL):
        action = int(policies.predict(state, w)[0])
        total += REWARDS[state, action]
    return total


def assert_same_policy_sets(a: GPIPolicy, b: GPIPolicy) -> None:
    assert len(a) == len(b) > 0
    for info_a, info_b in zip(a.infos, b.infos, strict=True):
        np.testing.assert_allclose(info_a.weights, info_b.weights)
        np.testing.assert_allclose(info_a.value, info_b.value)
        assert (info_a.agent, info_a.iteration) == (info_b.agent, info_b.iteration)
    np.testing.assert_allclose(a.successor_features(OBS), b.successor_features(OBS))


def test_learn_returns_self_and_fills_history_and_policy_set():
    model = make(steps=100, weights="random")
    assert model.learn(max_iterations=2) is model
    assert [row["iteration"] for row in model.history] == [1, 2]
    assert [row["timesteps"] for row in model.history] == [100, 200]
    assert len(model.policy_set) >= 1 and model.history[-1]["n_policies"] == len(model.policy_set)
    for row in model.history:
        assert set(row["weights_trained"]) == {"agent_0", "agent_1"}
        assert [entry["weights"] for entry in row["test"]] == TEST_WEIGHTS.tolist()
        assert np.isfinite(row["mean_return"])
    assert {info.agent for info in model.policy_set.infos} <= {"agent_0", "agent_1"}


def test_an_iterations_learners_are_freed_by_reference_counts_when_the_next_replaces_them():
    model = make(steps=100, weights="random")
    gc.disable()  # no collection: only a release free of cycles frees them (and their replay buffers)
    try:
        model.learn(max_iterations=1)
        first = [weakref.ref(learner) for learner in model.runner.learners.values()]
        model.learn(max_iterations=2)
        assert first and all(learner() is None for learner in first)
    finally:
        gc.enable()


def test_ols_finds_the_optimum_and_stops_before_the_cap():
    model = make(steps=600).learn(max_iterations=10)
    assert len(model.history) < 10 and model.callback.ended_by_schedule
    assert model.callback.schedule.ols.next_weight() is None
    assert model.history[0]["weights_trained"] == {"agent_0": [1.0, 0.0], "agent_1": [0.0, 1.0]}
    for w0 in np.linspace(0, 1, 21):
        w = np.array([w0, 1 - w0])
        assert model.policy_set.q_values(np.array([0]), w).max() == pytest.approx(optimal_value(w), abs=1e-3)
    for entry in model.history[-1]["test"]:  # GPI reaches the optimum in the env too, for both agents
        for returns in entry["agents"].values():
            assert np.dot(entry["weights"], returns["undiscounted"]) == pytest.approx(optimal_value(entry["weights"]))


def test_run_dir_holds_the_settings_and_the_iterations(tmp_path):
    model = make(steps=50, weights="random", seed=4, run_dir=tmp_path)
    model.run_info["domain"] = "chain"  # plain data of the caller's, written to run.json by learn()
    model.learn(max_iterations=2)
    config = json.loads((tmp_path / "run.json").read_text())
    assert set(RunSettings.names()) <= set(config) and config["domain"] == "chain"
    assert RunSettings.stored(config, "run.json") == model.settings
    assert config["policy"] == "TabularPolicy" and config["weights"] == "random"
    assert config["steps_per_iteration"] == 50 and config["seed"] == 4
    assert config["learner_kwargs"] == LEARNER_KWARGS
    np.testing.assert_allclose(config["test_weights"], TEST_WEIGHTS)
    assert (config["value_mode"], config["value_episodes"]) == ("joint", 1)
    assert (config["gpi_set"], config["eval_episodes"]) == ("all", 1)
    assert (config["validation_weights"], config["prune"], config["admit_together"]) == (0, False, False)
    checkpoint = json.loads((tmp_path / "checkpoint.json").read_text())
    assert (checkpoint["iteration"], checkpoint["timesteps"]) == (2, 100)
    assert checkpoint["n_policies"] == len(model.policy_set)
    assert len(json.loads((tmp_path / "evaluation.json").read_text())) == 2
    assert_same_policy_sets(GPIPolicy.load(tmp_path / "policy_set"), model.policy_set)
    assert (tmp_path / "logs" / "progress.csv").is_file()


@pytest.mark.parametrize(
    "options",
    [
        {"weights": "ols"},
        {"weights": "random"},
        {"weights": "random", "validation_weights": 3},
        {"weights": "random", "validation_weights": 3, "prune": True, "admit_together": True},
        {"weights": "random", "sharing": "shared"},
        {"weights": "ols", "value_mode": "shared", "value_episodes": 2, "ols_batch": "same-after-extrema"},
    ],
)
def test_load_continues_a_run_as_if_it_had_not_stopped(tmp_path, options):
    kwargs = dict(steps=300, seed=3, **options)
    whole = make(**kwargs, run_dir=tmp_path / "whole").learn(max_iterations=3)

    make(**kwargs, run_dir=tmp_path / "cut").learn(max_iterations=1)
    continued = MASFOLS.load(tmp_path / "cut", ParallelChainEnv(2))
    assert continued.settings == whole.settings
    continued.learn(max_iterations=3)

    assert len(continued.history) == len(whole.history) >= 2  # the continued run did iterate after the load
    assert [r["mean_return"] for r in continued.history] == [r["mean_return"] for r in whole.history]
    assert [r["weights_trained"] for r in continued.history] == [r["weights_trained"] for r in whole.history]
    assert_same_policy_sets(continued.policy_set, whole.policy_set)
    assert_same_policy_sets(GPIPolicy.load(tmp_path / "cut" / "policy_set"), whole.policy_set)
    assert json.loads((tmp_path / "cut" / "checkpoint.json").read_text())["iteration"] == len(whole.history)


@pytest.mark.parametrize("version", [None, 0, 2, "1"])
def test_load_refuses_a_run_file_of_another_format_version(tmp_path, version):
    make(steps=50, weights="random", run_dir=tmp_path).learn(max_iterations=1)
    config = json.loads((tmp_path / "run.json").read_text())
    assert (config["format"], config["version"]) == ("sb3-sfgpi/run", 1)
    (tmp_path / "run.json").write_text(json.dumps({**config, "version": version}))
    with pytest.raises(
        ValueError, match=f"is of format version {version!r}; this version of sb3-sfgpi reads version 1"
    ):
        MASFOLS.load(tmp_path, ParallelChainEnv(2))


def test_load_refuses_arguments_that_are_stored_in_the_run(tmp_path):
    make(steps=20, weights="random", run_dir=tmp_path).learn(max_iterations=1)
    with pytest.raises(ValueError, match="MASFOLS.load takes env_fn, verbose and eval_workers, not \\['seed'\\]"):
        MASFOLS.load(tmp_path, ParallelChainEnv(2), seed=1)


def test_fixed_weights_evaluate_each_agent_on_its_own_policies_and_keep_every_policy():
    model = make(steps=200, weights=[0.3, 0.7], test_weights=None).learn(max_iterations=3)  # tested at [0.3, 0.7]
    assert len(model.history) == 3  # fixed weights never end by themselves
    assert len(model.policy_set) == 3 * 2  # every policy of every agent, duplicate values included
    assert len(model.callback.schedule.ols.values) < len(model.policy_set)  # there were duplicates
    for info in model.policy_set.infos:
        np.testing.assert_allclose(info.weights, [0.3, 0.7])
    for row in model.history:
        assert row["weights_trained"] == {"agent_0": [0.3, 0.7], "agent_1": [0.3, 0.7]}
        (entry,) = row["test"]
        assert entry["weights"] == [0.3, 0.7]
    for agent, returns in model.history[-1]["test"][0]["agents"].items():
        own = model.policy_set.agent_policies(agent)
        assert {info.agent for info in own.infos} == {agent}
        np.testing.assert_allclose(returns["undiscounted"], chain_return(own, [0.3, 0.7]))


def test_learn_refuses_a_run_dir_that_already_holds_a_run(tmp_path):
    make(steps=20, weights="random", run_dir=tmp_path).learn(max_iterations=1)
    config = (tmp_path / "run.json").read_bytes()
    again = make(steps=20, weights="random", run_dir=tmp_path)
    with pytest.raises(ValueError, match="already holds a run"):
        again.learn(max_iterations=1)
    assert (tmp_path / "run.json").read_bytes() == config  # the run's description is not overwritten


@pytest.mark.parametrize(
    ("learner_kwargs", "message"),
    [
        ({"policy_kwargs": {"activation_fn": th.nn.Tanh}}, "policy argument 'activation_fn' is not taken"),
        ({"replay_buffer_class": MOReplayBuffer}, "'replay_buffer_class' must be one of MOReplayBuffer, Prioritized"),
        ({"verbose": 1}, "learner argument 'verbose' is not taken"),
    ],
)
def test_a_run_dir_refuses_learner_arguments_its_run_file_cannot_give_back(tmp_path, learner_kwargs, message):
    """A resume builds the learners from run.json alone: what it cannot hold (a class) is refused before training."""
    with pytest.raises(ValueError, match=f"MASFOLS with a run_dir: {message}"):
        MASFOLS(ParallelChainEnv(2), policy="MlpPolicy", learner_kwargs=learner_kwargs, run_dir=tmp_path)
    assert not (tmp_path / "run.json").exists()
    MASFOLS(ParallelChainEnv(2), policy="MlpPolicy", learner_kwargs=learner_kwargs)  # without one: any SFDQN argument


@pytest.mark.parametrize("weights", ["greedy", "OLS", ""])
def test_a_bad_weights_string_is_refused(weights):
    with pytest.raises(ValueError, match="'ols', 'random'"):
        make(weights=weights)


def test_load_refuses_a_directory_that_is_not_a_run(tmp_path):
    with pytest.raises(ValueError, match="not a run directory"):
        MASFOLS.load(tmp_path, ParallelChainEnv(2))
    (tmp_path / "run.json").write_text(json.dumps({"format": "sb3-sfgpi/run", "version": 1, "domain": "chain"}))
    with pytest.raises(ValueError, match="lacks the settings"):
        MASFOLS.load(tmp_path, ParallelChainEnv(2))


def test_a_second_learn_continues_or_is_refused():
    model = make(steps=100, weights="random").learn(max_iterations=1)
    try:
        model.learn(max_iterations=2)  # "iterations in all, those of a continued run included"
    except ValueError:
        return  # refusing is fine too
    assert len(model.history) == 2
    assert model.runner.num_timesteps == 200
    assert len(model.callback.schedule.ols.values) >= 1  # the values of Π are still recorded


# --- logs across resumes -----------------------------------------------------------------------------------------
def test_an_existing_runs_logs_survive_a_refused_learn_and_a_load(tmp_path):
    make(steps=50, weights="random", run_dir=tmp_path).learn(max_iterations=2)
    progress = tmp_path / "logs" / "progress.csv"
    before = progress.read_text()
    assert len(before.splitlines()) == 3  # header and one row per iteration
    with pytest.raises(ValueError, match="already holds a run"):
        make(steps=50, weights="random", run_dir=tmp_path).learn(max_iterations=2)
    assert progress.read_text() == before
    MASFOLS.load(tmp_path, ParallelChainEnv(2)).learn(max_iterations=3)
    assert len(progress.read_text().splitlines()) == 4
    software = json.loads((tmp_path / "software.json").read_text())  # the new run's process, then the resumed one's
    assert [record["from_iteration"] for record in software] == [0, 2]
    assert all(record["torch"] == th.__version__ and record["numpy"] == np.__version__ for record in software)


def test_a_killed_iterations_logs_are_replaced_on_resume(tmp_path):
    make(steps=50, weights="random", run_dir=tmp_path).learn(max_iterations=2)
    progress = tmp_path / "logs" / "progress.csv"
    finished = progress.read_text()
    progress.write_text(finished + finished.splitlines(keepends=True)[-1])  # a row logged, then killed: no checkpoint
    tensorboard = tmp_path / "tensorboard"
    for agent in ("agent_0", "agent_1"):  # the killed attempt at iteration 3 had started its TensorBoard logs
        (tensorboard / f"{agent}_iter003_1").mkdir()
        (tensorboard / f"{agent}_iter003_1" / "events.out.tfevents.killed").write_text("partial")
    killed_scalars = TensorBoardOutputFormat(str(tmp_path / "logs"))  # its OLS scalars too
    killed_scalars.write({"ols/iteration": 3}, {"ols/iteration": ()}, step=3)
    killed_scalars.close()
    MASFOLS.load(tmp_path, ParallelChainEnv(2)).learn(max_iterations=3)
    rows = progress.read_text().splitlines()
    assert progress.read_text().startswith(finished) and len(rows) == 4
    folders = sorted(folder.name for folder in tensorboard.iterdir())
    assert folders == [f"{agent}_iter{i:03d}_1" for agent in ("agent_0", "agent_1") for i in (1, 2, 3)]
    assert not list(tensorboard.glob("*/events.out.tfevents.killed"))
    assert scalar_steps(tmp_path / "logs", "ols/iteration") == [1, 2, 3]
    assert scalar_steps(tmp_path / "logs", "ols/mean_return") == [1, 2, 3]


def test_learners_log_their_learning_curve_during_the_iteration(tmp_path):
    make(steps=300, weights="random", run_dir=tmp_path).learn(max_iterations=1)
    steps = scalar_steps(tmp_path / "tensorboard" / "agent_0_iter001_1", "rollout/ep_rew_mean")
    # chain episodes take a few steps: a point every 4 episodes (SB3's log_interval), not one at the end
    assert len(steps) >= 5 and steps == sorted(steps) and steps[-1] <= 300


def test_training_without_a_run_directory_leaves_no_logger_folders(tmp_path, monkeypatch):
    monkeypatch.setenv("SB3_LOGDIR", str(tmp_path / "sb3"))  # where SB3's configure() would create its folder
    make(steps=50, weights="random").learn(max_iterations=2)
    assert not (tmp_path / "sb3").exists()


@pytest.mark.parametrize("sharing", ["independent", "shared"])
def test_replay_holds_one_iteration_and_learns_what_a_larger_buffer_does(monkeypatch, sharing):
    capped = make(steps=150, weights="random", sharing=sharing)
    capped.learn(max_iterations=2)
    positions = {learner.replay_buffer.buffer_size for learner in capped.runner.learners.values()}
    assert positions == {151}  # steps of the learner's slots (SB3 divides buffer_size by n_envs)
    monkeypatch.setattr(masfols, "replay_sized", lambda kwargs, steps, slots: dict(kwargs))  # as before: 10,000
    larger = make(steps=150, weights="random", sharing=sharing)
    larger.learn(max_iterations=2)
    assert {learner.replay_buffer.buffer_size for learner in larger.runner.learners.values()} == {
        10_000 // len(capped.runner.slots[name]) for name in capped.runner.learners
    }
    assert [row["mean_return"] for row in capped.history] == [row["mean_return"] for row in larger.history]
    np.testing.assert_array_equal(capped.policy_set.successor_features(OBS), larger.policy_set.successor_features(OBS))

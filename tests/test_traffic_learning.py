"""Learning and evaluation on the real SUMO traffic env: parallel evaluation, `train traffic`, the fixed-weight
baseline, `compare` and its plots, and recovery from a simulator crash. Short episodes, tiny budgets."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.torch_layers import FlattenExtractor

pytest.importorskip("libsumo")

from sfgpi_envs.traffic import TrafficSignalEnv, run_program_episode  # noqa: E402

from sb3_sfgpi.cli import main  # noqa: E402
from sb3_sfgpi.evaluation_jobs import EvaluationJob, ParallelEvaluator, evaluate_gpi_parallel, run_job  # noqa: E402
from sb3_sfgpi.gpi import GPIPolicy  # noqa: E402
from sb3_sfgpi.multiagent import MultiAgentRunner  # noqa: E402
from sb3_sfgpi.sfdqn import SFNetwork  # noqa: E402

ENV_KWARGS = {"num_seconds": 40, "reward_scale": 0.02}
# 2 iterations of 16 joint steps on 40 s episodes (8 decisions), 3 test weights, learning from the 8th step.
TINY = [
    "--iterations", "2", "--steps-per-iteration", "16", "--set", "n_test_weights=3", "--no-progress", "--seed", "3",
    "--env", "num_seconds=40", "--learner", "learning_starts=12", "--learner", "batch_size=8",
]  # fmt: skip
#: every policy joins Π, as the tests below count them (validation and pruning: tests/test_validation.py)
ALL_JOIN = ["--set", "validation_weights=0"]


def _random_policy_set(tmp_path):
    """Two random SF networks per traffic light, on the env's spaces, saved in tmp_path / "set"."""
    env = TrafficSignalEnv(**ENV_KWARGS)
    policy_set = GPIPolicy()
    for i, agent in enumerate(env.possible_agents * 2):
        th.manual_seed(i)
        extractor = FlattenExtractor(env.observation_space(agent))
        space = env.observation_space(agent)
        net = SFNetwork(space, env.action_space(agent), extractor, extractor.features_dim, 2, net_arch=[16])
        policy_set.add(net, weights=[1 - i / 5, i / 5], agent=agent, iteration=i // 3)
    env.close()
    policy_set.save(tmp_path / "set")
    return policy_set


def _same_returns(a, b):
    assert a.discounted.keys() == b.discounted.keys()
    for agent in a.discounted:
        np.testing.assert_array_equal(a.discounted[agent], b.discounted[agent])
        np.testing.assert_array_equal(a.undiscounted[agent], b.undiscounted[agent])
    assert a.final_infos == b.final_infos
    assert a.step_infos == b.step_infos


def test_parallel_evaluation_equals_in_process(tmp_path):
    policy_set = _random_policy_set(tmp_path)
    weights, seeds = [[1.0, 0.0], [0.3, 0.7], [0.0, 1.0]], [5, 6, 7]
    # each agent over its own policies only; and a program baseline, which needs no policy
    own = EvaluationJob(5, (0.5, 0.5), 1, str(tmp_path / "set"), own_policies=True)
    program = EvaluationJob(9, None, 1, env_overrides={"signal_control": "actuated"})
    with ParallelEvaluator(TrafficSignalEnv, ENV_KWARGS, workers=2, gamma=0.95) as evaluator:
        parallel = evaluate_gpi_parallel(
            TrafficSignalEnv, ENV_KWARGS, tmp_path / "set", weights, 0.95, seeds, 2, record_infos=True,
            evaluator=evaluator,
        )  # fmt: skip
        own_parallel, program_parallel = evaluator.run([own, program])
    env = TrafficSignalEnv(**ENV_KWARGS)
    try:
        for w, seed, result in zip(weights, seeds, parallel, strict=True):
            job = EvaluationJob(seed, tuple(w), 2, str(tmp_path / "set"), record_infos=True)
            _same_returns(result, run_job(env, job, 0.95, policy_set))
            assert len(result.final_infos) == 2 and "episode" in result.final_infos[0]["J1"]
            trace = result.step_infos[0]["J2"]
            assert trace["time"] == [5.0 * k for k in range(1, 9)] and len(trace["pedestrian_wait_total"]) == 8
        _same_returns(own_parallel, run_job(env, own, 0.95))
    finally:
        env.close()
    assert program_parallel.final_infos[0]["J1"]["episode"] == run_program_episode("actuated", seed=9, **ENV_KWARGS)


def test_reward_scale_per_objective():
    rewards = {}
    for scale in (1.0, (0.5, 2.0)):
        env = TrafficSignalEnv(num_seconds=200, reward_scale=scale)  # pedestrians reach J1 after ~2 minutes
        env.reset(seed=3)
        rewards[scale] = [env.step({a: int(k % 4 == 0) for a in env.agents})[1]["J1"] for k in range(40)]
        metrics = env.episode_metrics()
        env.close()
    raw = np.array(rewards[1.0])
    assert np.abs(raw).sum(axis=0).min() > 0  # both objectives moved
    np.testing.assert_allclose(np.array(rewards[(0.5, 2.0)]), raw * [0.5, 2.0], rtol=1e-6)
    assert metrics["vehicle_waiting_time_total"] >= 0  # metrics stay in seconds
    for bad in (0.0, -1.0, float("nan"), (1.0,), (1.0, 0.0), True):
        with pytest.raises(ValueError, match="reward_scale"):
            TrafficSignalEnv(reward_scale=bad)


def test_ccs_policies_keeps_the_undominated_policies(tmp_path):
    policy_set = _random_policy_set(tmp_path)  # 6 policies; give them values: 2 on the CCS, 1 duplicate, 3 dominated
    values = [[-1.0, -5.0], [-3.0, -3.0], [-5.0, -1.0], [-5.0, -1.0], [-6.0, -6.0], [-4.0, -4.0]]
    for i, value in enumerate(values):
        policy_set.infos[i] = policy_set.infos[i].__class__(policy_set.infos[i].weights, np.array(value), "J1", i)
    subset = policy_set.ccs_policies()
    assert [info.iteration for info in subset.infos] == [0, 2]  # [-3, -3] is below the segment of the others
    obs = np.zeros((1, 15), dtype=np.float32)
    np.testing.assert_array_equal(subset.successor_features(obs), policy_set.successor_features(obs)[[0, 2]])


def _evaluation(run_dir):
    """evaluation.json without the wall-clock times."""
    rows = json.loads((run_dir / "evaluation.json").read_text())
    return [{k: v for k, v in row.items() if k not in ("wall_time", "eval_time")} for row in rows]


def test_train_traffic_workers_crash_and_resume(tmp_path, monkeypatch, capsys):
    """`train traffic` writes a run; evaluating in workers or in-process gives the same run; a SUMO crash keeps
    the last checkpoint and --resume finishes exactly the run that was never interrupted."""
    train = ["train", "traffic", *TINY, *ALL_JOIN, "--algo", "random"]  # random weights: never ends before the cap
    reference, parallel, crashed = tmp_path / "in-process", tmp_path / "workers", tmp_path / "crashed"
    assert main([*train, "--set", "eval_workers=0", "--out", str(reference)]) == 0
    assert main([*train, "--set", "eval_workers=2", "--out", str(parallel)]) == 0
    config = json.loads((parallel / "run.json").read_text())
    assert config["env_kwargs"]["num_seconds"] == 40 and config["eval_workers"] == 2
    checkpoint = json.loads((parallel / "checkpoint.json").read_text())
    assert checkpoint["iteration"] == 2 and checkpoint["timesteps"] == 32
    assert len((parallel / "evaluation.csv").read_text().splitlines()) == 3
    assert 1 <= len(GPIPolicy.load(parallel / "policy_set")) == checkpoint["n_policies"] <= 6
    assert (parallel / "logs" / "progress.csv").exists() and any((parallel / "tensorboard").iterdir())
    evaluation = _evaluation(parallel)
    assert len(evaluation) == 2 and len(evaluation[0]["test"]) == 3
    assert set(evaluation[0]["test"][0]["agents"]) == {"J1", "J2", "J3"}
    assert "vehicle_waiting_time_mean" in evaluation[0]["test"][0]["final_infos"][0]["J1"]["episode"]
    assert evaluation == _evaluation(reference)

    step = MultiAgentRunner.step

    def crash_in_second_iteration(self, *chosen):
        if self.num_timesteps == 20:
            self.env.sim.close()  # the simulation dies under the env
        return step(self, *chosen)

    monkeypatch.setattr(MultiAgentRunner, "step", crash_in_second_iteration)
    capsys.readouterr()
    assert main([*train, "--set", "eval_workers=0", "--out", str(crashed)]) == 1
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1
    assert "SUMO simulation stopped unexpectedly" in error and "1 done" in error and "--resume" in error
    checkpoint = json.loads((crashed / "checkpoint.json").read_text())
    assert checkpoint["iteration"] == 1 and checkpoint["timesteps"] == 16
    assert len(GPIPolicy.load(crashed / "policy_set")) >= checkpoint["n_policies"]

    monkeypatch.setattr(MultiAgentRunner, "step", step)
    assert main([*train, "--set", "eval_workers=0", "--out", str(crashed), "--resume"]) == 0
    assert json.loads((crashed / "checkpoint.json").read_text())["iteration"] == 2
    assert _evaluation(crashed) == _evaluation(reference)  # exactly the run that was never interrupted


def test_fixed_weight_learners_compare_and_plots(tmp_path):
    masfols, fixed = tmp_path / "masfols", tmp_path / "fixed"
    assert main(["train", "traffic", *TINY, *ALL_JOIN, "--set", "eval_workers=0", "--out", str(masfols)]) == 0
    in_process = ["--set", "eval_workers=0"]  # workers: test_parallel_evaluation_equals_in_process
    assert (
        main(["train", "traffic", *TINY, *in_process, "--algo", "fixed", "--w", "0.4", "0.6", "--out", str(fixed)]) == 0
    )
    config = json.loads((fixed / "run.json").read_text())
    # the same steps per agent as an MA-SFOLS run of this budget, in one iteration
    assert (config["iterations"], config["steps_per_iteration"], config["weights"]) == (1, 32, [0.4, 0.6])
    taken = json.loads((masfols / "checkpoint.json").read_text())["timesteps"]  # OLS may end before the cap
    budget = ["--budget-from", str(masfols), "--out", str(tmp_path / "budget"), "--iterations", "1"]
    assert (
        main(
            ["train", "traffic", "--algo", "fixed", "--w", "1", "0", *budget, *in_process, "--steps-per-iteration", "1"]
        )
        == 0
    )
    assert json.loads((tmp_path / "budget" / "run.json").read_text())["steps_per_iteration"] == taken
    policy_set = GPIPolicy.load(fixed / "policy_set")
    assert [info.agent for info in policy_set.infos] == ["J1", "J2", "J3"]
    assert all(np.allclose(info.weights, [0.4, 0.6]) for info in policy_set.infos)
    assert json.loads((fixed / "evaluation.json").read_text())[0]["test"][0]["weights"] == [0.4, 0.6]

    output = tmp_path / "compare.json"
    argv = ["compare", str(masfols), "--fixed", str(fixed), "--w", "1", "0", "--w", "0", "1", "--episodes", "2"]
    assert main([*argv, "--workers", "0", "-o", str(output)]) == 0
    compare = json.loads(output.read_text())
    labels = [row["label"] for row in compare["rows"]]
    assert labels == [
        "GPI w=[1,0]", "GPI w=[0,1]", "GPI w=[0.4,0.6]", "scalarized w=[0.4,0.6]", "fixed-time", "actuated",
        "max-pressure",
    ]  # fmt: skip
    for row in compare["rows"]:
        assert set(row["episode_metrics"]) == {"vehicle_waiting_time_mean", "pedestrian_waiting_time_mean"}
        assert len(row["traces"]["time"]) == len(row["traces"]["vehicle_wait_total"]["mean"]) == 8
    fixed_time = compare["rows"][4]["episode_metrics"]["vehicle_waiting_time_mean"]["mean"]
    expected = np.mean([run_program_episode("fixed-time", seed=s, **ENV_KWARGS)["vehicle_waiting_time_mean"]
                        for s in (1000, 1001)])  # fmt: skip
    assert fixed_time == pytest.approx(expected)

    figures = tmp_path / "figures"
    assert main(["plot", str(output), "--kind", "steps", "-o", str(figures)]) == 0
    assert main(["plot", str(output), "--kind", "versus", "-o", str(figures)]) == 0
    assert main(["plot", str(output), "--kind", "tradeoff", "-o", str(figures / "tradeoff.png")]) == 0
    assert main(["plot", str(masfols), "-o", str(figures / "returns.png")]) == 0
    names = sorted(p.name for p in figures.iterdir())
    assert names == [
        "returns.png", "steps_pedestrian_delay.png", "steps_pedestrian_delay_zoom.png", "steps_vehicle_delay.png",
        "steps_vehicle_delay_zoom.png", "tradeoff.png", "versus_w0.4-0.6.png",
    ]  # fmt: skip
    assert all((figures / n).read_bytes()[:4] == b"\x89PNG" for n in names)

"""The benchmarks' resumable GPI-LS: the same run as morl-baselines' own ``train``, and the same again when cut after an
iteration and continued from its checkpoint."""

from __future__ import annotations

import random
import sys
from pathlib import Path

import numpy as np
import pytest
import torch as th

gpi_pd = pytest.importorskip("morl_baselines.multi_policy.gpi_pd.gpi_pd")
if str(Path(__file__).resolve().parents[1]) not in sys.path:  # the benchmarks are not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import bench_known_fronts as bench  # noqa: E402
from benchmarks.gpi_ls_runs import train_gpi_ls  # noqa: E402

STEPS, ITERATIONS = 150, 3
SETTINGS = bench.GPI_LS_SETTINGS | {"net_arch": [16, 16], "buffer_size": 1_000, "epsilon_decay_steps": 300}


def _agent() -> gpi_pd.GPIPD:
    bench.seed_peer_generators(0)
    env = bench._seeded_env(bench.PROBLEMS["deep-sea-treasure-mlp"], 0)
    agent = gpi_pd.GPIPD(env, gamma=0.98, gradient_updates=2, seed=0, log=False, device="cpu", **SETTINGS)
    bench.drop_sampled_indices(agent)
    return agent


def _eval_env():
    return bench._seeded_env(bench.PROBLEMS["deep-sea-treasure-mlp"], 1)


def _state(agent: gpi_pd.GPIPD) -> tuple:
    networks = [value.numpy().copy() for net in agent.q_nets for value in net.state_dict().values()]
    return agent.global_step, [tuple(w) for w in agent.weight_support], networks


def _same(first: tuple, second: tuple) -> bool:
    return first[:2] == second[:2] and all(np.array_equal(a, b) for a, b in zip(first[2], second[2], strict=True))


@pytest.fixture(scope="module")
def theirs() -> tuple:
    agent = _agent()
    agent.train(
        total_timesteps=STEPS * ITERATIONS, eval_env=_eval_env(), ref_point=np.zeros(2), timesteps_per_iter=STEPS,
        weight_selection_algo="gpi-ls", checkpoints=False,
    )  # fmt: skip
    return _state(agent)


def test_the_loop_is_morl_baselines_own(theirs):
    run = train_gpi_ls(_agent, _eval_env, {"seed": 0}, STEPS, ITERATIONS)
    assert run.iterations == ITERATIONS and run.wall_time > 0
    assert _same(_state(run.agent), theirs)


def test_a_run_cut_after_an_iteration_goes_on_to_the_same_end_from_its_checkpoint(theirs, tmp_path):
    checkpoint = tmp_path / "peer.pkl"
    cut = train_gpi_ls(_agent, _eval_env, {"seed": 0}, STEPS, 1, checkpoint)
    assert cut.iterations == 1 and checkpoint.exists()
    random.seed(99), np.random.seed(99), th.manual_seed(99)  # noqa: NPY002 - another session's generators
    again = train_gpi_ls(pytest.fail, _eval_env, {"seed": 0}, STEPS, ITERATIONS, checkpoint)  # no new agent
    assert again.iterations == ITERATIONS and again.wall_time > cut.wall_time
    assert _same(_state(again.agent), theirs)
    with pytest.raises(ValueError, match="other settings"):
        train_gpi_ls(_agent, _eval_env, {"seed": 1}, STEPS, ITERATIONS, checkpoint)

"""Four-Room's batched episodes (compiled moves for many episodes) against the env's own step, and GPI's rollouts on
them against one env per episode (``run_lockstep`` either way): the same numbers, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sfgpi_envs.four_room import FourRoomParallelEnv

from sb3_sfgpi.common.rollouts import batched_episodes, run_lockstep

SETTINGS = st.fixed_dictionaries(
    {
        "observation_mode": st.sampled_from(["xy", "own", "full"]),
        "starts": st.sampled_from([None, [(0, 9), (9, 12)], [(3, 3), (3, 3)], [(0, 11), (1, 12)]]),
        "max_steps": st.integers(1, 120),
        "goal_reward": st.sampled_from([(1.0, 1.0, 1.0), (0.5, -2.0, 3.25)]),
    }
)


def random_policy(seed: int):
    """A policy whose actions come from a generator of its own: two runs that call it alike get the same actions."""
    rng = np.random.default_rng(seed)

    def act(obs: np.ndarray, weights: np.ndarray, masks: np.ndarray | None, agents: list[str]) -> np.ndarray:
        assert masks is None and len(obs) == len(weights) == len(agents)
        return rng.integers(0, 4, len(obs))

    return act


@settings(max_examples=40, deadline=None)
@given(kwargs=SETTINGS, n=st.integers(1, 6), seed=st.integers(0, 2**16))
def test_batched_episodes_step_as_the_env_does(kwargs, n, seed):
    """Every episode of the batch sees the observations, rewards, ends and infos of an env stepped alike."""
    envs = [FourRoomParallelEnv(**kwargs) for _ in range(n)]
    batch = envs[0].batched_episodes(n)
    observations, live = batch.reset(list(range(n)))
    expected, last_infos = zip(*(env.reset(seed=i) for i, env in enumerate(envs)), strict=True)
    expected, last_infos = list(expected), [dict(infos) for infos in last_infos]
    rng = np.random.default_rng(seed)
    while live.any():
        for e, env in enumerate(envs):
            assert [batch.agents[k] for k in np.flatnonzero(live[e])] == env.agents
            for agent in env.agents:
                np.testing.assert_array_equal(observations[e, batch.agents.index(agent)], expected[e][agent])
        actions = rng.integers(0, 4, live.shape)
        stepped = [e for e, env in enumerate(envs) if env.agents]
        steps = [envs[e].step({a: int(actions[e, batch.agents.index(a)]) for a in envs[e].agents}) for e in stepped]
        rewards, live = batch.step(actions)
        observations = batch.observations()
        for e, (obs, step_rewards, terminations, _, infos) in zip(stepped, steps, strict=True):
            expected[e] = obs
            last_infos[e].update(infos)
            for agent, reward in step_rewards.items():
                k = batch.agents.index(agent)
                assert rewards[e, k].dtype == reward.dtype and rewards[e, k].tobytes() == reward.tobytes()
                assert bool(batch.terminated[e, k]) == terminations[agent]
    for e, (infos, env) in enumerate(zip(batch.final_infos(), envs, strict=True)):
        np.testing.assert_array_equal(batch.present[e], env.objects_present)
        for agent, info in last_infos[e].items():
            np.testing.assert_array_equal(infos[agent]["collected"], info["collected"])


@settings(max_examples=25, deadline=None)
@given(kwargs=SETTINGS, n_weights=st.integers(1, 4), per_result=st.integers(1, 3), seed=st.integers(0, 2**16))
def test_lockstep_on_batched_episodes_gives_the_envs_returns_bit_for_bit(kwargs, n_weights, per_result, seed):
    """The same decisions (rows, order, episodes) and the same discounted and plain returns and final infos."""
    n = n_weights * per_result
    weights = np.random.default_rng(seed).dirichlet(np.ones(3), n)
    seeds = [seed + i for i in range(n)]
    rows: list[list[int]] = []
    batched = run_lockstep(
        FourRoomParallelEnv(**kwargs).batched_episodes(n), random_policy(seed), weights, seeds, 0.95, per_result,
        rows.append,
    )  # fmt: skip
    expected_rows: list[list[int]] = []
    envs = [FourRoomParallelEnv(**kwargs) for _ in range(n)]
    expected = run_lockstep(envs, random_policy(seed), weights, seeds, 0.95, per_result, expected_rows.append)
    assert rows == expected_rows
    for got, want in zip(batched, expected, strict=True):
        assert got.discounted.keys() == want.discounted.keys()
        for agent in want.discounted:
            assert got.discounted[agent].tobytes() == want.discounted[agent].tobytes()
            assert got.undiscounted[agent].tobytes() == want.undiscounted[agent].tobytes()
        for got_infos, want_infos in zip(got.final_infos, want.final_infos, strict=True):
            for agent, info in want_infos.items():
                np.testing.assert_array_equal(got_infos[agent]["collected"], info["collected"])


def test_only_the_env_class_itself_offers_batched_episodes():
    """A wrapper may change observations or rewards: its episodes are not the arrays' (None)."""
    from pettingzoo.utils.wrappers import BaseParallelWrapper

    env = FourRoomParallelEnv()
    assert batched_episodes(env, 3) is not None
    assert batched_episodes(BaseParallelWrapper(env), 3) is None


def test_bad_actions_and_seeds_are_refused():
    batch = FourRoomParallelEnv().batched_episodes(2)
    with pytest.raises(ValueError, match="2 episodes, got 3 seeds"):
        batch.reset([0, 1, 2])
    batch.reset([0, 1])
    with pytest.raises(ValueError, match="actions are 0"):
        batch.step(np.array([[0, 4], [1, 1]]))

"""MOReplayBuffer: vector rewards stored and sampled where SB3's ReplayBuffer cannot, refusals."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from momdp import N_STATES, Fig1MOMDP
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.vec_env import MODummyVecEnv


def fill_buffer(buffer, n: int) -> np.ndarray:
    rewards = np.arange(2 * n, dtype=np.float32).reshape(n, 1, 2)
    for i in range(n):
        buffer.add(np.array([i % 4]), np.array([i % 4 + 1]), np.array([[i % 3]]), rewards[i], np.array([0.0]), [{}])
    return rewards[:, 0]


def test_mo_replay_buffer_samples_vector_rewards():
    observation_space, action_space = gym.spaces.Discrete(N_STATES), gym.spaces.Discrete(3)
    buffer = MOReplayBuffer(100, observation_space, action_space, device="cpu", reward_dim=2)
    stored = fill_buffer(buffer, 20)
    samples = buffer.sample(64)
    assert samples.rewards.shape == (64, 2)
    # Each sampled reward vector is the one stored with the sampled transition (rewards are 2i, 2i+1).
    index = (samples.rewards[:, 0] / 2).long().numpy()
    np.testing.assert_array_equal(samples.rewards.numpy(), stored[index])
    np.testing.assert_array_equal(samples.observations.flatten().numpy(), index % 4)

    # SB3's ReplayBuffer cannot do this: it refuses vector rewards or samples them with the wrong shape.
    sb3_buffer = ReplayBuffer(100, observation_space, action_space, device="cpu")
    try:
        fill_buffer(sb3_buffer, 20)
        sb3_shape = tuple(sb3_buffer.sample(64).rewards.shape)
    except ValueError:
        sb3_shape = None
    assert sb3_shape != (64, 2)


@pytest.mark.parametrize("shape", [(1,), (1, 3), (2, 2), (2,)])
def test_mo_replay_buffer_refuses_mismatched_rewards(shape):
    buffer = MOReplayBuffer(10, gym.spaces.Discrete(N_STATES), gym.spaces.Discrete(3), device="cpu", reward_dim=2)
    with pytest.raises(ValueError, match="reward"):
        buffer.add(np.array([0]), np.array([1]), np.array([[0]]), np.zeros(shape, np.float32), np.array([0.0]), [{}])
    assert buffer.pos == 0


def test_mo_replay_buffer_refuses_reward_normalisation():
    buffer = MOReplayBuffer(10, gym.spaces.Discrete(N_STATES), gym.spaces.Discrete(3), device="cpu", reward_dim=2)
    fill_buffer(buffer, 3)
    venv = VecNormalize(MODummyVecEnv([Fig1MOMDP]), norm_obs=False, norm_reward=True)
    with pytest.raises(ValueError, match="norm_reward"):
        buffer.sample(4, env=venv)


@pytest.mark.parametrize("optimize_memory_usage", [False, True], ids=["separate-next-obs", "optimize-memory"])
@pytest.mark.parametrize("n_added", [5, 12], ids=["partly-filled", "wrapped-around"])
def test_stored_arrays_returns_every_valid_stored_transition(optimize_memory_usage, n_added):
    buffer = MOReplayBuffer(
        16, gym.spaces.Discrete(200), gym.spaces.Discrete(3), device="cpu", n_envs=2, reward_dim=2,
        optimize_memory_usage=optimize_memory_usage, handle_timeout_termination=False,
    )  # fmt: skip
    for i in range(n_added):  # 8 steps of 2 envs fit; env e at step i: obs 10 i + e, next obs 10 (i + 1) + e
        obs = np.array([[10 * i], [10 * i + 1]])
        rewards = np.array([[i, 0], [i, 1]], dtype=np.float32)
        buffer.add(obs, obs + 10, np.array([[i % 3], [(i + 1) % 3]]), rewards, np.array([0.0, 0.0]), [{}, {}])
    obs, actions, next_obs, dones, rewards = buffer.stored_arrays()
    # Once full, one array for obs and next obs loses the oldest step's next observation to the newest step.
    kept = range(max(0, n_added - 8 + optimize_memory_usage * (n_added > 8)), n_added)
    expected = sorted((10 * i + e, (i + e) % 3, 10 * (i + 1) + e, i, e) for i in kept for e in (0, 1))
    got = sorted(
        zip(obs.reshape(-1).tolist(), actions.tolist(), next_obs.reshape(-1).tolist(), *rewards.T.tolist(), strict=True)
    )
    assert got == [tuple(float(x) if k >= 3 else x for k, x in enumerate(row)) for row in expected]
    assert not dones.any()


@pytest.mark.parametrize(
    "space, dtype",
    [
        (gym.spaces.MultiDiscrete([13, 13] + [2] * 12), np.uint8),  # the four-room preset's observations
        (gym.spaces.Discrete(40_000), np.int32),  # no uint16: torch supports it in part only
        (gym.spaces.Box(-3, 70_000, shape=(2,), dtype=np.int64), np.int32),
        (gym.spaces.Discrete(300, start=-5), np.int16),
        (gym.spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float32), np.float32),  # not an integer space: as SB3's
    ],
)
def test_integer_observations_are_stored_in_the_smallest_dtype_and_read_back_unchanged(space, dtype):
    buffer = MOReplayBuffer(50, space, gym.spaces.Discrete(2), device="cpu", reward_dim=2)
    assert buffer.observations.dtype == buffer.next_observations.dtype == dtype
    space.seed(0)
    observations = [space.sample() for _ in range(21)]
    for obs, next_obs in zip(observations[:-1], observations[1:], strict=True):
        buffer.add(obs[None], next_obs[None], np.array([[1]]), np.ones((1, 2)), np.array([0.0]), [{}])
    obs, _, next_obs, _, _ = buffer.stored_arrays()
    assert obs.dtype == next_obs.dtype == space.dtype  # read back as the space's
    np.testing.assert_array_equal(obs.reshape(20, -1), np.reshape(observations[:-1], (20, -1)))
    np.testing.assert_array_equal(next_obs.reshape(20, -1), np.reshape(observations[1:], (20, -1)))

"""MOReplayBuffer: vector rewards stored and sampled where SB3's ReplayBuffer cannot, refusals."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import N_STATES, Fig1MOMDP
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.prioritized_buffer import PrioritizedMOReplayBuffer
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


# --------------------------------------------------------------------------------------------------------------
# n-step returns
# --------------------------------------------------------------------------------------------------------------


def _expected_n_step(
    history: list[tuple], t: int, n_steps: int, gamma: float
) -> tuple[np.ndarray, float, float, float]:
    """
    One env's transition ``t`` of its ``history`` ((obs, reward, done, timeout, next obs) in order): the return of up
    to ``n_steps`` transitions, stopping after one that ends its episode or at the last stored, the observation after
    them, their last one's termination, and ``γ^m``.
    """
    total, m = np.zeros(2), 0
    while True:
        _, reward, done, timeout, next_obs = history[t + m]
        total += gamma**m * reward
        m += 1
        if done or m == n_steps or t + m == len(history):
            return total, next_obs, float(done and not timeout), gamma**m


@settings(max_examples=60, deadline=None)
@given(
    n_envs=st.integers(1, 3),
    n_steps=st.integers(1, 4),
    size=st.integers(2, 6),
    ends=st.lists(st.sampled_from(["", "done", "truncated"]), min_size=1, max_size=40),
    gamma=st.sampled_from([1.0, 0.9, 0.5]),
)
def test_n_step_samples_are_the_discounted_returns_of_each_episode_up_to_n_transitions(
    n_envs, n_steps, size, ends, gamma
):
    buffer = PrioritizedMOReplayBuffer(
        size * n_envs, spaces.Box(-1.0, 1e6, (1,)), spaces.Discrete(2), device="cpu", n_envs=n_envs, reward_dim=2,
        n_steps=n_steps, gamma=gamma,
    )  # fmt: skip
    histories: list[list[tuple]] = [[] for _ in range(n_envs)]
    stored = {}  # flat row -> (env, index in its history)
    for step, end in enumerate(ends):
        envs = np.arange(n_envs)
        obs, next_obs = (step * n_envs + envs).astype(np.float32), (1000 + step * n_envs + envs).astype(np.float32)
        rewards = np.stack([step + envs, np.full(n_envs, (-1.0) ** step)], axis=1).astype(np.float32)
        dones = (envs == step % n_envs) & (end != "")  # one env a step may end its episode
        infos = [{"TimeLimit.truncated": bool(d and end == "truncated")} for d in dones]
        for env in envs:
            truncated = infos[env]["TimeLimit.truncated"]
            histories[env].append((obs[env], rewards[env], dones[env], truncated, next_obs[env]))
            stored[buffer._next_rows(n_envs)[env]] = (env, len(histories[env]) - 1)
        buffer.add(obs[:, None], next_obs[:, None], envs % 2, rewards, dones, infos)
    rows = buffer.stored_rows()
    samples = buffer.samples_at(rows)
    for i, row in enumerate(rows):
        env, t = stored[row]
        total, next_obs, done, discount = _expected_n_step(histories[env], t, n_steps, gamma)
        assert samples.observations[i, 0] == histories[env][t][0]
        np.testing.assert_allclose(samples.rewards[i].numpy(), total, rtol=1e-6)
        assert samples.next_observations[i, 0] == next_obs and samples.dones[i, 0] == done
        if n_steps == 1:
            assert samples.discounts is None  # one-step samples: the learner's γ
        else:
            assert samples.discounts[i, 0] == pytest.approx(discount)


def test_a_uniform_buffer_samples_n_step_returns_too():
    buffer = MOReplayBuffer(50, spaces.Box(-1.0, 100.0, (1,)), spaces.Discrete(2), device="cpu", reward_dim=2,
                            n_steps=3, gamma=0.5)  # fmt: skip
    for t in range(6):  # one episode of 4 transitions, then one of 2 still going
        reward = np.array([[t, 1.0]], dtype=np.float32)
        buffer.add(np.array([[t]]), np.array([[t + 1]]), np.array([0]), reward, np.array([t == 3]), [{}])
    samples = buffer.sample(200)
    by_start = {int(o): (r.tolist(), int(n), float(d), float(g)) for o, r, n, d, g in zip(
        samples.observations[:, 0], samples.rewards, samples.next_observations[:, 0], samples.dones[:, 0],
        samples.discounts[:, 0], strict=True)}  # fmt: skip
    assert by_start[0] == ([0 + 0.5 * 1 + 0.25 * 2, 1.75], 3, 0.0, 0.125)
    assert by_start[2] == ([2 + 0.5 * 3, 1.5], 4, 1.0, 0.25)  # the episode ends after 2 transitions: no bootstrap
    assert by_start[4] == ([4 + 0.5 * 5, 1.5], 6, 0.0, 0.25)  # nothing stored after step 5 yet
    assert by_start[5] == ([5, 1.0], 6, 0.0, 0.5)


def test_n_step_buffers_refuse_what_they_cannot_sample_right():
    space, actions = spaces.Box(-1.0, 1.0, (1,)), spaces.Discrete(2)
    with pytest.raises(ValueError, match="n_steps must be a positive integer, got 0"):
        MOReplayBuffer(10, space, actions, device="cpu", reward_dim=2, n_steps=0)
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        MOReplayBuffer(10, space, actions, device="cpu", reward_dim=2, n_steps=2, optimize_memory_usage=True)
    buffer = MOReplayBuffer(10, space, actions, device="cpu", n_envs=2, reward_dim=2, n_steps=2)
    with pytest.raises(ValueError, match="a transition of every env at every step, got 1 rows of 2"):
        buffer.add_rows(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(1), np.zeros((1, 2)), np.zeros(1), np.zeros(1))
    buffer.add_rows(np.zeros((2, 1)), np.zeros((2, 1)), np.zeros(2), np.zeros((2, 2)), np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="sample_arrays gives one-step transitions"):
        buffer.sample_arrays(4)

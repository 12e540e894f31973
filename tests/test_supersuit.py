"""PettingZoo envs wrapped with SuperSuit, as users hand them over: the reward space found through the wrappers,
black death's dead agents with zero reward vectors, SuperSuit's padded actions masked, and clear errors where a
wrapper cannot work with vector rewards."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces
from parallel_chain import ParallelChainEnv
from queue_lights import QueueLights

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.common.parallel_wrappers import as_parallel_env
from sb3_sfgpi.common.rollouts import run_episodes

ss = pytest.importorskip("supersuit")
mobeach_v0 = pytest.importorskip("momaland.envs.beach.mobeach_v0")

MLP = dict(learning_starts=20, batch_size=16, buffer_size=500, policy_kwargs=dict(net_arch=[16]))


class BoxChain(ParallelChainEnv):
    """The chain with one-hot Box observations (SuperSuit's black death needs Box spaces); agents finish one by one."""

    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(0.0, 1.0, (5,), np.float32)

    def reset(self, seed=None, options=None):
        observations, infos = super().reset(seed, options)
        return {a: np.eye(5, dtype=np.float32)[s] for a, s in observations.items()}, infos

    def step(self, actions):
        observations, *rest = super().step(actions)
        return ({a: np.eye(5, dtype=np.float32)[s] for a, s in observations.items()}, *rest)


class ImageChain(BoxChain):
    """The chain seen as 8 × 8 RGB images (the state's row lit), for SuperSuit's image wrappers."""

    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(0, 255, (8, 8, 3), np.uint8)

    def reset(self, seed=None, options=None):
        observations, infos = super().reset(seed, options)
        return {a: self._image(o) for a, o in observations.items()}, infos

    def step(self, actions):
        observations, *rest = super().step(actions)
        return ({a: self._image(o) for a, o in observations.items()}, *rest)

    @staticmethod
    def _image(one_hot: np.ndarray) -> np.ndarray:
        image = np.zeros((8, 8, 3), np.uint8)
        image[int(one_hot.argmax())] = 255
        return image


def test_resize_shrinks_image_observations_and_runs():
    env = as_parallel_env(ss.resize_v1(ImageChain(), 4, 4))
    assert env.observation_space("agent_0").shape == (4, 4, 3) and env.reward_space("agent_0").shape == (2,)
    returns = run_episodes(env, lambda obs: {agent: 0 for agent in obs}, 1, 0.9, seed=0)
    assert returns.discounted["agent_0"].shape == (1, 2)


@pytest.mark.parametrize(
    "wrap",
    [
        lambda env: ss.dtype_v0(env, np.float64),
        lambda env: ss.normalize_obs_v0(env),
        lambda env: ss.flatten_v0(env),
        lambda env: ss.frame_stack_v1(env, 2),
        lambda env: ss.pad_observations_v0(env),
    ],
    ids=["dtype", "normalize_obs", "flatten", "frame_stack", "pad_observations"],
)
def test_observation_wrappers_keep_the_reward_space_and_run(wrap):
    env = as_parallel_env(wrap(mobeach_v0.parallel_env(num_agents=2)))
    assert env.reward_space("agent_0") == mobeach_v0.parallel_env(num_agents=2).reward_space("agent_0")
    returns = run_episodes(env, lambda obs: {agent: 0 for agent in obs}, 1, 0.9, seed=0)
    assert returns.discounted["agent_0"].shape == (1, 2)


def test_black_deaths_dead_agents_get_the_zero_reward_vector():
    env = as_parallel_env(ss.black_death_v3(BoxChain(staggered=True)))
    env.reset(seed=0)
    rewards = []
    while env.agents:
        rewards.append(env.step({agent: 0 for agent in env.agents})[1])
    np.testing.assert_array_equal(rewards[3]["agent_1"], np.zeros(2))  # agent_1 (started at s1) left after step 3
    assert rewards[3]["agent_0"].tolist() == [1.0, 0.0]  # agent_0's own last reward
    with pytest.raises(ValueError, match="black_death_v3 needs Box observation spaces"):
        as_parallel_env(ss.black_death_v3(ParallelChainEnv()))


def test_supersuits_padded_actions_are_masked_and_never_taken():
    env = as_parallel_env(ss.pad_action_space_v0(QueueLights((2, 3))))
    _, infos = env.reset(seed=0)
    assert infos["light_0"]["action_mask"].tolist() == [True, True, False]
    assert "action_mask" not in infos["light_1"]  # its own three actions: nothing padded
    model = MASFOLS(
        ss.pad_action_space_v0(QueueLights((2, 3))), policy="TabularPolicy", steps_per_iteration=300, seed=0,
        learner_kwargs=dict(learning_starts=0, batch_size=8), test_weights=[[0.5, 0.5]],
    )  # fmt: skip
    model.learn(max_iterations=1)
    gpi, taken = model.policy_set.joint_policy([0.5, 0.5]), []

    def recorded(observations, action_masks=None):
        taken.append(gpi(observations, action_masks=action_masks))
        return taken[-1]

    run_episodes(env, recorded, 2, 0.9, seed=1)
    assert taken and all(step["light_0"] < 2 for step in taken)
    gem_mining_v0 = pytest.importorskip("momaland.envs.gem_mining.mogem_mining_v0")
    with pytest.raises(ValueError, match="ignores the start"):
        as_parallel_env(ss.pad_action_space_v0(gem_mining_v0.parallel_env()))


def test_wrappers_that_cannot_work_are_named():
    with pytest.raises(ValueError, match="reward wrapper .* does not keep a vector reward"):
        as_parallel_env(ss.clip_reward_v0(mobeach_v0.parallel_env(num_agents=2)))
    with pytest.raises(ValueError, match="vectorised env"):
        as_parallel_env(ss.pettingzoo_env_to_vec_env_v1(mobeach_v0.parallel_env(num_agents=2)))


def test_masfols_trains_on_a_supersuit_pipeline():
    env = ss.frame_stack_v1(ss.normalize_obs_v0(ss.dtype_v0(mobeach_v0.parallel_env(num_agents=2), np.float32)), 2)
    model = MASFOLS(
        env, policy="MlpPolicy", steps_per_iteration=60, learner_kwargs=MLP, seed=0,
        test_weights=[[1.0, 0.0], [0.5, 0.5]],
    )  # fmt: skip
    model.learn(max_iterations=1)
    assert len(model.policy_set) >= 1 and model.policy_set.observation_space.shape == (2 * 5,)  # 5 features, 2 frames

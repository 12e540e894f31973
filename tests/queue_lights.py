"""Traffic lights with different numbers of greens, as small queueing MDPs, for exact and learning tests of masks.

Light ``i`` serves ``greens[i]`` approaches. Every step the green approach (the action) discharges up to two
vehicles, then each approach gains one with its arrival probability; queues hold at most :data:`MAX_QUEUE`. The
reward is ``[-(queue of approach 0), -(the other approaches' queues)]``: the main road against the side roads.
:class:`QueueLights` pads the observations into one layout (each approach's queue, then a flag per approach slot
saying whether the light has it); its action spaces stay each light's own, for
:class:`~sb3_sfgpi.PadActions`. It refuses an action a light does not have, so a test fails wherever a masked action
is ever executed. :class:`SingleLight` is one of the lights alone in its own, unpadded layout (the reference: the
same light trained apart). Each light draws its arrivals from its own generator, seeded from the reset seed and its
index, so light ``i`` sees the same arrivals in both envs.
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

MAX_QUEUE = 2
ARRIVALS = (0.5, 0.3, 0.3, 0.3)
EPISODE_STEPS = 30
REWARD_SPACE = spaces.Box(-float(MAX_QUEUE * len(ARRIVALS)), 0.0, shape=(2,), dtype=np.float32)


def _episode_seed(seed: int | None, previous: int) -> int:
    """The seed of an episode's arrivals: the one given, else the previous episode's plus one."""
    return previous + 1 if seed is None else seed


class _Light:
    """The queues of one light and their arrivals."""

    def __init__(self, greens: int):
        self.greens = greens
        self.queues = np.zeros(greens, dtype=np.int64)
        self.rng = np.random.default_rng(0)

    def reset(self, seed: int) -> None:
        self.queues[:] = 0
        self.rng = np.random.default_rng(seed)

    def step(self, action: int) -> np.ndarray:
        if not 0 <= action < self.greens:
            raise ValueError(f"a light with {self.greens} greens was sent to green {action}")
        self.queues[action] = max(0, self.queues[action] - 2)
        arrived = self.rng.random(self.greens) < np.array(ARRIVALS[: self.greens])
        self.queues = np.minimum(self.queues + arrived, MAX_QUEUE)
        return np.array([-self.queues[0], -self.queues[1:].sum()], dtype=np.float32)


class QueueLights(ParallelEnv):
    """Lights with ``greens`` approaches each, observations padded to the largest light; own action spaces."""

    metadata = {"name": "queue_lights_v0", "render_modes": []}

    def __init__(self, greens: Sequence[int] = (2, 3)):
        self.possible_agents = [f"light_{i}" for i in range(len(greens))]
        self.lights = {agent: _Light(g) for agent, g in zip(self.possible_agents, greens, strict=True)}
        self.slots = max(greens)
        self._observation_space = spaces.MultiDiscrete([MAX_QUEUE + 1] * self.slots + [2] * self.slots)
        self.agents: list[str] = []
        self._steps = self._seed = 0

    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Discrete:
        return spaces.Discrete(self.lights[agent].greens)

    def reward_space(self, agent: str) -> spaces.Box:
        return REWARD_SPACE

    def _observe(self, agent: str) -> np.ndarray:
        light = self.lights[agent]
        queues, exists = np.zeros(self.slots, dtype=np.int64), np.zeros(self.slots, dtype=np.int64)
        queues[: light.greens], exists[: light.greens] = light.queues, 1
        return np.concatenate([queues, exists])

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._seed = _episode_seed(seed, self._seed)
        for i, light in enumerate(self.lights.values()):
            light.reset(self._seed * 100 + i)
        self.agents, self._steps = list(self.possible_agents), 0
        return {a: self._observe(a) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        rewards = {agent: self.lights[agent].step(int(actions[agent])) for agent in self.agents}
        self._steps += 1
        done = self._steps >= EPISODE_STEPS
        observations = {a: self._observe(a) for a in self.agents}
        infos = {a: {} for a in self.agents}
        truncations = dict.fromkeys(self.agents, done)
        terminations = dict.fromkeys(self.agents, False)
        if done:
            self.agents = []
        return observations, rewards, terminations, truncations, infos


class SingleLight(gym.Env):
    """Light ``index`` of ``QueueLights(greens)`` alone, in its own layout (its queues; its own greens)."""

    def __init__(self, greens: Sequence[int] = (2, 3), index: int = 0):
        self.index = index
        self.light = _Light(greens[index])
        self.observation_space = spaces.MultiDiscrete([MAX_QUEUE + 1] * greens[index])
        self.action_space = spaces.Discrete(greens[index])
        self.reward_space = REWARD_SPACE
        self._steps = self._seed = 0

    def reset(self, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._seed = _episode_seed(seed, self._seed)
        self.light.reset(self._seed * 100 + self.index)
        self._steps = 0
        return self.light.queues.copy(), {}

    def step(self, action: int):
        reward = self.light.step(int(action))
        self._steps += 1
        return self.light.queues.copy(), reward, False, self._steps >= EPISODE_STEPS, {}


class PaddedSingleLight(SingleLight):
    """:class:`SingleLight` choosing among ``slots`` greens, those it lacks masked (``info["action_mask"]``)."""

    def __init__(self, greens: Sequence[int] = (2, 3), index: int = 0, slots: int = 3):
        super().__init__(greens, index)
        self.action_space = spaces.Discrete(slots)
        self._mask = (np.arange(slots) < greens[index]).astype(np.int8)

    def reset(self, seed: int | None = None, options: dict | None = None):
        observation, _ = super().reset(seed=seed, options=options)
        return observation, {"action_mask": self._mask}

    def step(self, action: int):
        observation, reward, terminated, truncated, _ = super().step(action)
        return observation, reward, terminated, truncated, {"action_mask": self._mask}

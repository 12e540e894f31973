"""Four-Room's moves as arrays: one compiled step for many episodes side by side.

:meth:`FourRoomParallelEnv.batched_episodes <sfgpi_envs.four_room.FourRoomParallelEnv.batched_episodes>` gives
:class:`FourRoomEpisodes`: GPI's rollouts (validation, value estimates, evaluation) run their episodes through it
(:func:`~sb3_sfgpi.common.rollouts.run_lockstep`), one call per step for all of them, where one env per episode
costs a Python step each. The env's own step stays in Python: for one episode a compiled call costs more than it
saves (3.9 µs per step against 21.8 µs through these arrays). The rules are the env's:
``tests/test_four_room_batched.py`` steps both with the same actions and compares everything they return.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from sfgpi_envs.four_room import Layout


@njit(cache=True, nogil=True)
def advance(
    cells: np.ndarray,
    present: np.ndarray,
    collected: np.ndarray,
    live: np.ndarray,
    actions: np.ndarray,
    tables: tuple[np.ndarray, np.ndarray, np.ndarray, int],
    goal_reward: np.ndarray,
    rewards: np.ndarray,
    terminated: np.ndarray,
) -> None:
    """
    Move every live agent of every episode, in agent order (``agent_0`` takes an object both enter in one step), and
    collect the object it enters if it is still there; an agent entering the goal is terminated.

    :param cells: shape ``(episodes, agents)``: each agent's cell, updated
    :param present: shape ``(episodes, objects)``: the objects still on the grid, updated
    :param collected: shape ``(episodes, agents, objects)``: what each agent collected, updated
    :param live: shape ``(episodes, agents)``: the agents that move (the others are left as they are)
    :param actions: shape ``(episodes, agents)``: each live agent's action in ``{0, 1, 2, 3}``
    :param tables: :class:`~sfgpi_envs.four_room.Layout`'s ``next_cell``, ``object_at``, ``object_type`` and
        ``goal_cell``
    :param goal_reward: shape ``(d,)``, float32: the reward of entering the goal
    :param rewards: written, shape ``(episodes, agents, d)``, float32: each live agent's reward (zero for the others)
    :param terminated: written, shape ``(episodes, agents)``: whether each live agent entered the goal (False for
        the others)
    """
    next_cell, object_at, object_type, goal_cell = tables
    for e in range(cells.shape[0]):
        for i in range(cells.shape[1]):
            rewards[e, i, :] = 0.0
            terminated[e, i] = False
            if not live[e, i]:
                continue
            cell = next_cell[cells[e, i], actions[e, i]]
            cells[e, i] = cell
            terminated[e, i] = cell == goal_cell
            if terminated[e, i]:
                rewards[e, i, :] = goal_reward
                continue
            k = object_at[cell]
            if k >= 0 and present[e, k]:
                present[e, k] = False
                collected[e, i, k] = True
                rewards[e, i, object_type[k]] = 1.0


class FourRoomEpisodes:
    """
    ``n`` episodes of one Four-Room env as arrays (:class:`~sb3_sfgpi.common.rollouts.BatchedEpisodes`): each is
    the episode the env runs from a reset, with the same observations, rewards, ends and final infos.

    :param layout: the grid's tables
    :param starts: each agent's start cell
    :param goal_reward: the goal's reward, float32
    :param max_steps: steps after which every live agent is truncated
    :param observation_mode: ``"xy"``, ``"own"`` or ``"full"`` (see the env)
    :param agents: the agents' names, in index order
    :param n: number of episodes
    """

    def __init__(
        self,
        layout: Layout,
        starts: Sequence[int],
        goal_reward: np.ndarray,
        max_steps: int,
        observation_mode: str,
        agents: Sequence[str],
        n: int,
    ):
        self.layout, self.goal_reward, self.max_steps = layout, goal_reward, max_steps
        self.observation_mode, self.agents = observation_mode, list(agents)
        self._tables = (layout.next_cell, layout.object_at, layout.object_type, layout.goal_cell)
        self._starts = np.array(starts, dtype=np.int64)
        m, n_objects = len(self.agents), len(layout.object_type)
        self.cells = np.empty((n, m), dtype=np.int64)
        self.present = np.empty((n, n_objects), dtype=bool)
        self.collected = np.empty((n, m, n_objects), dtype=bool)
        self.live = np.empty((n, m), dtype=bool)
        self.steps = np.empty(n, dtype=np.int64)
        self._rewards = np.zeros((n, m, len(goal_reward)), dtype=np.float32)
        #: whether each agent entered the goal at the last step
        self.terminated = np.zeros((n, m), dtype=bool)

    @property
    def reward_dim(self) -> int:
        """Number of objectives."""
        return len(self.goal_reward)

    def reset(self, seeds: Sequence[int | None]) -> tuple[np.ndarray, np.ndarray]:
        """
        Every episode at its start (the moves draw nothing: ``seeds`` only say how many).

        :return: the observations, shape ``(episodes, agents, obs_dim)``, and the live agents (all)
        """
        if len(seeds) != len(self.cells):
            raise ValueError(f"{len(self.cells)} episodes, got {len(seeds)} seeds")
        self.cells[:] = self._starts
        self.present[:] = True
        self.collected[:] = False
        self.live[:] = True
        self.steps[:] = 0
        return self.observations(), self.live.copy()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        One step of every episode with a live agent (:meth:`observations` then gives where they are).

        :param actions: shape ``(episodes, agents)``: each live agent's action (the others' are ignored)
        :return: the rewards (shape ``(episodes, agents, d)``, float32, zero for the agents that did not move) and
            the agents live after the step (:attr:`terminated` says which of the others entered the goal)
        :raises ValueError: an action of a live agent outside ``{0, 1, 2, 3}``
        """
        moving = actions[self.live]
        if moving.size and (moving.min() < 0 or moving.max() > 3):
            raise ValueError(f"Four-Room's actions are 0 (left), 1 (up), 2 (right), 3 (down), got {moving.tolist()}")
        advance(
            self.cells, self.present, self.collected, self.live, actions.astype(np.int64, copy=False),
            self._tables, self.goal_reward, self._rewards, self.terminated,
        )  # fmt: skip
        stepped = self.live.any(axis=1)
        self.steps[stepped] += 1
        truncated = (self.steps >= self.max_steps)[:, None]
        self.live &= ~(self.terminated | truncated)
        return self._rewards.copy(), self.live.copy()

    def observations(self) -> np.ndarray:
        """Every agent's observation, shape ``(episodes, agents, obs_dim)``, int64 (the env's ``_observe``)."""
        xy = self.layout.xy[self.cells]
        if self.observation_mode == "xy":
            return xy
        if self.observation_mode == "own":
            flags = self.collected
        else:
            flags = np.broadcast_to(~self.present[:, None, :], self.collected.shape)
        return np.concatenate((xy, flags.astype(np.int64)), axis=2)

    def final_infos(self) -> list[dict[str, dict[str, Any]]]:
        """Each episode's last info of every agent: the objects it collected."""
        return [
            {agent: {"collected": self.collected[e, i].copy()} for i, agent in enumerate(self.agents)}
            for e in range(len(self.cells))
        ]

"""Four-Room's moves as arrays: one compiled step for many episodes side by side, and a packed step for training.

:meth:`FourRoomParallelEnv.batched_episodes <sfgpi_envs.four_room.FourRoomParallelEnv.batched_episodes>` gives
:class:`FourRoomEpisodes`: GPI's rollouts (validation, value estimates, evaluation) run their episodes through it
(:func:`~sb3_sfgpi.common.rollouts.run_lockstep`), one call per step for all of them, where one env per episode
costs a Python step each. The env's own step stays in Python: for one episode a compiled call costs more than it
saves (3.9 µs per step against 21.8 µs through these arrays). The rules are the env's:
``tests/test_four_room_batched.py`` steps both with the same actions and compares everything they return.

:func:`packed_step` is the env's step over its state packed in integers
(:meth:`FourRoomParallelEnv.packed_dynamics <sfgpi_envs.four_room.FourRoomParallelEnv.packed_dynamics>`), for
compiled training loops that call it from their own compiled code (``sb3_sfgpi.tabular.joint_steps``): it is
compiled with the signature :data:`PACKED_STEP_SIGNATURE` so that a loop typed by that signature takes it as a
first-class function and numba can cache that loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numba import njit, types

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
                for j in range(goal_reward.shape[0]):  # no array assignment: its shape check is seconds of compiling
                    rewards[e, i, j] = goal_reward[j]
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


class PackedDynamics(NamedTuple):
    """An env's step compiled over a packed state (the arguments of :func:`packed_step` an env gives)."""

    step: Any  #: the compiled step, of signature :data:`PACKED_STEP_SIGNATURE`
    episode_step: Any  #: the compiled step with episode ends (:func:`packed_episode_step`), of that signature too
    model: np.ndarray  #: int64: what never changes (layout, settings)
    constants: np.ndarray  #: float32: rewards the step gives
    state: np.ndarray  #: int64: the episode's state now


#: The signature of a packed step: ``(model, constants, state, actions, observations, rewards) -> ended``.
PACKED_STEP_SIGNATURE = types.int64(
    types.int64[::1], types.float32[::1], types.int64[::1], types.int64[::1], types.int64[:, ::1], types.float32[:, ::1]
)
#: Where each part of a packed Four-Room model starts: agents, objects, cells, goal cell, step limit, observation mode,
#: then ``next_cell``, ``object_at``, ``object_type`` and ``xy`` flattened.
_AGENTS, _OBJECTS, _CELLS, _GOAL, _LIMIT, _MODE, _TABLES = range(7)
#: Observation modes as the packed model names them (the env's ``OBSERVATION_MODES`` order).
_XY, _OWN, _FULL = range(3)


@njit(PACKED_STEP_SIGNATURE, cache=True, nogil=True)
def packed_episode_step(
    model: np.ndarray,
    constants: np.ndarray,
    state: np.ndarray,
    actions: np.ndarray,
    observations: np.ndarray,
    rewards: np.ndarray,
) -> int:
    """
    The env's ``step`` on a packed state, episode ends included (for compiled rollouts that run whole episodes): every
    live agent moves, in agent order; an agent entering the goal gets its reward and is terminated, and at the step
    limit every live agent is truncated. The arguments are :func:`packed_step`'s.

    :return: the agents live after the step, as bits (agent ``i``: ``1 << i``); 0: the episode is over
    """
    m, k, n_cells = model[_AGENTS], model[_OBJECTS], model[_CELLS]
    next_cell = model[_TABLES : _TABLES + 4 * n_cells]
    object_at = model[_TABLES + 4 * n_cells : _TABLES + 5 * n_cells]
    object_type = model[_TABLES + 5 * n_cells : _TABLES + 5 * n_cells + k]
    xy = model[_TABLES + 5 * n_cells + k :]
    cells, live, present, collected = (
        state[1 : 1 + m],
        state[1 + m : 1 + 2 * m],
        state[1 + 2 * m : 1 + 2 * m + k],
        state[1 + 2 * m + k :],
    )
    state[0] += 1
    for i in range(m):
        if not live[i]:
            continue
        cells[i] = next_cell[4 * cells[i] + actions[i]]
        rewards[i, :] = 0.0
        if cells[i] == model[_GOAL]:
            live[i] = 0  # terminated
            for j in range(constants.shape[0]):
                rewards[i, j] = constants[j]
            continue
        j = object_at[cells[i]]
        if j >= 0 and present[j]:
            present[j] = 0
            collected[i * k + j] = 1
            rewards[i, object_type[j]] = 1.0
    live_after = 0
    for i in range(m):
        if state[0] >= model[_LIMIT]:
            live[i] = 0  # truncated
        if live[i]:
            live_after |= 1 << i
            observations[i, 0], observations[i, 1] = xy[2 * cells[i]], xy[2 * cells[i] + 1]
            for j in range(observations.shape[1] - 2):
                observations[i, 2 + j] = collected[i * k + j] if model[_MODE] == _OWN else 1 - present[j]
    return live_after


@njit(PACKED_STEP_SIGNATURE, cache=True, nogil=True)
def packed_step(
    model: np.ndarray,
    constants: np.ndarray,
    state: np.ndarray,
    actions: np.ndarray,
    observations: np.ndarray,
    rewards: np.ndarray,
) -> int:
    """
    The env's ``step`` on a packed state, unless it ends an agent's episode: then nothing changes and it returns 1 (the
    caller steps the env itself); else every live agent moves, in agent order, and it returns 0.

    :param model: the layout and settings, constant (see :func:`pack_model`)
    :param constants: the goal's reward, float32
    :param state: the step count, each agent's cell, whether it is live, each object's presence, what each agent
        collected (see :func:`pack_state`), updated
    :param actions: each agent's action (the live agents' are read)
    :param observations: written: each live agent's observation after the step
    :param rewards: written: each live agent's reward
    """
    m, n_cells = model[_AGENTS], model[_CELLS]
    next_cell = model[_TABLES : _TABLES + 4 * n_cells]
    if state[0] + 1 >= model[_LIMIT]:
        return 1  # every live agent is truncated
    for i in range(m):
        if state[1 + m + i] and next_cell[4 * state[1 + i] + actions[i]] == model[_GOAL]:
            return 1
    packed_episode_step(model, constants, state, actions, observations, rewards)  # it ends no episode
    return 0


def pack_model(layout: Layout, n_agents: int, max_steps: int, observation_mode: int) -> np.ndarray:
    """The constant part of :func:`packed_step`'s arguments: the layout's tables and the env's settings."""
    n_cells, k = len(layout.object_at), len(layout.object_type)
    header = [n_agents, k, n_cells, layout.goal_cell, max_steps, observation_mode]
    tables = (layout.next_cell, layout.object_at, layout.object_type, layout.xy)
    return np.concatenate([np.array(header, dtype=np.int64), *(table.reshape(-1) for table in tables)])


def pack_state(
    step_count: int,
    cells: Sequence[int],
    live: Sequence[bool],
    present: Sequence[bool],
    collected: Sequence[np.ndarray],
) -> np.ndarray:
    """An episode's state as :func:`packed_step` reads it."""
    parts = [[step_count], cells, np.asarray(live, dtype=np.int64), np.asarray(present, dtype=np.int64)]
    return np.concatenate(
        [np.asarray(part, dtype=np.int64) for part in parts] + [np.asarray(collected, dtype=np.int64).reshape(-1)]
    )


def unpack_state(
    state: np.ndarray, n_agents: int, n_objects: int
) -> tuple[int, list[int], list[bool], list[bool], np.ndarray]:
    """:func:`pack_state`'s parts: the step count, cells, live flags, objects present and what each agent collected."""
    m, k = n_agents, n_objects
    live = [bool(x) for x in state[1 + m : 1 + 2 * m]]
    present = [bool(x) for x in state[1 + 2 * m : 1 + 2 * m + k]]
    collected = state[1 + 2 * m + k :].reshape(m, k).astype(bool)
    return int(state[0]), [int(x) for x in state[1 : 1 + m]], live, present, collected

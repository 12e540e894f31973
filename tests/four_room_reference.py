"""References for single-agent ``four-room-v0``: brute-force value iteration and the exact CCS found by OLS.

Shared by ``tests/test_four_room_optimum.py`` and ``benchmarks/bench_optimum.py``.
"""

from __future__ import annotations

import numpy as np
from mo_gymnasium.envs.four_room.four_room import FourRoom
from sfgpi_envs.four_room_optimum import FourRoomOptimum

from sb3_sfgpi.ols import OLS


def _transitions(env: FourRoom) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Per (cell, action), from MO-Gymnasium's own ``step``: the next cell, the object entered (-1: none), the reward
    when that object is still there, and whether the episode ends.
    """
    n_cells, n_objects = env.height * env.width, len(env.shape_ids)
    next_cell = np.tile(np.arange(n_cells)[:, None], (1, 4))
    entered, terminal = np.full((n_cells, 4), -1), np.zeros((n_cells, 4), dtype=bool)
    reward = np.zeros((n_cells, 4, env.reward_dim))
    for cell in range(n_cells):
        position = divmod(cell, env.width)
        if position in env.occupied or position == env.goal:
            continue
        for action in range(4):
            env.state = (position, (0,) * n_objects)
            observation, r, terminated, _, _ = env.step(action)
            after = (int(observation[0]), int(observation[1]))
            next_cell[cell, action] = after[0] * env.width + after[1]
            if after != position:  # a blocked move enters nothing
                entered[cell, action] = env.shape_ids.get(after, -1)
            reward[cell, action], terminal[cell, action] = r, terminated
    return next_cell, entered, reward, terminal


def value_iteration(maze: np.ndarray, w: np.ndarray, gamma: float, horizon: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """
    Finite-horizon value iteration over every state (cell, collected set) of ``FourRoom(maze=maze)``, all arrays.

    The transitions come from MO-Gymnasium's ``step`` (an object is collected, with its reward, when entered while
    not collected). The sweeps stop early at an exact fixed point, which the finite-horizon values then keep.

    :param maze: MO-Gymnasium's maze array
    :param w: a weight
    :param gamma: the discount factor
    :param horizon: steps to go
    :return: ``Q`` of shape ``(4, cells, sets)`` and ``V`` of shape ``(cells, sets)``, with ``horizon`` steps to go
    """
    env = FourRoom(maze=maze)
    next_cell, entered, reward, terminal = _transitions(env)
    n_cells, n_masks = next_cell.shape[0], 2 ** len(env.shape_ids)
    masks = np.arange(n_masks)
    bit = np.maximum(entered, 0)[..., None]
    present = (entered[..., None] >= 0) & (masks >> bit & 1 == 0)  # (cells, actions, sets): an object is collected
    gain = np.where(present | terminal[..., None], (reward @ w)[..., None], 0.0)  # (cells, actions, sets)
    after = np.where(present, masks | 1 << bit, masks)
    successor = (next_cell[..., None] * n_masks + after).transpose(1, 0, 2).reshape(4, -1)
    gain, go_on = gain.transpose(1, 0, 2).reshape(4, -1), gamma * ~terminal.T.repeat(n_masks, axis=1)
    values = np.zeros(n_cells * n_masks)
    for _ in range(horizon):
        q = gain + go_on * values[successor]
        new = q.max(axis=0)
        if np.array_equal(new, values):
            break
        values = new
    return q.reshape(4, n_cells, n_masks), values.reshape(n_cells, n_masks)


def exact_ccs(optimum: FourRoomOptimum, tolerance: float = 1e-6, max_iterations: int = 1_000):
    """
    OLS with the exact oracle (:meth:`FourRoomOptimum.vector_value`) until its queue is empty.

    :param optimum: the oracle
    :param tolerance: OLS's tolerance
    :param max_iterations: give up (``RuntimeError``) after this many weights
    :return: the CCS (a list of value vectors) and the number of OLS iterations (weights solved)
    """
    ols = OLS(optimum.reward_dim, tolerance)
    for iteration in range(max_iterations):
        w = ols.next_weight()
        if w is None:
            return ols.ccs, iteration
        ols.add_solution(optimum.vector_value(w), w)
    raise RuntimeError(f"OLS did not end within {max_iterations} iterations")

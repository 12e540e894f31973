"""The exact optimum of MO-Gymnasium's single-agent ``four-room-v0``, for any weight.

**The environment** (MO-Gymnasium 1.3, ``mo_gymnasium/envs/four_room/four_room.py``): a maze of walls (``X``),
objects of types ``1``, ``2``, ``3``, one goal (``G``) and a start cell; actions ``0`` left, ``1`` up, ``2`` right,
``3`` down; a move into a wall or off the grid leaves the agent where it is (reward zero). Entering an object not
collected yet collects it (reward: the one-hot of its type); entering the goal ends the episode (reward
``(1, 1, 1)``). ``gym.make`` adds a time limit of 200 steps (truncation).

**The method.** The set ``m`` of collected objects only grows, and a reward comes only when the agent enters an
*exit* of ``m``: an object not in ``m`` (which then joins it) or the goal (which ends the episode). Between two
exits an optimal agent walks a shortest path, so for a weight ``w`` the Bellman optimality equation over the
states ``(cell c, set m)`` has the exact solution

    ``V(m, c) = max_e γ^(d_m(c, e) - 1) X_m(e)``,  ``X_m(e) = w · r_e + γ V(m ∪ {e}, cell of e)``,  ``X_m(G) = w · 1``,

where ``d_m(c, e)`` is the length of a shortest path from ``c`` into ``e`` through cells that are neither the goal
nor objects outside ``m``. The distances are computed once per instance (a breadth-first search from each exit,
then, for every ``m``, Floyd-Warshall through the objects of ``m``); each weight then costs one backward pass over
the sets from ``|m| = 12`` down to ``0`` (the values at object cells chain the sets), vectorised over the sets of
one size (milliseconds; brute-force value iteration over all 169 · 4096 states takes about a second and agrees,
see ``tests/test_four_room_optimum.py``). Other cells are evaluated on demand, from the same distances.

**The time limit.** For ``w >= 0`` every reward ``w · r`` is ``>= 0``, so truncation can only take reward away:
the optimum of the truncated env is at most the infinite-horizon ``V(∅, start)``. An optimal policy follows the
chain of exits that attains the maxima above; when that chain reaches the goal within ``max_steps`` steps, it
collects all of ``V(∅, start)`` before the limit, which is therefore the exact optimum of the truncated env.
:meth:`FourRoomOptimum.value` checks this and raises otherwise (it does not happen on the default layout, whose
optimal episodes are far shorter than 200 steps). The actions are those of the infinite-horizon problem: optimal
for the truncated env along an episode from the start, not necessarily in a state reached with few steps left.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .four_room import DEFAULT_STARTS, MAZE

__all__ = ["FourRoomOptimum"]

_OBJECT_TYPES = "123"  # object characters, in reward order
_MOVES = ((0, -1), (-1, 0), (0, 1), (1, 0))  # (d_row, d_col) of left, up, right, down
_UNREACHABLE = 10**6  # a distance longer than any path


class FourRoomOptimum:
    """
    Exact optimal values and actions of single-agent Four-Room (see the module docstring for the method).

    The distances are built once; the solution of the last weight asked about is kept, so rolling out
    :meth:`greedy_action` for one weight solves it once.

    :param maze: the layout, one string (or one sequence of 1-character strings, as MO-Gymnasium's ``MAZE``) per
        row: ``X`` wall, ``G`` the goal, ``1``/``2``/``3`` an object of type 0/1/2 (MO-Gymnasium's object order:
        column by column); any other character is an empty cell. The default is ``four-room-v0``'s layout.
    :param start: the start cell ``(row, col)``; ``four-room-v0``'s is ``(12, 0)``
    :param gamma: the discount factor, in ``(0, 1]``
    :param max_steps: the time limit of an episode, in steps
    """

    reward_dim = len(_OBJECT_TYPES)

    def __init__(
        self,
        maze: Sequence[str] | Sequence[Sequence[str]] | np.ndarray = MAZE,
        start: tuple[int, int] = DEFAULT_STARTS[0],
        gamma: float = 0.95,
        max_steps: int = 200,
    ) -> None:
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma!r}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps!r}")
        self.gamma = float(gamma)
        self.max_steps = int(max_steps)
        self._parse(["".join(row) for row in maze], tuple(start))
        self._moves = self._move_table()
        # (cells, exits): the shortest path from a cell into an exit, crossing no exit
        self._to_exit = np.stack([self._distances_to(cell) for cell in self._exit_cells], axis=1)
        self._distance = self._closure(self._to_exit[[*self._exit_cells[:-1], self._start]])
        self._discount = self._discounts(self._distance)
        popcount = np.array([bin(m).count("1") for m in range(self._n_masks)])
        levels = [np.flatnonzero(popcount == k) for k in range(self._n_objects, -1, -1)]
        # The sets of each size, largest first, with their discounts laid out (exits, sets, sources): the backward
        # pass then takes its maxima over the leading axis, which numpy does fastest.
        self._levels = [(masks, np.ascontiguousarray(self._discount[masks].transpose(2, 0, 1))) for masks in levels]
        self._solved: tuple[bytes, np.ndarray, float] | None = None

    @classmethod
    def from_env(cls, env: Any, gamma: float = 0.95) -> FourRoomOptimum:
        """
        The optimum of a (wrapped) MO-Gymnasium Four-Room env: its maze, its start cell and its time limit.

        :param env: e.g. ``mo_gymnasium.make("four-room-v0")``; it must have one start cell and a time limit
        :param gamma: the discount factor
        :return: the optimum of that env
        """
        four_room = env.unwrapped
        if len(four_room.initial) != 1:
            raise ValueError(f"the env must have exactly one start cell, got {four_room.initial}")
        if env.spec is None or env.spec.max_episode_steps is None:
            raise ValueError("the env has no time limit (make it with gym.make or mo_gymnasium.make)")
        return cls(four_room.maze, four_room.initial[0], gamma, env.spec.max_episode_steps)

    # --- the public face ------------------------------------------------------------------------------
    def value(self, w: Sequence[float] | np.ndarray) -> float:
        """
        The optimal scalarised value ``max_π w · V^π`` at the start, exact for the time-limited env.

        :param w: a weight (non-negative, finite, not all zero; normalised onto the simplex)
        :return: the optimal value of ``w · (discounted vector return)``
        :raises RuntimeError: the optimal episode is longer than ``max_steps`` (the time limit would bind)
        """
        exits, start_value = self._solve(w)
        length = self._optimal_length(exits)
        if length > self.max_steps:
            raise RuntimeError(f"the optimal episode takes {length} > max_steps={self.max_steps} steps")
        return start_value

    def vector_value(self, w: Sequence[float] | np.ndarray) -> np.ndarray:
        """
        ``V^π`` at the start of the policy acting by :meth:`greedy_action` for ``w`` (an optimal policy).

        The env is deterministic, so this is the discounted vector return of one episode, within the time limit.

        :param w: a weight
        :return: shape ``(3,)``, one discounted return per object type
        """
        exits, _ = self._solve(w)
        total, discount = np.zeros(self.reward_dim), 1.0
        cell, mask = self._start, 0
        for _ in range(self.max_steps):
            cell = self._moves[cell, self._best_action(cell, mask, exits)]
            exit_ = int(self._exit_of_cell[cell])
            if exit_ == self._n_objects:  # the goal
                return total + discount
            if exit_ >= 0 and not mask >> exit_ & 1:
                total[self._types[exit_]] += discount
                mask |= 1 << exit_
            discount *= self.gamma
        return total

    def greedy_action(self, observation: Sequence[int] | np.ndarray, w: Sequence[float] | np.ndarray) -> int:
        """
        An optimal action for ``w`` (of the infinite-horizon problem; ties go to the lowest action).

        :param observation: MO-Gymnasium's observation ``[row, col, flag_0, ..., flag_11]`` (flag 1: collected)
        :param w: a weight
        :return: the action, ``0`` left, ``1`` up, ``2`` right, ``3`` down
        """
        cell, mask = self._state(observation)
        return self._best_action(cell, mask, self._solve(w)[0])

    # --- the layout -----------------------------------------------------------------------------------
    def _parse(self, rows: list[str], start: tuple[int, int]) -> None:
        """Walls, objects (column by column, as MO-Gymnasium numbers them), goal and start of the layout."""
        self._height, self._width = len(rows), len(rows[0])
        if any(len(row) != self._width for row in rows):
            raise ValueError("the maze rows must all have the same length")
        cells = [(r, c) for c in range(self._width) for r in range(self._height)]
        self._walls = {r * self._width + c for r, c in cells if rows[r][c] == "X"}
        objects = [(r, c) for r, c in cells if rows[r][c] in _OBJECT_TYPES]
        goals = [r * self._width + c for r, c in cells if rows[r][c] == "G"]
        if len(goals) != 1:
            raise ValueError(f"the maze must have exactly one goal G, got {len(goals)}")
        self._types = np.array([_OBJECT_TYPES.index(rows[r][c]) for r, c in objects])
        self._n_objects, self._n_masks = len(objects), 2 ** len(objects)
        self._exit_cells = [r * self._width + c for r, c in objects] + goals  # exit i < n: object i; exit n: goal
        self._exit_of_cell = np.full(self._height * self._width, -1)
        self._exit_of_cell[self._exit_cells] = np.arange(self._n_objects + 1)
        row, col = start
        self._start = row * self._width + col
        if not (0 <= row < self._height and 0 <= col < self._width) or rows[row][col] in "XG" + _OBJECT_TYPES:
            raise ValueError(f"the start {start} must be an empty cell of the maze")

    def _move_table(self) -> np.ndarray:
        """``moves[cell, action]``: the cell after the move (the same cell when a wall or the edge blocks it)."""
        moves = np.zeros((self._height * self._width, len(_MOVES)), dtype=np.int64)
        for cell in range(self._height * self._width):
            row, col = divmod(cell, self._width)
            for action, (dr, dc) in enumerate(_MOVES):
                r, c = row + dr, col + dc
                inside = 0 <= r < self._height and 0 <= c < self._width
                moves[cell, action] = r * self._width + c if inside and r * self._width + c not in self._walls else cell
        return moves

    def _distances_to(self, target: int) -> np.ndarray:
        """Breadth-first search: steps from every cell into ``target`` through no other exit (moves are symmetric)."""
        distance = np.full(self._height * self._width, _UNREACHABLE)
        distance[target], frontier, steps = 0, [target], 0
        while frontier:
            steps += 1
            relays = [u for u in frontier if u == target or self._exit_of_cell[u] < 0]  # exits are not crossed
            frontier = sorted({int(v) for u in relays for v in self._moves[u] if distance[v] == _UNREACHABLE})
            distance[frontier] = steps
        return distance

    def _closure(self, direct: np.ndarray) -> np.ndarray:
        """
        Per set ``m``, the shortest paths from each source (object, then the start) into each exit crossing only
        objects of ``m``: Floyd-Warshall through the objects of ``m``, all sets at once.

        :param direct: ``(sources, exits)`` steps crossing no exit
        :return: ``(sets, sources, exits)``
        """
        distance = np.broadcast_to(direct, (self._n_masks, *direct.shape)).copy()
        masks = np.arange(self._n_masks)
        for k in range(self._n_objects):
            has = masks >> k & 1 == 1
            d = distance[has]
            distance[has] = np.minimum(d, d[:, :, k, None] + d[:, None, k, :])  # source -> object k -> exit
        return distance

    def _discounts(self, distance: np.ndarray) -> np.ndarray:
        """``γ^(d - 1)`` per (set, source, exit); 0 where the exit is collected, unreachable or the source absent."""
        n = self._n_objects
        masks = np.arange(self._n_masks)[:, None]
        collected = np.hstack([masks >> np.arange(n) & 1 == 1, np.zeros((self._n_masks, 1), dtype=bool)])
        present = np.hstack([collected[:, :n], np.ones((self._n_masks, 1), dtype=bool)])  # the start is always
        valid = (distance < _UNREACHABLE) & present[:, :, None] & ~collected[:, None, :]
        discount = np.zeros(distance.shape)
        discount[valid] = self.gamma ** (distance[valid] - 1.0)
        return discount

    # --- one weight -----------------------------------------------------------------------------------
    def _solve(self, w: Sequence[float] | np.ndarray) -> tuple[np.ndarray, float]:
        """
        The backward pass over the sets (module docstring) for ``w``, or the kept solution of the same ``w``.

        :return: ``X`` of shape ``(sets, exits)`` (0 for collected exits) and ``V(∅, start)``
        """
        w = self._check_weight(w)
        if self._solved is None or self._solved[0] != w.tobytes():
            n = self._n_objects
            values = np.zeros((self._n_masks, n + 1))  # V(m, source): sources are the objects, then the start
            exits = np.zeros((self._n_masks, n + 1))
            exits[:, n] = w.sum()
            bits = 1 << np.arange(n)
            for masks, discount in self._levels:
                after = masks[:, None] | bits
                gain = w[self._types] + self.gamma * values[after, np.arange(n)]
                exits[masks, :n] = np.where(after == masks[:, None], 0.0, gain)
                values[masks] = np.max(discount * exits[masks].T[:, :, None], axis=0)
            self._solved = (w.tobytes(), exits, float(values[0, n]))
        return self._solved[1], self._solved[2]

    def _cell_values(self, cells: np.ndarray, mask: int, exits: np.ndarray) -> np.ndarray:
        """``V(m, c)`` of non-exit cells ``c`` (empty, the start or collected objects), from the distances."""
        n = self._n_objects
        to_exit = self._to_exit[cells]  # (cells, exits), crossing no object
        collected = np.flatnonzero(mask >> np.arange(n) & 1)
        via = to_exit[:, collected, None] + self._distance[mask, collected][None]  # into a collected object first
        distance = np.minimum(to_exit, via.min(axis=1, initial=_UNREACHABLE))
        valid = (distance < _UNREACHABLE) & (exits[mask] > 0)  # X_m(e) > 0 exactly for the exits not collected
        return np.max(np.where(valid, self.gamma ** (np.where(valid, distance, 1) - 1.0) * exits[mask], 0.0), axis=1)

    def _best_action(self, cell: int, mask: int, exits: np.ndarray) -> int:
        """``argmax_a Q(s, a)``: ``X_m(e)`` for a move into an exit ``e``, else ``γ V(m, next cell)``."""
        after = self._moves[cell]
        exit_ = self._exit_of_cell[after]
        into_exit = (exit_ >= 0) & (exits[mask, exit_] > 0)  # an object already collected is an empty cell
        q = np.where(into_exit, exits[mask, exit_], self.gamma * self._cell_values(after, mask, exits))
        return int(np.argmax(q))

    def _optimal_length(self, exits: np.ndarray) -> int:
        """The number of steps of an optimal episode: the chain of exits attaining the maxima, from the start."""
        source, mask, length = self._n_objects, 0, 0
        while True:
            exit_ = int(np.argmax(self._discount[mask, source] * exits[mask]))
            length += int(self._distance[mask, source, exit_])
            if exit_ == self._n_objects:
                return length
            source, mask = exit_, mask | 1 << exit_

    # --- checks ---------------------------------------------------------------------------------------
    def _check_weight(self, w: Sequence[float] | np.ndarray) -> np.ndarray:
        """A float64 weight on the simplex, or ``ValueError`` naming what is wrong."""
        w = np.asarray(w, dtype=np.float64)
        if w.shape != (self.reward_dim,):
            raise ValueError(f"w must have length {self.reward_dim}, got shape {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError(f"w must be finite, got {w.tolist()}")
        if np.any(w < 0):
            raise ValueError(f"w must be non-negative, got {w.tolist()}")
        if not np.any(w > 0):
            raise ValueError("w must not be all zero")
        return w / w.sum()

    def _state(self, observation: Sequence[int] | np.ndarray) -> tuple[int, int]:
        """The cell index and the collected set (bit ``i``: object ``i``) of an observation, checked."""
        observation = np.asarray(observation).astype(np.int64)
        if observation.shape != (2 + self._n_objects,):
            raise ValueError(f"the observation must have length {2 + self._n_objects}, got {observation.shape}")
        (row, col), flags = observation[:2], observation[2:]
        if not (0 <= row < self._height and 0 <= col < self._width) or np.any((flags != 0) & (flags != 1)):
            raise ValueError(f"not a Four-Room observation: {observation.tolist()}")
        cell, mask = int(row * self._width + col), int(flags @ (1 << np.arange(self._n_objects)))
        exit_ = self._exit_of_cell[cell]
        if cell in self._walls or exit_ == self._n_objects or (exit_ >= 0 and not mask >> exit_ & 1):
            raise ValueError(f"no agent can observe {observation.tolist()} (a wall, the goal or an object not taken)")
        return cell, mask

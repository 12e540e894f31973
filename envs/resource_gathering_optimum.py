"""The exact optimum of MO-Gymnasium's ``resource-gathering-v0`` for any weight: value iteration on its true MDP.

**The environment** (MO-Gymnasium 1.3, ``mo_gymnasium/envs/resource_gathering/resource_gathering.py``): a 5 × 5 grid
with gold ``R1`` at ``(0, 2)``, a gem ``R2`` at ``(1, 4)``, enemies ``E1`` at ``(1, 2)`` and ``E2`` at ``(0, 3)``,
and home ``H`` at ``(4, 2)``, where the agent starts carrying nothing. Actions ``0`` up, ``1`` down, ``2`` left,
``3`` right; a move off the grid leaves the agent where it is. After the move, the cell it is on acts: a resource
is picked up (and stays picked up); on an enemy's cell the agent is killed with probability 0.1 (reward
``(-1, 0, 0)``, the episode ends), also when it stays there by bumping the edge; at home the episode ends with the
reward ``(0, gold, gem)`` of what it carries (zero when nothing, e.g. after bumping the edge at the start). The
observation is ``[row, col, gold, gem]``; ``mo_gymnasium.make`` adds a time limit of 100 steps.

**The method.** The state is the position and what is carried (25 · 4 states); the model has two outcomes where
an enemy may attack. :class:`~sfgpi_envs.tabular_optimum.TabularMDP` solves ``w · r`` by backward induction over
the time limit, so :func:`optimal_value` is the exact optimum of the env as it is played.

**Why not the env's own front.** ``ResourceGathering.pareto_front(γ)`` lists six hand-made policies. Its returns
are discounted one factor of γ too much (a reward on step ``n`` is worth ``γ^(n - 1)``, not ``γ^n``: the safe trip
to the gem takes 10 steps and is worth ``γ^9``), and it misses the policy that fetches both resources by safe paths
(6 steps to the gold, 7 from the gold to the gem around both enemies, 5 home). Each of its points is γ times the
value of the policy it describes, and the optimum is never negative (going home at once is worth zero), so the
optimum here is never below that front's best: above it by about a factor ``1/γ`` wherever some reward is worth
having, and by more where the missed policy is the best one (``tests/test_known_fronts.py`` checks this on the
test weights, and the value against Monte-Carlo rollouts of the optimal policy).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .tabular_optimum import Outcome, TabularMDP, _time_limit

__all__ = ["optimal_value", "resource_gathering_mdp"]

_MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))  # (d_row, d_col) of up, down, left, right
#: The chance that an enemy kills the agent on its cell, hard-coded in the env's ``step`` (the map is read).
ENEMY_ATTACK_PROBABILITY = 0.1


def resource_gathering_mdp(env: Any, gamma: float) -> TabularMDP:
    """
    The model of a (wrapped) ``resource-gathering-v0`` env: its map, its start and its time limit.

    :param env: ``mo_gymnasium.make("resource-gathering-v0")``
    :param gamma: the discount factor
    :return: the MDP over (row, col, gold, gem), solved exactly for any weight by its methods
    """
    game = env.unwrapped
    cells = np.asarray(game.map)
    rows, cols = cells.shape
    start = (*(int(x) for x in game.initial_pos), 0, 0)
    if cells[start[0], start[1]] != "H":
        raise ValueError(f"the agent must start at home, got {start[:2]}")

    def step(state: tuple[int, int, int, int], action: int) -> list[Outcome]:
        row, col, gold, gem = state
        r, c = row + _MOVES[action][0], col + _MOVES[action][1]
        if not (0 <= r < rows and 0 <= c < cols):
            r, c = row, col
        cell = cells[r, c]
        if cell == "R1":
            gold = 1
        elif cell == "R2":
            gem = 1
        elif cell in ("E1", "E2"):
            p = ENEMY_ATTACK_PROBABILITY
            return [(p, None, (-1.0, 0.0, 0.0)), (1.0 - p, (r, c, gold, gem), (0.0, 0.0, 0.0))]
        elif cell == "H":
            return [(1.0, None, (0.0, float(gold), float(gem)))]
        return [(1.0, (r, c, gold, gem), (0.0, 0.0, 0.0))]

    states = [(r, c, g, m) for r in range(rows) for c in range(cols) for g in (0, 1) for m in (0, 1)]
    return TabularMDP.from_step(states, len(_MOVES), step, lambda s: s, start, _time_limit(env), gamma)


def optimal_value(env: Any, w: Sequence[float] | np.ndarray, gamma: float) -> float:
    """
    ``max_π w · V^π(s0)`` of ``resource-gathering-v0``: the best expected ``w ·`` (discounted vector return).

    Builds the model each call; keep :func:`resource_gathering_mdp`'s result to ask about many weights.

    :param env: ``mo_gymnasium.make("resource-gathering-v0")``
    :param w: a weight of length 3 (objectives: killed, gold home, gem home)
    :param gamma: the discount factor
    """
    return resource_gathering_mdp(env, gamma).value(w)

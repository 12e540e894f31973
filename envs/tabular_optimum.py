"""Exact optimal values of small multi-objective MDPs with a time limit, for any weight: finite-horizon value
iteration on the scalarised reward, and the exact value vector of any policy given as a table of actions.

**Why exact.** For a weight ``w`` the scalarised problem ``max_π w · V^π(s0)`` is an ordinary MDP with the reward
``w · r``: its optimal value is the one number a set of policies acting by GPI can at best reach for ``w`` (the
convex coverage set's value at ``w``). A time limit of ``H`` steps (Gymnasium's ``TimeLimit``) makes the problem
finite-horizon, so backward induction over the steps ``t = H - 1, ..., 0`` gives the exact optimum of the env as
it is played, with time-dependent optimal actions (they only differ from stationary ones in states reached with
few steps left).

**The model.** A :class:`TabularMDP` holds, per state and action, up to ``K`` outcomes: a probability, the next
state (or the end of the episode: an absorbing state of value zero) and the vector reward of the step. Builders
turn an env's documented dynamics into one: :func:`deep_sea_treasure_mdp` and :func:`fruit_tree_mdp` below,
:func:`~sfgpi_envs.resource_gathering_optimum.resource_gathering_mdp` for resource gathering.

**Evaluating learned policies.** :meth:`TabularMDP.policy_value` gives the exact expected discounted vector return
of a policy acting by a table of actions (one per state, or one per step and state), e.g. GPI's actions for a
weight on every state's observation: a measurement of a learned policy with no Monte-Carlo noise, also in a
stochastic env.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from typing import Any

import numpy as np

__all__ = ["TabularMDP", "deep_sea_treasure_mdp", "fruit_tree_mdp"]

#: An outcome of a step: (probability, next state or None where the episode ends, vector reward).
Outcome = tuple[float, Hashable | None, Sequence[float]]


class TabularMDP:
    """
    A finite MDP with vector rewards, a start state and a horizon, solved exactly for any weight.

    :param next_state: ``(S, A, K)`` index of the next state of each outcome; ``S`` means the episode ended
    :param probability: ``(S, A, K)`` probability of each outcome (each ``(s, a)`` sums to 1; padding has 0)
    :param reward: ``(S, A, K, d)`` vector reward of each outcome
    :param observations: ``(S, ...)`` the env's observation in each state (to find a state and to ask a policy)
    :param start: the index of the start state
    :param horizon: the time limit of an episode, in steps
    :param gamma: the discount factor, in ``(0, 1]``
    """

    def __init__(
        self,
        next_state: np.ndarray,
        probability: np.ndarray,
        reward: np.ndarray,
        observations: np.ndarray,
        start: int,
        horizon: int,
        gamma: float,
    ) -> None:
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma!r}")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon!r}")
        if not np.allclose(probability.sum(axis=2), 1.0):
            raise ValueError("the outcome probabilities of every state and action must sum to 1")
        self.next_state, self.probability, self.reward = next_state, probability, reward
        self.observations = observations
        self.observation_dtype = np.int32  # MO-Gymnasium's grid envs observe int32 arrays
        self.n_states, self.n_actions, _, self.reward_dim = reward.shape
        self.start, self.horizon, self.gamma = int(start), int(horizon), float(gamma)
        self._index = {tuple(np.asarray(o).ravel().tolist()): s for s, o in enumerate(observations)}
        self._solved: tuple[bytes, np.ndarray] | None = None

    @classmethod
    def from_step(
        cls,
        states: Sequence[Hashable],
        n_actions: int,
        step: Callable[[Any, int], list[Outcome]],
        observe: Callable[[Any], Sequence[float]],
        start: Hashable,
        horizon: int,
        gamma: float,
    ) -> TabularMDP:
        """
        The model of an env given by its step function on hashable states.

        :param states: every state (those never reached may be included)
        :param n_actions: the number of actions
        :param step: ``step(state, action)`` -> its outcomes ``(probability, next state or None, reward)``
        :param observe: the env's observation of a state
        :param start: the start state
        :param horizon: the time limit, in steps
        :param gamma: the discount factor
        """
        index = {state: i for i, state in enumerate(states)}
        table = [[step(state, a) for a in range(n_actions)] for state in states]
        k = max(len(outcomes) for row in table for outcomes in row)
        d = len(table[0][0][0][2])
        shape = (len(states), n_actions, k)
        next_state, probability = np.full(shape, len(states)), np.zeros(shape)
        reward = np.zeros((*shape, d))
        for s, row in enumerate(table):
            for a, outcomes in enumerate(row):
                for j, (p, after, r) in enumerate(outcomes):
                    next_state[s, a, j] = len(states) if after is None else index[after]
                    probability[s, a, j], reward[s, a, j] = p, r
        observations = np.array([observe(state) for state in states])
        return cls(next_state, probability, reward, observations, index[start], horizon, gamma)

    # --- one weight ------------------------------------------------------------------------------------------------
    def q_values(self, w: Sequence[float] | np.ndarray) -> np.ndarray:
        """
        The optimal action values of ``w · r`` at every step, by backward induction (kept for the last ``w``).

        :param w: a weight of length ``d`` (used as given: the scale of the values is the scale of ``w``)
        :return: ``(horizon, S, A)``; entry ``t`` is the value with ``horizon - t`` steps left
        """
        w = np.asarray(w, dtype=np.float64)
        if w.shape != (self.reward_dim,) or not np.all(np.isfinite(w)):
            raise ValueError(f"w must be {self.reward_dim} finite numbers, got {w.tolist()}")
        if self._solved is None or self._solved[0] != w.tobytes():
            scalar = self.probability * (self.reward @ w)  # (S, A, K): expected immediate reward per outcome
            q = np.zeros((self.horizon, self.n_states, self.n_actions))
            after = np.zeros(self.n_states + 1)  # values at the next step; the last entry: the episode ended
            for t in range(self.horizon - 1, -1, -1):
                q[t] = scalar.sum(axis=2) + self.gamma * np.sum(self.probability * after[self.next_state], axis=2)
                after[:-1] = q[t].max(axis=1)
            self._solved = (w.tobytes(), q)
        return self._solved[1]

    def value(self, w: Sequence[float] | np.ndarray) -> float:
        """The optimal expected ``w ·`` (discounted vector return) from the start: ``max_π w · V^π(s0)``."""
        return float(self.q_values(w)[0, self.start].max())

    def greedy_actions(self, w: Sequence[float] | np.ndarray) -> np.ndarray:
        """Optimal actions for ``w``, shape ``(horizon, S)`` (step, state); ties go to the lowest action."""
        return self.q_values(w).argmax(axis=2)

    def vector_value(self, w: Sequence[float] | np.ndarray) -> np.ndarray:
        """``V^π(s0)`` of the optimal policy of :meth:`greedy_actions`, shape ``(d,)``: a point of the CCS."""
        return self.policy_value(self.greedy_actions(w))

    # --- any policy ------------------------------------------------------------------------------------------------
    def policy_value(self, actions: np.ndarray) -> np.ndarray:
        """
        The exact expected discounted vector return from the start of a policy given by its actions.

        :param actions: ``(S,)`` one action per state (a stationary policy) or ``(horizon, S)`` per step and state
        :return: shape ``(d,)``
        """
        actions = np.asarray(actions, dtype=np.int64)
        if actions.shape == (self.n_states,):
            actions = np.broadcast_to(actions, (self.horizon, self.n_states))
        if actions.shape != (self.horizon, self.n_states):
            raise ValueError(f"actions must have shape ({self.n_states},) or {(self.horizon, self.n_states)}")
        states = np.arange(self.n_states)
        after = np.zeros((self.n_states + 1, self.reward_dim))
        for t in range(self.horizon - 1, -1, -1):
            p = self.probability[states, actions[t]]  # (S, K)
            r = self.reward[states, actions[t]]  # (S, K, d)
            nxt = self.next_state[states, actions[t]]  # (S, K)
            after[:-1] = np.einsum("sk,skd->sd", p, r + self.gamma * after[nxt])
        return after[self.start].copy()

    def expected_utility(
        self, act: Callable[[np.ndarray, np.ndarray], Sequence[int] | np.ndarray], weights: np.ndarray
    ) -> float:
        """
        Mean over ``weights`` of ``w · V^π(s0)`` of a policy asked for its actions in every state, exactly.

        :param act: ``act(observations, w)``: the actions for a batch of observations (every state's, with the
            dtype of the env's observation space) and a weight, e.g. GPI's ``predict(observations, w)[0]``
        :param weights: shape ``(n, d)``
        """
        observations = self.observations.astype(self.observation_dtype)
        values = [float(np.dot(w, self.policy_value(np.asarray(act(observations, w)).reshape(-1)))) for w in weights]
        return float(np.mean(values))

    def state_of(self, observation: Sequence[float] | np.ndarray) -> int:
        """The index of the state the env shows as ``observation``, or ``KeyError``."""
        return self._index[tuple(np.asarray(observation).ravel().tolist())]


def deep_sea_treasure_mdp(env: Any, gamma: float) -> TabularMDP:
    """
    The model of MO-Gymnasium's ``deep-sea-treasure-v0`` (``mo_gymnasium/envs/deep_sea_treasure``), from its map.

    The submarine starts at ``(0, 0)``; actions ``0`` up, ``1`` down, ``2`` left, ``3`` right; a move off the grid or
    into the sea floor (``-10``) leaves it where it is. Every step costs ``-1`` time; entering a treasure (a positive
    value) ends the episode with that value. ``mo_gymnasium.make`` adds a time limit of 100 steps.

    :param env: ``mo_gymnasium.make("deep-sea-treasure-v0")`` (its default, convex map, integer observations)
    :param gamma: the discount factor
    """
    sea = np.asarray(env.unwrapped.sea_map, dtype=np.float64)
    if env.unwrapped.map_name != "convex" or env.unwrapped.float_state:
        raise ValueError("only the default map with integer observations is modelled")
    moves = ((-1, 0), (1, 0), (0, -1), (0, 1))
    rows, cols = sea.shape

    def step(state: tuple[int, int], action: int) -> list[Outcome]:
        r, c = state[0] + moves[action][0], state[1] + moves[action][1]
        if not (0 <= r < rows and 0 <= c < cols) or sea[r, c] == -10:
            r, c = state
        treasure = sea[r, c]
        if treasure > 0:
            return [(1.0, None, (treasure, -1.0))]
        return [(1.0, (r, c), (0.0, -1.0))]

    states = [(r, c) for r in range(rows) for c in range(cols) if sea[r, c] == 0]
    return TabularMDP.from_step(states, 4, step, lambda s: s, (0, 0), _time_limit(env), gamma)


def fruit_tree_mdp(env: Any, gamma: float) -> TabularMDP:
    """
    The model of MO-Gymnasium's ``fruit-tree-v0`` (``mo_gymnasium/envs/fruit_tree``), from its tree.

    A full binary tree of depth ``D`` (``mo_gymnasium.make("fruit-tree-v0", depth=D)``, ``D`` in 5, 6, 7): the
    agent starts at the root ``[0, 0]`` and each step goes down to child ``2 i`` (action ``0``) or ``2 i + 1``
    (action ``1``) of node ``[row, i]``, with the reward of the node it enters (zero except at the leaves, the
    fruits). The episode ends at a leaf, after ``D`` steps; the env has no time limit, the horizon is ``D``.

    :param env: ``mo_gymnasium.make("fruit-tree-v0", depth=D)``
    :param gamma: the discount factor
    """
    tree = env.unwrapped
    depth = int(tree.tree_depth)

    def step(state: tuple[int, int], action: int) -> list[Outcome]:
        child = (state[0] + 1, 2 * state[1] + action)
        reward = tuple(float(x) for x in tree.get_tree_value(np.array(child)))
        return [(1.0, None if child[0] == depth else child, reward)]

    states = [(row, i) for row in range(depth) for i in range(2**row)]
    return TabularMDP.from_step(states, 2, step, lambda s: s, (0, 0), depth, gamma)


def _time_limit(env: Any) -> int:
    """The env's time limit (``gym.make`` reads it from its registration), or ``ValueError``."""
    if env.spec is None or env.spec.max_episode_steps is None:
        raise ValueError("the env has no time limit (make it with gym.make or mo_gymnasium.make)")
    return int(env.spec.max_episode_steps)

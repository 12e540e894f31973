"""GPI's episodes over a set of tables in one compiled call: each episode to its end, every decision traced.

Validation scores GPI over Π (and over Π without each member, and with new policies) on the same weights again and
again: in Python each step of those episodes is a batched GPI decision and an env step, some two hundred microseconds.
Where the env offers its step over a packed state with episode ends (``packed_dynamics().episode_step``, of the
signature :data:`~sb3_sfgpi.tabular.joint_steps.PACKED_STEP_SIGNATURE`) and the set is tables on the CPU,
:func:`run_gpi_episodes` runs every episode in one call: each live agent's GPI decision
(:func:`~sb3_sfgpi.tabular.kernels.gpi_decision`, numpy's bits), the env's step, the returns added up as
:func:`~sb3_sfgpi.common.rollouts.run_lockstep` adds them (float64, in step order), and each decision's observation,
action, members attaining GPI's value and episode, episode after episode, each in step order and agent order: what the
lockstep's trace gives once sorted by episode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numba import njit, types

from sb3_sfgpi.tabular.joint_steps import PACKED_STEP_SIGNATURE
from sb3_sfgpi.tabular.kernels import gpi_decision, observation_row

if TYPE_CHECKING:
    from sb3_sfgpi.stacking import StackedTables
    from sb3_sfgpi.tabular.network import TabularSFNetwork

#: Why :func:`_run_episodes` stopped: every episode ended; the trace is full (call again with more room); an
#: observation is outside the tables' space (the trace's row at the count returned holds it).
ENDED, NO_ROOM, OUTSIDE = range(3)


class GPIEpisodes(NamedTuple):
    """What :func:`run_gpi_episodes` gives: each episode's returns, and every decision in episode order."""

    discounted: np.ndarray  #: each episode's discounted return of every agent, ``(episodes, agents, d)``, float64
    total: np.ndarray  #: the plain sums of rewards, likewise
    observations: np.ndarray  #: each decision's observation, ``(decisions, obs_size)``, int64
    actions: np.ndarray  #: GPI's action, ``(decisions,)``
    attaining: np.ndarray  #: whether each member attains GPI's value of it, ``(P, decisions)``
    episodes: np.ndarray  #: each decision's episode, ``(decisions,)``


def _run_episodes(
    step: Any,
    model: np.ndarray,
    constants: np.ndarray,
    states: np.ndarray,
    observations: np.ndarray,
    live: np.ndarray,
    stack: np.ndarray,
    stack_row: np.ndarray,
    geometry: tuple[np.ndarray, np.ndarray, np.ndarray, int],
    weights: np.ndarray,
    left_out: np.ndarray,
    gamma: float,
    returns: tuple[np.ndarray, np.ndarray],
    trace: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    first: tuple[int, int],
) -> tuple[int, int, int]:
    """
    Every episode from ``first`` (an episode and the decisions traced before it) to its end, one after another, GPI
    acting for each live agent.

    :param step: the env's packed step with episode ends, with its ``model`` and ``constants``
    :param states: each episode's packed state at reset, ``(episodes, size)``, advanced
    :param observations: each episode's observations of every agent at reset, ``(episodes, agents, obs_size)``,
        advanced
    :param live: the agents live at each episode's reset, as bits
    :param stack: the stacked tables (:class:`~sb3_sfgpi.stacking.StackedTables`), with each table row's state
        ``stack_row``; ``geometry``: the tables' ``low``, ``end``, ``strides`` and ``first_row``
    :param weights: each episode's weights, float32; ``left_out``: the member it acts without (``-1``: none)
    :param returns: written: each episode's discounted returns and plain sums of rewards, ``(episodes, agents, d)``
    :param trace: written: each decision's observation, action, members attaining (``(room, P)``) and episode
    :return: :data:`ENDED`, :data:`NO_ROOM` (with the episode that found none and the decisions before it) or
        :data:`OUTSIDE` (with the trace row holding the observation), the decisions traced, and the episode
    """
    low, end, strides, first_row = geometry
    discounted, total = returns
    trace_observations, trace_actions, trace_attaining, trace_episodes = trace
    n_agents, d = observations.shape[1], discounted.shape[2]
    q = np.empty((trace_attaining.shape[1], stack.shape[1] // (trace_attaining.shape[1] * d)), dtype=np.float32)
    best = np.empty(q.shape[1], dtype=np.float32)
    actions = np.zeros(n_agents, dtype=np.int64)
    rewards = np.zeros((n_agents, d), dtype=np.float32)
    every_action = np.empty(0, dtype=np.bool_)
    count = first[1]
    for e in range(first[0], states.shape[0]):
        alive, discount, episode_start = live[e], 1.0, count
        for i in range(n_agents):
            for k in range(d):
                discounted[e, i, k], total[e, i, k] = 0.0, 0.0
        while alive:
            for i in range(n_agents):
                if not alive >> i & 1:
                    continue
                if count == trace_episodes.shape[0]:
                    return NO_ROOM, episode_start, e
                for j in range(low.shape[0]):
                    trace_observations[count, j] = observations[e, i, j]
                row = observation_row(observations[e, i], low, end, strides, first_row)
                if row < 0:
                    return OUTSIDE, count, e
                state = stack[stack_row[row]]
                actions[i] = gpi_decision(state, weights[e], left_out[e], every_action, q, best)
                for p in range(q.shape[0]):
                    trace_attaining[count, p] = q[p, actions[i]] == best[actions[i]]
                trace_actions[count], trace_episodes[count] = actions[i], e
                count += 1
            moved, alive = alive, step(model, constants, states[e], actions, observations[e], rewards)
            for i in range(n_agents):
                if moved >> i & 1:
                    for k in range(d):
                        reward = np.float64(rewards[i, k])
                        discounted[e, i, k] += discount * reward
                        total[e, i, k] += reward
            discount *= gamma
    return ENDED, count, states.shape[0]


_kernel: list[Any] = []


def _compiled() -> Any:
    """:func:`_run_episodes` compiled, typed by :data:`PACKED_STEP_SIGNATURE` for the env's step so numba caches it."""
    if not _kernel:
        int64s, float32s = types.int64[::1], types.float32[::1]
        matrix, floats3 = types.Array(types.int64, 2, "C"), types.Array(types.float64, 3, "C")
        signature = types.UniTuple(types.int64, 3)(
            types.FunctionType(PACKED_STEP_SIGNATURE), int64s, float32s, matrix, types.Array(types.int64, 3, "C"),
            int64s, types.Array(types.float32, 2, "C"), types.int32[::1],
            types.Tuple((int64s, int64s, int64s, types.int64)), types.Array(types.float32, 2, "C"), int64s,
            types.float64, types.UniTuple(floats3, 2),
            types.Tuple((matrix, int64s, types.Array(types.bool_, 2, "C"), int64s)), types.UniTuple(types.int64, 2),
        )  # fmt: skip
        _kernel.append(njit(signature, cache=True, nogil=True)(_run_episodes))
    return _kernel[0]


def run_gpi_episodes(
    dynamics: Any,
    states: np.ndarray,
    observations: np.ndarray,
    live: np.ndarray,
    stacked: StackedTables,
    network: TabularSFNetwork,
    weights: np.ndarray,
    left_out: np.ndarray,
    gamma: float,
) -> GPIEpisodes:
    """
    GPI's episodes over stacked tables, each to its end, in one compiled call (see the module).

    :param dynamics: the env's packed dynamics (its ``episode_step``, ``model`` and ``constants`` are used)
    :param states: each episode's packed state at reset, ``(episodes, size)``, int64
    :param observations: every agent's observation at each reset, ``(episodes, agents, obs_size)``, int64
    :param live: the agents live at each reset, as bits, ``(episodes,)``
    :param stacked: the set's :class:`~sb3_sfgpi.stacking.StackedTables`
    :param network: one of the tables (their geometry)
    :param weights: each episode's weights, ``(episodes, d)``, float32 (as GPI reads them)
    :param left_out: each episode's member GPI acts without (``-1``: none)
    :raises ValueError: an observation outside the tables' space
    """
    shape = (*observations.shape[:2], stacked.reward_dim)
    returns = (np.empty(shape), np.empty(shape))
    trace = _trace(64 * shape[0] * shape[1], observations.shape[2], stacked.n_policies)
    advanced_states, advanced = states.copy(), observations.copy()
    first = (0, 0)
    while True:
        status, count, episode = _compiled()(
            dynamics.episode_step, dynamics.model, dynamics.constants, advanced_states, advanced, live,
            stacked.tables_numpy, stacked.stack_row_numpy, network.geometry, weights, left_out, gamma, returns, trace,
            first,
        )  # fmt: skip
        if status == ENDED:
            observations_of, actions, attaining, episodes = _first(trace, count)
            return GPIEpisodes(*returns, observations_of, actions, attaining.T, episodes)
        if status == OUTSIDE:
            network.rows(trace[0][count : count + 1])  # the tables' own error for it
            raise ValueError(f"an observation outside the tables' space: {trace[0][count].tolist()}")
        advanced_states[episode], advanced[episode] = states[episode], observations[episode]  # that episode again
        trace = _trace(2 * len(trace[1]), observations.shape[2], stacked.n_policies, _first(trace, count))
        first = (episode, count)


def _trace(room: int, obs_size: int, n_policies: int, kept: tuple[np.ndarray, ...] = ()) -> tuple[np.ndarray, ...]:
    """Room for ``room`` decisions (observations, actions, members attaining, episodes), the ``kept`` ones first."""
    trace = (
        np.empty((room, obs_size), dtype=np.int64), np.empty(room, dtype=np.int64),
        np.empty((room, n_policies), dtype=bool), np.empty(room, dtype=np.int64),
    )  # fmt: skip
    for part, old in zip(trace, kept, strict=False):
        part[: len(old)] = old
    return trace


def _first(trace: tuple[np.ndarray, ...], count: int) -> tuple[np.ndarray, ...]:
    """The first ``count`` decisions of a trace."""
    return tuple(part[:count] for part in trace)

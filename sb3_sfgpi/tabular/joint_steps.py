"""Joint steps of tabular learners and their env in one compiled loop: what a runner's step does, without Python.

A joint step of :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` with tables is a few microseconds of arithmetic (an
ε-greedy read, a transition stored, a minibatch drawn, a TD update) inside some two hundred microseconds of Python.
:func:`joint_steps_kernel` runs many joint steps in one call: every live learner's behaviour action (the draws of
:meth:`~sb3_sfgpi.sfdqn.tabular_policy.TabularPolicy.masked_actions`: numpy's global generator, then the action
space's PCG64), the env's step (an env's packed step, :data:`PACKED_STEP_SIGNATURE`, called as a first-class
function), and each learner's transition stored, its exploration rate moved on and its TD update
(:func:`~sb3_sfgpi.tabular.kernels.sampled_td_update`), in the order the runner does them, with the same draws, so
the tables, buffers and generators end as the step-by-step path leaves them. It stops where Python must act
(:data:`EPISODE_ENDS`, :data:`PLANNING_DUE`, :data:`TABLE_FULL`, :data:`UPDATE_DIVERGED`; :data:`DONE` where its steps
are done); :mod:`sb3_sfgpi.compiled_steps` hands the learners their arrays and takes their state back.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numba
import numpy as np
from numba import njit, types

from sb3_sfgpi.tabular.kernels import DIVERGED, STORE_ROWS, epsilon_greedy, sample_rows, sampled_td_update
from sb3_sfgpi.tabular.numpy_random import pcg64_integer

#: The signature of an env's packed step: ``(model, constants, state, actions, observations, rewards) -> ended``.
#: It advances ``state`` by one joint step of the live agents and writes their observations and rewards, unless the
#: step would end an agent's episode: then it changes nothing and returns 1.
PACKED_STEP_SIGNATURE = types.int64(
    types.int64[::1], types.float32[::1], types.int64[::1], types.int64[::1], types.int64[:, ::1], types.float32[:, ::1]
)

#: Why :func:`joint_steps_kernel` stopped: its steps are done; the next step ends an episode (its actions are chosen,
#: the env not stepped: Python steps it); a learner plans at the next step; a table needs room for a minibatch's
#: rows; a TD update diverged.
DONE, EPISODE_ENDS, PLANNING_DUE, TABLE_FULL, UPDATE_DIVERGED = range(5)

#: The learner's counters (:attr:`LearnerArrays.counters`), updated by the kernel.
NUM_TIMESTEPS, N_CALLS, N_UPDATES, POS, FULL, STORED, LAST_TRAIN = range(7)
#: Its settings (:attr:`LearnerArrays.settings`): the schedules' first step, the table's first row, and SFDQN's.
BASE, FIRST_ROW, BUFFER_SIZE, BATCH_SIZE, LEARNING_STARTS, TRAIN_FREQ, PLANNING_INTERVAL, PLANNINGS, N_ACTIONS = range(
    9
)
#: Its float state (:attr:`LearnerArrays.rates`): the exploration rate, updated, and the discount.
EXPLORATION_RATE, GAMMA = range(2)

_FLOAT32_MAX = float(np.finfo(np.float32).max)


class LearnerArrays(NamedTuple):
    """A tabular learner as :func:`joint_steps_kernel` reads and writes it (views of its own arrays)."""

    psi: np.ndarray  #: the table's storage, ``(slots + 1, n_actions, d)``, the default row last
    slot_map: np.ndarray  #: each row's slot, ``-1``: not stored
    stored_rows: np.ndarray  #: the row of each slot (room for every slot)
    storage: tuple  #: the replay buffer's :class:`~sb3_sfgpi.common.buffers.FlatStorage`
    low: np.ndarray  #: the observations' geometry (see :func:`~sb3_sfgpi.tabular.kernels.action_values`)
    end: np.ndarray
    strides: np.ndarray
    weights: np.ndarray  #: ``w``, float32
    epsilons: np.ndarray  #: the exploration rate once ``num_timesteps`` is ``BASE + k``
    learning_rates: np.ndarray  #: the learning rate of a TD update at ``num_timesteps = BASE + k``
    generator: np.ndarray  #: the PCG64 state of its action space (:func:`~sb3_sfgpi.tabular.numpy_random.pcg64_words`)
    last_obs: np.ndarray  #: the observation it acts on, updated
    episode_return: np.ndarray  #: float64, the episode's vector return so far, updated
    td_error: np.ndarray  #: the last TD update's errors, ``(batch, d)``, float32
    scratch: np.ndarray  #: int64 ``(3, batch)``: a minibatch's rows, their next rows, their table rows
    counters: np.ndarray  #: int64, see :data:`NUM_TIMESTEPS`
    settings: np.ndarray  #: int64, see :data:`BASE`
    rates: np.ndarray  #: float64, see :data:`EXPLORATION_RATE`


def _run_joint_steps(
    step: Any,
    model: np.ndarray,
    constants: np.ndarray,
    state: np.ndarray,
    live: np.ndarray,
    learners: tuple,
    key: np.ndarray,
    position: np.ndarray,
    max_steps: int,
    actions: np.ndarray,
    observations: np.ndarray,
    rewards: np.ndarray,
) -> tuple[int, int]:
    """
    Up to ``max_steps`` joint steps of the env and its live learners (``live``: one flag per agent, its learner at
    the same index), in the runner's order.

    :param step: the env's packed step (:data:`PACKED_STEP_SIGNATURE`), with its ``model``, ``constants`` and
        ``state`` (updated)
    :param learners: one :class:`LearnerArrays` per agent
    :param key: numpy's global Mersenne Twister (:func:`~sb3_sfgpi.tabular.numpy_random.global_stream`), with
        ``position``
    :param actions: written: the agents' last actions (those of the step that ends an episode, where one does)
    :param observations: scratch for the env's observations, ``(agents, obs_size)``
    :param rewards: scratch for its rewards, ``(agents, d)``
    :return: why it stopped (:data:`DONE`, :data:`EPISODE_ENDS`, ...) and the joint steps done (where an update
        diverged: its learner's index)
    """
    values = np.empty((1, learners[0].psi.shape[1]), dtype=np.float32)
    chosen = np.empty(1, dtype=np.int64)
    done = 0
    while done < max_steps:
        for i in range(len(learners)):
            if live[i]:
                stop = _stop_before(learners[i])
                if stop != DONE:
                    return stop, done
        for i in range(len(learners)):
            if live[i]:
                actions[i] = _behaviour_action(learners[i], key, position, values, chosen)
        if step(model, constants, state, actions, observations, rewards):
            return EPISODE_ENDS, done
        for i in range(len(learners)):
            if live[i] and not _learner_step(learners[i], observations[i], actions[i], rewards[i], key, position):
                return UPDATE_DIVERGED, i
        done += 1
    return DONE, done


@njit(cache=True, nogil=True)
def _stop_before(learner: LearnerArrays) -> int:
    """Why a learner's next step needs Python (:data:`PLANNING_DUE`, :data:`TABLE_FULL`), else :data:`DONE`."""
    counters, settings = learner.counters, learner.settings
    if learner.stored_rows.shape[0] - counters[STORED] < settings[BATCH_SIZE]:
        return TABLE_FULL
    num_timesteps, n_calls = counters[NUM_TIMESTEPS] + 1, counters[N_CALLS] + 1
    trains = num_timesteps > settings[LEARNING_STARTS] and n_calls % settings[TRAIN_FREQ] == 0
    if trains and settings[PLANNING_INTERVAL] and num_timesteps // settings[PLANNING_INTERVAL] > settings[PLANNINGS]:
        return PLANNING_DUE
    return DONE


@njit(cache=True, nogil=True)
def _behaviour_action(
    learner: LearnerArrays, key: np.ndarray, position: np.ndarray, values: np.ndarray, chosen: np.ndarray
) -> int:
    """SB3's ``_sample_action``: uniform before ``learning_starts``, else ε-greedy (an exploring one uniform)."""
    n_actions = learner.settings[N_ACTIONS]
    if learner.counters[NUM_TIMESTEPS] < learner.settings[LEARNING_STARTS]:
        return pcg64_integer(learner.generator, n_actions)
    geometry = (learner.low, learner.end, learner.strides, learner.settings[FIRST_ROW])
    observation = learner.last_obs.reshape((1, learner.last_obs.shape[0]))
    no_masks = np.zeros((0, 0), dtype=np.bool_)
    epsilon_greedy(
        (learner.psi, learner.slot_map), observation, geometry, learner.weights, no_masks,
        learner.rates[EXPLORATION_RATE], (key, position), values, chosen,
    )  # fmt: skip
    return pcg64_integer(learner.generator, n_actions) if chosen[0] < 0 else chosen[0]


@njit(cache=True, nogil=True)
def _learner_step(
    learner: LearnerArrays,
    observation: np.ndarray,
    action: int,
    reward: np.ndarray,
    key: np.ndarray,
    position: np.ndarray,
) -> bool:
    """
    :func:`~sb3_sfgpi.learners.learner_step` of a step inside an episode: the transition stored, the counters and the
    exploration rate moved on, and the TD update when due.

    :return: False where the update diverged
    """
    counters, settings = learner.counters, learner.settings
    observations, next_observations, stored_actions, stored_rewards, dones, timeouts, _ = learner.storage
    pos = counters[POS]
    _copy(observations[pos], learner.last_obs)
    _copy(next_observations[pos], observation)
    stored_actions[pos] = action
    _copy(stored_rewards[pos], reward)
    dones[pos], timeouts[pos] = 0.0, 0.0
    if pos + 1 >= settings[BUFFER_SIZE]:
        counters[FULL] = 1
    counters[POS] = (pos + 1) % settings[BUFFER_SIZE]
    _copy(learner.last_obs, observation)
    for k in range(reward.shape[0]):
        learner.episode_return[k] += np.float64(reward[k])
    counters[NUM_TIMESTEPS] += 1
    counters[N_CALLS] += 1
    k = counters[NUM_TIMESTEPS] - settings[BASE]
    learner.rates[EXPLORATION_RATE] = learner.epsilons[k]
    if counters[NUM_TIMESTEPS] <= settings[LEARNING_STARTS] or counters[N_CALLS] % settings[TRAIN_FREQ]:
        return True
    counters[N_UPDATES] += 1
    counters[LAST_TRAIN] = counters[NUM_TIMESTEPS]
    return _td_update(learner, np.float32(learner.learning_rates[k]), key, position)


@njit(cache=True, nogil=True)
def _td_update(learner: LearnerArrays, lr: np.float32, key: np.ndarray, position: np.ndarray) -> bool:
    """:meth:`~sb3_sfgpi.sfdqn.tabular_policy.TabularPolicy.td_update` on a fresh minibatch; False where it diverged."""
    counters, settings = learner.counters, learner.settings
    flat, next_flat, rows = learner.scratch[0], learner.scratch[1], learner.scratch[2]
    capacity = settings[BUFFER_SIZE]
    stop = capacity if counters[FULL] else counters[POS]
    sample_rows(key, position, (0, stop, 0), capacity, 1, 0, flat, next_flat)
    table = (learner.psi, learner.slot_map)
    gamma = np.float32(learner.rates[GAMMA])
    arguments = (learner.storage, flat, next_flat, learner.strides, settings[FIRST_ROW], learner.weights, gamma, lr)
    outcome = sampled_td_update(table, table, *arguments, rows, learner.td_error)
    if outcome == STORE_ROWS:
        _store_rows(learner, rows)
        outcome = sampled_td_update(table, table, *arguments, rows, learner.td_error)
    if outcome == DIVERGED:
        return False
    loss = 0.0
    for i in range(learner.td_error.shape[0]):
        for k in range(learner.td_error.shape[1]):
            loss += np.float64(learner.td_error[i, k]) ** 2
    return 0.5 * loss <= _FLOAT32_MAX  # a loss beyond float32 is divergence too


@njit(cache=True, nogil=True)
def _store_rows(learner: LearnerArrays, rows: np.ndarray) -> None:
    """:meth:`~sb3_sfgpi.tabular.sparse.SparseTable.store` of ``rows`` with room for them: new rows sorted, default."""
    missing = np.empty(rows.shape[0], dtype=np.int64)  # the rows not stored, sorted, each once
    n = 0
    for i in range(rows.shape[0]):
        row = rows[i]
        if learner.slot_map[row] >= 0:
            continue
        j = n
        while j > 0 and missing[j - 1] > row:
            j -= 1
        if j > 0 and missing[j - 1] == row:
            continue
        for m in range(n, j, -1):
            missing[m] = missing[m - 1]
        missing[j] = row
        n += 1
    count = learner.counters[STORED]
    for i in range(n):
        for a in range(learner.psi.shape[1]):
            _copy(learner.psi[count, a], learner.psi[-1, a])
        learner.stored_rows[count] = missing[i]
        learner.slot_map[missing[i]] = count
        count += 1
    learner.counters[STORED] = count


@njit(cache=True, nogil=True)
def _copy(target: np.ndarray, source: np.ndarray) -> None:
    """
    ``target[:] = source`` for 1-D arrays of one length, element by element: numba compiles an array assignment
    with a shape check whose error message alone takes seconds to compile on a machine's first run.
    """
    for i in range(source.shape[0]):
        target[i] = source[i]


_kernels: dict[Any, Any] = {}


def joint_steps_kernel(
    learners: tuple[LearnerArrays, ...], stream: tuple[np.ndarray, np.ndarray], observations: np.ndarray
) -> Any:
    """
    The compiled :func:`_run_joint_steps` for these learners' arrays: typed by :data:`PACKED_STEP_SIGNATURE` for the
    env's step, so numba caches it (a kernel per number of agents and array types, compiled once per machine).
    """
    learner_types = numba.typeof(learners)
    key = (learner_types, numba.typeof(stream), numba.typeof(observations))
    if key not in _kernels:
        int64s, float32s = types.int64[::1], types.float32[::1]
        signature = types.UniTuple(types.int64, 2)(
            types.FunctionType(PACKED_STEP_SIGNATURE), int64s, float32s, int64s, numba.typeof(np.zeros(1, bool)),
            learner_types, *(numba.typeof(part) for part in stream), types.int64, int64s, numba.typeof(observations),
            types.float32[:, ::1],
        )  # fmt: skip
        _kernels[key] = njit(signature, cache=True, nogil=True)(_run_joint_steps)
    return _kernels[key]

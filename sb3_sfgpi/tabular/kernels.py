"""The tabular learner's per-step arithmetic, compiled by numba: the same operations in the same order as numpy's.

A tabular TD update on a batch of transitions is a few hundred floating-point operations: in numpy each of its steps is
a call whose overhead outweighs its arithmetic, compiled the whole update is one call (its cost: the docs' performance
page). Compiled code must not change a single number: every product and sum here is one float32 IEEE operation, in the
order numpy does them (:func:`~sb3_sfgpi.common.weights.weighted_sum`: ``(v_0 w_0 + v_1 w_1) + v_2 w_2 + ...``), with no
``fastmath`` (no reassociation, no fused multiply-add; ``tests/test_kernels.py`` checks the machine code), so the table
holds the same bits as numpy's update would, on every CPU. The compiled code is cached next to this file (or in numba's
user cache where that is not writable), so a run compiles it once per machine.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from sb3_sfgpi.tabular.numpy_random import random_double, random_integers

_ONE = np.float32(1.0)


#: What :func:`sampled_td_update` returns: done; a value overflowed float32 (the update diverged); a sampled state
#: has no row in the table yet (store the rows it wrote, then call again).
UPDATED, DIVERGED, STORE_ROWS = 1, 0, -1


@njit(cache=True, nogil=True)
def weighted_value(psi: np.ndarray, weights: np.ndarray) -> np.float32:
    """``w · ψ`` of one action, as :func:`~sb3_sfgpi.common.weights.weighted_sum` adds it (float32 in, float32 out)."""
    q = psi[0] * weights[0]
    if psi.shape[0] > 1:
        q = q + psi[1] * weights[1]
        for k in range(2, psi.shape[0]):
            q = q + psi[k] * weights[k]
    return q


@njit(cache=True, nogil=True)
def action_values(
    table: tuple,
    observations: np.ndarray,
    low: np.ndarray,
    end: np.ndarray,
    strides: np.ndarray,
    first_row: int,
    weights: np.ndarray,
    values: np.ndarray,
) -> int:
    """
    ``w · ψ(s, a)`` of every action of each observation, written into ``values`` (shape ``(batch, n_actions)``,
    float32): the bits of :func:`~sb3_sfgpi.common.weights.weighted_sum` over the table's rows.

    :param table: the table's storage and slot map (see :func:`sampled_td_update`)
    :param observations: raw observations, one row of components each (any numeric dtype)
    :param low: each component's lowest value, with ``end`` one past its highest
    :param strides: the mixed-radix strides, with ``first_row`` the row of the lowest observation
    :param weights: ``w``, shape ``(d,)``, float32
    :return: ``-1``, or the index of the first observation outside the space (not an integer in its bounds: it
        would read another state's row); the values of the observations before it are written
    """
    psi, slot_map = table
    for i in range(observations.shape[0]):
        row = observation_row(observations[i], low, end, strides, first_row)
        if row < 0:
            return i
        slot = slot_map[row]
        if slot < 0:
            slot = psi.shape[0] - 1
        for a in range(psi.shape[1]):
            values[i, a] = weighted_value(psi[slot, a], weights)
    return -1


@njit(cache=True, nogil=True)
def observation_row(
    observation: np.ndarray, low: np.ndarray, end: np.ndarray, strides: np.ndarray, first_row: int
) -> int:
    """
    The table row of one raw observation (see :func:`action_values` for the geometry), or ``-1`` where it is outside
    the space: a component not an integer in its bounds, which would read another state's row.
    """
    row = 0
    for j in range(strides.shape[0]):
        x = observation[j]
        if not (low[j] <= x < end[j]) or np.int64(x) != x:  # bounds first: NaN and huge floats
            return -1
        row += np.int64(x) * strides[j]
    return row - first_row


@njit(cache=True, nogil=True)
def epsilon_greedy(
    table: tuple,
    observations: np.ndarray,
    geometry: tuple[np.ndarray, np.ndarray, np.ndarray, int],
    weights: np.ndarray,
    masks: np.ndarray,
    exploration_rate: float,
    stream: tuple[np.ndarray, np.ndarray],
    values: np.ndarray,
    actions: np.ndarray,
) -> int:
    """
    The ε-greedy actions of :meth:`SFDQNPolicy.masked_actions <sb3_sfgpi.sfdqn.policies.SFDQNPolicy.masked_actions>`
    with numpy's draws (``stream``: :func:`~sb3_sfgpi.tabular.numpy_random.global_stream`), the same numbers: a
    uniform draw per observation (it explores below ``exploration_rate``); then, unless every one explores, the
    values (:func:`action_values`, ``-inf`` where ``masks`` forbids) and the greedy actions, ties broken by a uniform
    draw per action of every observation, drawn only where some observation ties.

    :param geometry: the observations' ``low``, ``end``, ``strides`` and ``first_row`` (see :func:`action_values`)
    :param masks: the actions each observation has, shape ``(batch, n_actions)``, or empty: all
    :param actions: written: each observation's action, ``-1`` where it explores (a uniform action is the caller's to
        draw, from the action space's own generator)
    :return: ``-1``, or the index of the first observation outside the space (see :func:`action_values`)
    """
    key, position = stream
    explore = np.empty(observations.shape[0], dtype=np.bool_)
    for i in range(observations.shape[0]):
        explore[i] = random_double(key, position) < exploration_rate
    if explore.all():
        actions[:] = -1
        return -1
    low, end, strides, first_row = geometry
    outside = action_values(table, observations, low, end, strides, first_row, weights, values)
    if outside >= 0:
        return outside
    if masks.shape[0]:
        for i in range(values.shape[0]):
            for a in range(values.shape[1]):
                if not masks[i, a]:
                    values[i, a] = -np.inf
    _greedy_random_ties(values, key, position, actions)
    for i in range(actions.shape[0]):
        if explore[i]:
            actions[i] = -1
    return -1


@njit(cache=True, nogil=True)
def _numpy_max(values: np.ndarray) -> float:
    """numpy's ``max`` of a 1-D array: NaN where a value is NaN (a loop: no reduction's error message to compile)."""
    best = values[0]
    for k in range(1, values.shape[0]):
        if not np.isnan(best) and (np.isnan(values[k]) or values[k] > best):
            best = values[k]
    return best


@njit(cache=True, nogil=True)
def _numpy_argmax(values: np.ndarray) -> int:
    """numpy's ``argmax`` of a 1-D array: the first largest value, or the first NaN."""
    chosen = 0
    for k in range(1, values.shape[0]):
        if np.isnan(values[chosen]):
            break
        if np.isnan(values[k]) or values[k] > values[chosen]:
            chosen = k
    return chosen


@njit(cache=True, nogil=True)
def _greedy_random_ties(values: np.ndarray, key: np.ndarray, position: np.ndarray, actions: np.ndarray) -> None:
    """:func:`~sb3_sfgpi.sfdqn.networks.argmax_random_ties` on numpy's global generator: the same draws."""
    n, n_actions = values.shape
    best = np.empty(n, dtype=values.dtype)
    n_best = 0
    for i in range(n):
        best[i] = _numpy_max(values[i])
        for a in range(n_actions):
            if values[i, a] == best[i]:
                n_best += 1
    for i in range(n):
        top, actions[i] = -2.0, 0
        for a in range(n_actions):
            score = np.float64(values[i, a] == best[i])  # no ties anywhere: the first greedy action
            if n_best != n:
                draw = random_double(key, position)  # a draw for every action of every observation
                score = draw if values[i, a] == best[i] else -1.0
            if score > top:
                top, actions[i] = score, a


@njit(cache=True, nogil=True)
def greedy_action(psi: np.ndarray, weights: np.ndarray, forbidden: np.ndarray) -> tuple[int, bool]:
    """
    ``argmax_a w · ψ(a)`` over the actions not forbidden, ties to the first (numpy's ``argmax`` of
    :func:`~sb3_sfgpi.common.weights.weighted_sum`, masked to ``-inf``).

    :param psi: one state's ψ, shape ``(n_actions, d)``, float32
    :param weights: ``w``, shape ``(d,)``, float32
    :param forbidden: True for the actions the state does not have, shape ``(n_actions,)``, or empty: none
    :return: the action, and whether every allowed action's value is finite
    """
    best, best_action, finite = -np.inf, 0, True
    for a in range(psi.shape[0]):
        if forbidden.shape[0] and forbidden[a]:
            continue
        q = weighted_value(psi[a], weights)
        if not np.isfinite(q):
            finite = False
        if q > best:
            best, best_action = q, a
    return best_action, finite


@njit(cache=True, nogil=True)
def gpi_attaining(
    stack: np.ndarray,
    stack_rows: np.ndarray,
    weights: np.ndarray,
    left_out: np.ndarray,
    allowed: np.ndarray,
    actions: np.ndarray,
    attaining: np.ndarray,
) -> None:
    """
    GPI's action of each observation over stacked tables, and the members that attain its value, with numpy's bits
    (:meth:`~sb3_sfgpi.gpi_decisions.BatchedGPI.predict_attaining`): each member's ``w · ψ(s, a)`` as
    :func:`weighted_value`, ``-inf`` for the member left out and the actions not allowed, the maximum over members
    (NaN if one is NaN), the first action of the largest such value (or the first NaN), and the members whose value
    of it equals that maximum.

    :param stack: every member's ``ψ`` of each stacked state, shape ``(states, P·A·d)``, float32
    :param stack_rows: each observation's state in ``stack``, shape ``(B,)``
    :param weights: each observation's weights, shape ``(B, d)``, float32
    :param left_out: each observation's member that GPI acts without (``-1``: none), shape ``(B,)``
    :param allowed: the actions each observation has, ``(B, A)``, or ``(0, A)``: every action
    :param actions: written: GPI's actions, shape ``(B,)``
    :param attaining: written: whether each member attains GPI's value of the action taken, shape ``(P, B)``
    """
    n_policies, d = attaining.shape[0], weights.shape[1]
    q = np.empty((n_policies, stack.shape[1] // (n_policies * d)), dtype=np.float32)
    best = np.empty(q.shape[1], dtype=np.float32)
    for b in range(stack_rows.shape[0]):
        allowed_b = allowed[b] if allowed.shape[0] > 0 else allowed[0:0, 0]
        actions[b] = gpi_decision(stack[stack_rows[b]], weights[b], left_out[b], allowed_b, q, best)
        for p in range(n_policies):
            attaining[p, b] = q[p, actions[b]] == best[actions[b]]


@njit(cache=True, nogil=True)
def gpi_decision(
    row: np.ndarray, weights: np.ndarray, left_out: int, allowed: np.ndarray, q: np.ndarray, best: np.ndarray
) -> int:
    """
    GPI's action in one state (see :func:`gpi_attaining`): every member's ``w · ψ(s, a)`` written into ``q``
    (``(P, A)``, ``-inf`` for ``left_out`` and the actions ``allowed`` forbids, empty: none), their maximum over
    members into ``best``, and the first action of the largest (or the first NaN) returned.
    """
    n_policies, n_actions = q.shape
    d = weights.shape[0]
    for p in range(n_policies):
        for a in range(n_actions):
            start = (p * n_actions + a) * d
            q[p, a] = weighted_value(row[start : start + d], weights)
            if p == left_out or (allowed.shape[0] > 0 and not allowed[a]):
                q[p, a] = -np.inf
    for a in range(n_actions):
        best[a] = _numpy_max(q[:, a])
    return _numpy_argmax(best)


@njit(cache=True, nogil=True)
def table_row(observations: np.ndarray, flat: int, strides: np.ndarray, first_row: int) -> int:
    """The table row of the observation stored at row ``flat``: its mixed-radix index (integers: exact)."""
    row = 0
    for j in range(strides.shape[0]):
        row += np.int64(observations[flat, j]) * strides[j]
    return row - first_row


@njit(cache=True, nogil=True)
def sample_rows(
    key: np.ndarray,
    position: np.ndarray,
    positions: tuple[int, int, int],
    capacity: int,
    n_envs: int,
    next_offset: int,
    flat: np.ndarray,
    next_flat: np.ndarray,
) -> None:
    """
    The flat rows ``transition * n_envs + env`` of a minibatch of a replay buffer, drawn from numpy's global
    generator (``key``, ``position``: :func:`~sb3_sfgpi.tabular.numpy_random.global_stream`) as
    :meth:`MOReplayBuffer.sample_rows <sb3_sfgpi.common.buffers.MOReplayBuffer.sample_rows>` draws them: the same
    numbers, the same state left.

    :param positions: the buffer's ``valid_positions()``: transitions ``(i + shift) % capacity``, ``start <= i < stop``
    :param capacity: transitions per env the buffer holds
    :param next_offset: how many rows further the next observation is stored (``n_envs`` where observations and next
        observations share one array, else 0)
    :param flat: written: the rows
    :param next_flat: written: the rows of their next observations
    """
    start, stop, shift = positions
    random_integers(key, position, start, stop, flat)
    if shift:
        for i in range(flat.shape[0]):
            flat[i] = (flat[i] + shift) % capacity
    if n_envs > 1:
        random_integers(key, position, 0, n_envs, next_flat)  # the envs, before next_flat is written
        for i in range(flat.shape[0]):
            flat[i] = flat[i] * n_envs + next_flat[i]
    for i in range(flat.shape[0]):
        next_flat[i] = (flat[i] + next_offset) % (capacity * n_envs)


@njit(cache=True, nogil=True)
def sampled_td_update(
    table: tuple,
    target: tuple,
    storage: tuple,
    flat: np.ndarray,
    next_flat: np.ndarray,
    strides: np.ndarray,
    first_row: int,
    weights: np.ndarray,
    gamma: np.float32,
    lr: np.float32,
    rows: np.ndarray,
    td_error: np.ndarray,
) -> int:
    """
    The tabular TD update of the transitions stored at rows ``flat`` of a replay buffer, in place: first every TD error
    from the table as it was, then ``ψ(s, a) += lr · δ`` transition after transition (repeats add up, as
    ``np.add.at``).

    The target of a transition is ``r + (1 − done) γ ψ_target(s', a*)`` (``done``: terminated, not truncated) with
    ``a* = argmax_a w · ψ(s', a)`` over the actions the next state has, read from the online table.

    :param table: the online table: its storage, shape ``(slots + 1, n_actions, d)``, float32 (slot ``-1``: the
        default row), and its slot map (for each row its slot, ``-1``: not stored)
    :param target: the target table, the same pair (the online one where there is none)
    :param storage: the buffer's :class:`~sb3_sfgpi.common.buffers.FlatStorage`
    :param next_flat: the rows of the next observations
    :param strides: the table's mixed-radix strides of an observation's components, with ``first_row`` the row of
        the lowest observation
    :param rows: written: the table row of each transition's observation
    :param td_error: written: each transition's TD error before the update, shape ``(batch, d)``, float32
    :return: :data:`UPDATED`, :data:`DIVERGED` (the table may be partly updated) or :data:`STORE_ROWS` (nothing
        updated)
    """
    psi, slot_map = table
    target_psi, target_slot_map = target
    observations, next_observations, actions, rewards, dones, timeouts, next_forbidden = storage
    no_masks = np.zeros(0, dtype=np.bool_)
    if not _stored_rows(observations, flat, strides, first_row, slot_map, rows):
        return STORE_ROWS
    for i in range(flat.shape[0]):
        f = flat[i]
        next_row = table_row(next_observations, next_flat[i], strides, first_row)
        next_slot = slot_map[next_row] if slot_map[next_row] >= 0 else psi.shape[0] - 1
        forbidden = next_forbidden[f] if next_forbidden.shape[0] else no_masks
        best, finite = greedy_action(psi[next_slot], weights, forbidden)
        if not finite:
            return DIVERGED
        target_slot = target_slot_map[next_row] if target_slot_map[next_row] >= 0 else target_psi.shape[0] - 1
        terminated = dones[f] * (_ONE - timeouts[f])
        discount = (_ONE - terminated) * gamma
        slot, action = slot_map[rows[i]], actions[f]
        for k in range(psi.shape[2]):
            target_value = rewards[f, k] + discount * target_psi[target_slot, best, k]
            td_error[i, k] = target_value - psi[slot, action, k]
            if not np.isfinite(td_error[i, k]):
                return DIVERGED
    return UPDATED if _add_td_errors(psi, slot_map, rows, actions, flat, lr, td_error) else DIVERGED


@njit(cache=True, nogil=True)
def _stored_rows(
    observations: np.ndarray,
    flat: np.ndarray,
    strides: np.ndarray,
    first_row: int,
    slot_map: np.ndarray,
    rows: np.ndarray,
) -> bool:
    """Write the table row of each observation at ``flat`` into ``rows``; return whether the table stores them all."""
    stored = True
    for i in range(flat.shape[0]):
        rows[i] = table_row(observations, flat[i], strides, first_row)
        stored = stored and slot_map[rows[i]] >= 0
    return stored


@njit(cache=True, nogil=True)
def _add_td_errors(
    psi: np.ndarray,
    slot_map: np.ndarray,
    rows: np.ndarray,
    actions: np.ndarray,
    flat: np.ndarray,
    lr: np.float32,
    td_error: np.ndarray,
) -> bool:
    """``ψ(s, a) += lr · δ``, transition after transition; False at the first value beyond float32."""
    for i in range(flat.shape[0]):
        slot, action = slot_map[rows[i]], actions[flat[i]]
        for k in range(psi.shape[2]):
            value = psi[slot, action, k] + lr * td_error[i, k]
            if not np.isfinite(value):
                return False
            psi[slot, action, k] = value
    return True


@njit(cache=True, nogil=True)
def planning_sweeps(
    psi: np.ndarray,
    weights: np.ndarray,
    n_actions: int,
    own: np.ndarray,
    following_state: np.ndarray,
    pair: np.ndarray,
    summed: bool,
    scale: np.ndarray,
    expected_reward: np.ndarray,
    max_sweeps: int,
    tolerance: float,
) -> int:
    """
    :meth:`EmpiricalModel.sweep <sb3_sfgpi.tabular.planning.EmpiricalModel.sweep>`'s Jacobi sweeps on its copy of the
    rows, in place, with numpy's arithmetic in numpy's order: each state's greedy action by ``w · ψ`` (the first of
    the largest, the first NaN where there is one), each outcome's ``r̄ P̂ + (γ (1 − d̄) P̂) ψ(s', a*)`` in float64,
    summed over a pair's outcomes from 0 in their order where ``summed`` (as ``np.bincount``), the largest change,
    and the rows written back in ψ's precision.

    :param psi: the rows, one per state and action, shape ``(states * n_actions, d)``, updated
    :param own: each recorded pair's row; ``following_state``: each outcome's next state; ``pair``: its pair
    :param scale: ``γ (1 − d̄) P̂`` of each outcome, float64; ``expected_reward``: ``r̄ P̂``, shape ``(outcomes, d)``
    :return: the number of sweeps done
    """
    n_states, d = psi.shape[0] // n_actions, psi.shape[1]
    greedy = np.empty(n_states, dtype=np.int64)
    backed_up = np.empty((own.shape[0], d), dtype=np.float64)
    sweeps = 0
    while sweeps < max_sweeps:
        sweeps += 1
        for s in range(n_states):
            greedy[s] = s * n_actions + _first_argmax(psi, s * n_actions, n_actions, weights)
        if summed:
            backed_up[:] = 0.0
        for o in range(following_state.shape[0]):
            row, target = greedy[following_state[o]], pair[o]
            for k in range(d):
                value = expected_reward[o, k] + scale[o] * np.float64(psi[row, k])
                backed_up[target, k] = backed_up[target, k] + value if summed else value
        change, unsettled = 0.0, False
        for p in range(own.shape[0]):
            for k in range(d):
                moved = abs(np.float64(psi[own[p], k]) - backed_up[p, k])
                unsettled |= np.isnan(moved)
                change = max(change, moved)
        for p in range(own.shape[0]):
            for k in range(d):
                psi[own[p], k] = backed_up[p, k]
        if not unsettled and change <= tolerance:
            break
    return sweeps


@njit(cache=True, nogil=True)
def _first_argmax(psi: np.ndarray, first: int, n_actions: int, weights: np.ndarray) -> int:
    """numpy's ``argmax`` of ``w · ψ`` over a state's actions (rows ``first`` on): the first largest, or first NaN."""
    best, best_action = weighted_value(psi[first], weights), 0
    if np.isnan(best):
        return 0
    for a in range(1, n_actions):
        q = weighted_value(psi[first + a], weights)
        if np.isnan(q):
            return a
        if q > best:
            best, best_action = q, a
    return best_action

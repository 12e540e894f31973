"""Dyna-style planning: sweeps of the SF backup on a recorded model of the two-agent Four-Room.

The model is the experience of one agent of ``FourRoomParallelEnv`` (the ``four-room`` preset's ``"own"``
observations: cell and own collected objects, a table of 2.8 million rows) acting uniformly at random for
``N`` joint steps. The candidate is :meth:`~sb3_sfgpi.tabular.planning.EmpiricalModel.sweep`, which works on a
contiguous copy of the rows the sweeps touch, of a table holding its stored rows; the baseline is the backup it
replaced, written here on a dense table: the same Jacobi sweeps indexing the whole table at every sweep (greedy
actions read per outcome, one ``bincount`` per objective). Both start from the same table (optimistic values, as the
preset plans) and must end with identical tables (the note says so), since the candidate keeps the arithmetic and its
order.
"""

from __future__ import annotations

import numpy as np
from sfgpi_envs.four_room import FourRoomParallelEnv

from benchmarks._common import Row, fmt_time, interleaved_samples, paired_ratio
from sb3_sfgpi.common.weights import weighted_sum
from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.tabular.planning import TOLERANCE, EmpiricalModel, Experience
from sb3_sfgpi.tabular.sparse import SparseTable

NAME = "planning"
WEIGHTS = np.array([0.4, 0.59, 0.01], dtype=np.float32)
GAMMA = 0.95
SWEEPS = 60  # the four-room preset's planning_sweeps
OPTIMISTIC = 1.25  # the four-room preset's optimistic_init


def whole_table_sweep(model: EmpiricalModel, table: np.ndarray, weights: np.ndarray, gamma: float, sweeps: int) -> int:
    """The baseline: :meth:`EmpiricalModel.sweep` as it was, indexing the whole table at every sweep."""
    scale = (gamma * model.continues * model.probability)[:, None]
    expected_reward = model.reward * model.probability[:, None]
    for sweep in range(1, sweeps + 1):
        next_psi = table.reshape(-1, model.n_actions, table.shape[1])[model.next_first // model.n_actions]
        following = table[model.next_first + weighted_sum(next_psi, weights).argmax(axis=1)]
        contributions = expected_reward + scale * following
        columns = [np.bincount(model.pair, contributions[:, i], len(model.entries)) for i in range(table.shape[1])]
        backed_up = np.stack(columns, axis=1)
        change = np.abs(table[model.entries] - backed_up).max(initial=0.0)
        table[model.entries] = backed_up
        if change <= TOLERANCE:
            return sweep
    return sweeps


def random_walk_model(joint_steps: int, seed: int = 0) -> tuple[EmpiricalModel, int]:
    """The empirical model of ``agent_0``'s transitions under uniformly random actions, and its table's row count."""
    env = FourRoomParallelEnv(observation_mode="own")
    agent = env.possible_agents[0]
    net = TabularSFNetwork(env.observation_space(agent), env.action_space(agent), reward_dim=3)
    rng = np.random.default_rng(seed)
    observations, _ = env.reset(seed=seed)
    recorded: list[tuple] = []
    for _ in range(joint_steps):
        actions = {name: int(rng.integers(env.action_space(name).n)) for name in env.agents}
        next_observations, rewards, terminations, truncations, _ = env.step(actions)
        recorded.append(
            (observations[agent], actions[agent], next_observations[agent], terminations[agent], rewards[agent])
        )
        observations = next_observations
        if not env.agents or terminations[agent] or truncations[agent]:
            observations, _ = env.reset()
    obs, actions, next_obs, dones, rewards = (np.array(column) for column in zip(*recorded, strict=True))
    n_rows = net.table.n_rows
    experience = Experience.from_transitions(
        net.rows(obs), actions, net.rows(next_obs), dones.astype(np.float64), rewards, n_rows, net.n_actions
    )
    return experience.model(), n_rows


def run(quick: bool = False) -> list[Row]:
    """Time one planning (up to 60 sweeps from optimistic values) with both sweeps, on models of two sizes."""
    repeats = 3 if quick else 7
    return [_planning_row(joint_steps, repeats) for joint_steps in ((20_000, 100_000) if quick else (20_000, 200_000))]


def _planning_row(joint_steps: int, repeats: int) -> Row:
    model, n_rows = random_walk_model(joint_steps)
    start = np.zeros((n_rows * model.n_actions, 3), dtype=np.float32)
    untried = np.ones(len(start), dtype=bool)
    untried[model.entries] = False
    start[untried] = OPTIMISTIC
    stored = SparseTable(n_rows, model.n_actions * 3, default=OPTIMISTIC)  # the candidate's table: the same values
    tried = stored.store(model.entries // model.n_actions) * model.n_actions + model.entries % model.n_actions

    def plan(name: str) -> None:  # the only entries a planning changes are reset first
        if name == "contiguous rows":
            stored.values.reshape(-1, 3)[tried] = start[model.entries]
            model.sweep(stored, WEIGHTS, GAMMA, SWEEPS)
        else:
            start_copy[model.entries] = start[model.entries]
            whole_table_sweep(model, start_copy, WEIGHTS, GAMMA, SWEEPS)

    sweeps = ("contiguous rows", "whole table")
    start_copy = start.copy()

    samples = interleaved_samples({name: (lambda name=name: plan(name)) for name in sweeps}, repeats)
    ratio, q1, q3 = paired_ratio(samples, "whole table", "contiguous rows")
    same = np.array_equal(stored.dense().reshape(-1, 3), start_copy)
    return Row(
        NAME,
        f"{SWEEPS} sweeps, two-agent Four-Room model of {joint_steps:,} random steps "
        f"({len(model.entries):,} pairs, {len(model.pair):,} outcomes)",
        fmt_time(float(np.median(samples["contiguous rows"]))),
        fmt_time(float(np.median(samples["whole table"]))),
        ratio,
        note=f"same tables: {'yes' if same else 'NO'}; per-round quartiles {q1:.2f}–{q3:.2f}; "
        f"{repeats} interleaved rounds; the planned rows reset before each planning",
    )

"""GPI's episodes in one compiled call, where the env offers a packed step with episode ends and the set is tables.

:func:`compiled_gpi_episodes` reads each episode's packed state and first observations (:class:`PackedStarts`: the
env reset once per seed), then runs every episode to its end in
:func:`~sb3_sfgpi.tabular.gpi_episodes.run_gpi_episodes`: the returns :func:`~sb3_sfgpi.common.rollouts.run_lockstep`
gives for a GPI policy (bit for bit) and every decision traced. The episodes' final infos are not kept (validation
reads returns and decisions only).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from pettingzoo import ParallelEnv

from sb3_sfgpi.common.action_masks import ACTION_MASK
from sb3_sfgpi.common.rollouts import EpisodeReturns, batched_returns
from sb3_sfgpi.common.weights import validate_weight_rows
from sb3_sfgpi.tabular.network import TabularSFNetwork

if TYPE_CHECKING:
    from sb3_sfgpi.gpi import GPIPolicy
    from sb3_sfgpi.tabular.gpi_episodes import GPIEpisodes

#: The most agents an episode's live agents as bits hold.
MAX_AGENTS = 63


def compiled_gpi_episodes(
    starts: PackedStarts,
    policy_set: GPIPolicy,
    weights: np.ndarray,
    left_out: np.ndarray,
    seeds: Sequence[int],
    gamma: float,
    per_result: int,
) -> tuple[list[EpisodeReturns], GPIEpisodes] | None:
    """
    GPI's episodes over ``policy_set``, one per seed, each for its weights and without its member ``left_out``
    (``-1``: none), where they can run compiled: the env's own class offers a packed step with episode ends
    (``packed_dynamics().episode_step``), the set is tables on the CPU of the env's observation size and number of
    actions, and the env gives integer observations and no action masks. Else None (nothing was run).

    :param starts: the env's episodes' packed starts
    :return: the returns of each ``per_result`` consecutive episodes, and every decision
    """
    stacked = policy_set.stacked_tables()
    read = None if stacked is None else starts(seeds)
    if stacked is None or read is None:
        return None
    from sb3_sfgpi.tabular.gpi_episodes import run_gpi_episodes

    dynamics, states, observations, live = read
    network = cast(TabularSFNetwork, policy_set.networks[0])
    if observations.shape[2] != len(network.geometry[0]) or stacked.n_actions != starts.n_actions:
        return None  # observations or actions of another size than the tables': GPI or the env refuses them
    rows = validate_weight_rows(weights, policy_set.reward_dim).astype(np.float32)  # as GPI reads them
    episodes = run_gpi_episodes(
        dynamics, states, observations, live, stacked, network, rows, left_out.astype(np.int64), gamma
    )
    started = (live[:, None] >> np.arange(observations.shape[1])) & 1 == 1
    infos: list[dict[str, dict[str, Any]]] = [{} for _ in seeds]
    returns = batched_returns(starts.agents, started, episodes.discounted, episodes.total, infos, per_result)
    return returns, episodes


class PackedStarts:
    """
    The packed start of an env's episode for each seed: after ``reset(seed)``, its packed state, every agent's
    observation (zeros for an agent absent) and the live agents as bits. Each seed's is read once (the env reset with
    it): validation's episodes start from the same seeds in every iteration, and ``reset(seed)`` decides an episode.

    :param env: an env whose own class offers ``packed_dynamics`` (else no start is read)
    """

    def __init__(self, env: ParallelEnv):
        self.env, self.agents = env, list(env.possible_agents)
        #: the agents' number of actions (-1: they differ)
        sizes = {getattr(env.action_space(agent), "n", -1) for agent in self.agents}
        self.n_actions = int(sizes.pop()) if len(sizes) == 1 else -1
        self._starts: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}
        self._dynamics: Any = None
        self._usable = getattr(type(env), "packed_dynamics", None) is not None and len(self.agents) <= MAX_AGENTS

    def __call__(self, seeds: Sequence[int]) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray] | None:
        """
        The env's packed dynamics and each seed's start (``(seeds, ...)`` arrays); None where the env has no packed
        step with episode ends, gives an observation that is not a vector of integers, or an action mask.
        """
        for seed in seeds:
            if self._usable and seed not in self._starts:
                self._usable = self._read(seed)
        if not self._usable:
            return None
        states, observations, live = zip(*(self._starts[seed] for seed in seeds), strict=True)
        return self._dynamics, np.stack(states), np.stack(observations), np.array(live, dtype=np.int64)

    def _read(self, seed: int) -> bool:
        """Reset the env with ``seed`` and keep its start; False where it cannot run compiled."""
        from sb3_sfgpi.tabular.joint_steps import PACKED_STEP_SIGNATURE

        obs, infos = self.env.reset(seed=seed)
        dynamics = self.env.packed_dynamics()  # type: ignore[attr-defined]
        arrays = [np.asarray(obs[agent]) for agent in self.env.agents]
        masked = any(ACTION_MASK in infos.get(agent, {}) for agent in self.env.agents)
        if masked or not all(np.issubdtype(array.dtype, np.integer) and array.ndim == 1 for array in arrays):
            return False
        if PACKED_STEP_SIGNATURE not in getattr(getattr(dynamics, "episode_step", None), "nopython_signatures", ()):
            return False
        first = np.zeros((len(self.agents), arrays[0].size), dtype=np.int64)
        for agent, array in zip(self.env.agents, arrays, strict=True):
            first[self.agents.index(agent)] = array
        self._dynamics = dynamics
        self._starts[seed] = (dynamics.state, first, sum(1 << self.agents.index(agent) for agent in self.env.agents))
        return True

"""Monte-Carlo rollouts of a joint policy in a PettingZoo ParallelEnv with vector rewards."""

from __future__ import annotations

import numbers
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from pettingzoo import ParallelEnv

from sb3_sfgpi.common.action_masks import ACTION_MASK, info_mask
from sb3_sfgpi.common.checks import check_parallel_reset, check_parallel_step

#: Maps the observations of the live agents to their actions: ``policy(observations)``, or, where the env gives
#: action masks (:mod:`~sb3_sfgpi.common.action_masks`), ``policy(observations, action_masks=masks)`` with the live
#: agents' masks (every action allowed for an agent whose info has none).
JointPolicy = Callable[..., dict[str, Any]]
#: The actions of a batch of observations, each for its own weights: ``policy(observations, weights, action_masks,
#: agents)`` with shapes ``(n, ...)``, ``(n, d)``, ``(n, n_actions)`` or None, and the agent of each row.
RowPolicy = Callable[[np.ndarray, np.ndarray, np.ndarray | None, list[str]], np.ndarray]


@dataclass
class EpisodeReturns:
    """
    Vector returns of every agent over several episodes.

    :param discounted: agent -> array ``(n_episodes, d)`` of discounted returns
    :param undiscounted: agent -> array ``(n_episodes, d)`` of plain sums of rewards
    :param final_infos: per episode, the last info dict of every agent
    :param step_infos: per episode (when recorded), agent -> info key -> its value after every step; only the
        numeric entries of the infos are kept
    """

    discounted: dict[str, np.ndarray]
    undiscounted: dict[str, np.ndarray]
    final_infos: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    step_infos: list[dict[str, dict[str, list[float]]]] = field(default_factory=list)
    _means: dict[str, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)

    def mean_discounted(self, agent: str) -> np.ndarray:
        """
        Mean discounted vector return of ``agent``: the Monte-Carlo estimate of ``V^π`` (computed once: validation
        scores the same episodes again for every policy set that would take the same actions).
        """
        if agent not in self._means:
            mean = self._means[agent] = self.discounted[agent].mean(axis=0)
            mean.flags.writeable = False  # shared by every call
        return self._means[agent]

    def mean_discounted_over(self, agents: Iterable[str] | None = None) -> np.ndarray:
        """Mean over ``agents`` (default: all of them) of their mean discounted vector returns."""
        return np.mean(
            [self.mean_discounted(agent) for agent in (self.discounted if agents is None else agents)], axis=0
        )

    def mean_undiscounted(self, agent: str) -> np.ndarray:
        """Mean undiscounted vector return of ``agent``."""
        return self.undiscounted[agent].mean(axis=0)


class _Episode:
    """
    One episode of a ParallelEnv under way: reset with its seed, stepped with the live agents' actions, its returns
    added up.

    :param env: the env (reset here)
    :param seed: the seed of the reset
    :param gamma: discount factor of the discounted returns
    :param record_infos: keep the numeric entries of every agent's info after every step
    """

    def __init__(self, env: ParallelEnv, seed: int | None, gamma: float, record_infos: bool):
        self.env, self.gamma, self.record_infos = env, gamma, record_infos
        self.obs, self.infos = env.reset(seed=seed)
        check_parallel_reset(env, 0, self.obs, env.possible_agents)
        self.agents = list(env.agents)
        dims = {agent: env.reward_space(agent).shape[0] for agent in self.agents}  # type: ignore[attr-defined]
        self.discounted = {agent: np.zeros(dims[agent]) for agent in self.agents}
        self.total = {agent: np.zeros(dims[agent]) for agent in self.agents}
        self.last_infos = dict(self.infos)
        self.trace: dict[str, dict[str, list[float]]] = {}
        self.discount, self.steps = 1.0, 0

    @property
    def live(self) -> list[str]:
        """The agents still in the episode (none: it is over)."""
        return list(self.env.agents)

    def observations(self) -> tuple[dict[str, Any], dict[str, np.ndarray] | None]:
        """The live agents' observations and action masks (None where no agent has one)."""
        live = self.live
        return {agent: self.obs[agent] for agent in live}, _live_masks(self.env, live, self.infos)

    def step(self, actions: dict[str, Any]) -> None:
        """Step the env with the live agents' actions and add their rewards."""
        live = self.live
        self.obs, rewards, terminations, truncations, self.infos = self.env.step(actions)
        self.steps += 1
        outcome = (self.obs, rewards, terminations, truncations)
        check_parallel_step(self.env, 0, live, outcome, self.env.agents, self.steps)
        for agent, reward in rewards.items():
            self.discounted[agent] += self.discount * np.asarray(reward, dtype=np.float64)
            self.total[agent] += reward
        self.last_infos.update(self.infos)
        if self.record_infos:
            _record_step(self.trace, self.infos)
        self.discount *= self.gamma


def _returns_of(episodes: Sequence[_Episode]) -> EpisodeReturns:
    """The returns of finished episodes, in their order."""
    discounted: dict[str, list[np.ndarray]] = {}
    undiscounted: dict[str, list[np.ndarray]] = {}
    for episode in episodes:
        for agent in episode.agents:
            discounted.setdefault(agent, []).append(episode.discounted[agent])
            undiscounted.setdefault(agent, []).append(episode.total[agent])
    return EpisodeReturns(
        {agent: np.array(values) for agent, values in discounted.items()},
        {agent: np.array(values) for agent, values in undiscounted.items()},
        [episode.last_infos for episode in episodes],
        [episode.trace for episode in episodes if episode.record_infos],
    )


def run_episodes(
    env: ParallelEnv,
    policy: JointPolicy,
    n_episodes: int,
    gamma: float,
    seed: int | None = None,
    record_infos: bool = False,
) -> EpisodeReturns:
    """
    Run full episodes of a PettingZoo ParallelEnv with vector rewards and collect each agent's returns.

    :param env: the env (it is reset, once per episode)
    :param policy: maps the live agents' observations to their actions (and their action masks, where the env
        gives any: :data:`JointPolicy`)
    :param n_episodes: number of episodes
    :param gamma: discount factor of the discounted returns
    :param seed: seed of the first reset (episode ``i`` uses ``seed + i``)
    :param record_infos: also keep the numeric entries of every agent's info after every step
        (:attr:`EpisodeReturns.step_infos`), e.g. waiting times over a traffic episode
    :return: the returns of every agent that was present at reset
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be at least 1, got {n_episodes}")
    episodes = []
    for i in range(n_episodes):
        episode = _Episode(env, None if seed is None else seed + i, gamma, record_infos)
        while episode.live:
            observations, masks = episode.observations()
            episode.step(policy(observations) if masks is None else policy(observations, action_masks=masks))
        episodes.append(episode)
    return _returns_of(episodes)


def run_lockstep(
    envs: Sequence[ParallelEnv] | BatchedEpisodes,
    policy: RowPolicy,
    weights: np.ndarray,
    seeds: Sequence[int],
    gamma: float,
    per_result: int = 1,
    decided: Callable[[list[int]], None] | None = None,
) -> list[EpisodeReturns]:
    """
    One episode on each env, all stepped together: at every step the live agents of every episode act by one call
    of ``policy``, each for its episode's weights. Each episode is the one :func:`run_episodes` runs on its env with
    its seed and a joint policy for its weights, where ``policy`` decides every row as it would alone.

    :param envs: one env per episode (each is reset), or the episodes as arrays (:class:`BatchedEpisodes`, one per
        seed: one call steps them all; the same decisions in the same rows and the same returns, added up in the
        same order)
    :param policy: the actions of a batch of observations, each for its own weights (:data:`RowPolicy`)
    :param weights: each episode's weights, shape ``(n_episodes, d)``
    :param seeds: each episode's seed
    :param gamma: discount factor of the discounted returns
    :param per_result: consecutive episodes whose returns form one result (the episodes of one weight)
    :param decided: called after every call of ``policy`` with the episode (index into ``envs``) of each row (an
        episode's rows are consecutive)
    :return: the returns of each ``per_result`` consecutive episodes
    """
    n_episodes = len(envs) if isinstance(envs, Sequence) else len(seeds)
    if not n_episodes == len(weights) == len(seeds):
        raise ValueError(f"one env, weight and seed per episode: got {n_episodes}, {len(weights)} and {len(seeds)}")
    if per_result < 1 or n_episodes % per_result:
        raise ValueError(f"per_result must divide the {n_episodes} episodes, got {per_result}")
    if not isinstance(envs, Sequence):
        return _run_batched(envs, policy, np.asarray(weights), seeds, gamma, per_result, decided)
    episodes = [_Episode(env, seed, gamma, False) for env, seed in zip(envs, seeds, strict=True)]
    while running := [(k, episode) for k, episode in enumerate(episodes) if episode.live]:
        stepped = [(k, *episode.observations()) for k, episode in running]
        rows = [(j, agent) for j, (_, observations, _) in enumerate(stepped) for agent in observations]
        obs = np.stack([stepped[j][1][agent] for j, agent in rows])
        row_weights = np.asarray(weights)[[stepped[j][0] for j, _ in rows]]
        agents = [agent for _, agent in rows]
        actions = policy(obs, row_weights, _row_masks(episodes, stepped, rows), agents).tolist()
        if decided is not None:
            decided([stepped[j][0] for j, _ in rows])
        joint: list[dict[str, Any]] = [{} for _ in stepped]
        for (j, agent), action in zip(rows, actions, strict=True):
            joint[j][agent] = action
        for (k, _, _), joint_actions in zip(stepped, joint, strict=True):
            episodes[k].step(joint_actions)
    return [_returns_of(episodes[i : i + per_result]) for i in range(0, len(episodes), per_result)]


class BatchedEpisodes(Protocol):
    """
    Episodes of one env held as arrays and stepped together, where an env offers them (its
    ``batched_episodes(n)``; Four-Room's: :class:`~sfgpi_envs.four_room_dynamics.FourRoomEpisodes`): each is the
    episode the env itself runs from a reset with its seed, without action masks. :func:`run_lockstep` steps them.
    """

    #: the agents' names, in the order of the arrays' agent axis (the env's ``possible_agents``)
    agents: list[str]

    @property
    def reward_dim(self) -> int:
        """Number of objectives."""

    def reset(self, seeds: Sequence[int | None]) -> tuple[np.ndarray, np.ndarray]:
        """Every episode reset with its seed: the observations ``(episodes, agents, ...)`` and the live agents."""

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Every episode with a live agent steps (``actions``: ``(episodes, agents)``, the live agents' are read): the
        rewards ``(episodes, agents, d)`` and the agents live after the step.
        """

    def observations(self) -> np.ndarray:
        """Every agent's observation now, shape ``(episodes, agents, ...)``."""

    def final_infos(self) -> list[dict[str, dict[str, Any]]]:
        """Each episode's last info of every agent."""


def batched_episodes(env: ParallelEnv, n: int) -> BatchedEpisodes | None:
    """
    ``n`` episodes of ``env`` as arrays where its class offers them (``batched_episodes``), else None. A wrapper does
    not pass them on: what it changes of the observations or rewards the arrays would not.
    """
    make = getattr(type(env), "batched_episodes", None)
    return None if make is None else make(env, n)


def _run_batched(
    batch: BatchedEpisodes,
    policy: RowPolicy,
    weights: np.ndarray,
    seeds: Sequence[int],
    gamma: float,
    per_result: int,
    decided: Callable[[list[int]], None] | None,
) -> list[EpisodeReturns]:
    """:func:`run_lockstep` on batched episodes: one step of every live agent of every episode a loop."""
    observations, live = batch.reset(seeds)
    started = live.copy()
    discounted = np.zeros((*live.shape, batch.reward_dim))
    total = np.zeros_like(discounted)
    discount = np.ones(len(live))
    joint = np.zeros(live.shape, dtype=np.int64)
    names_of = np.array(batch.agents, dtype=object)
    while live.any():
        episodes, agents = np.nonzero(live)
        stepping = live.any(axis=1)
        joint[episodes, agents] = policy(
            observations[episodes, agents], weights[episodes], None, names_of[agents].tolist()
        )
        if decided is not None:
            decided(episodes.tolist())
        rewards, live = batch.step(joint)
        rewards = rewards[episodes, agents]
        discounted[episodes, agents] += discount[episodes, None] * rewards.astype(np.float64)
        total[episodes, agents] += rewards
        discount[stepping] *= gamma
        observations = batch.observations()
    return batched_returns(batch.agents, started, discounted, total, batch.final_infos(), per_result)


def batched_returns(
    agents: list[str],
    started: np.ndarray,
    discounted: np.ndarray,
    total: np.ndarray,
    infos: list[dict[str, dict[str, Any]]],
    per_result: int,
) -> list[EpisodeReturns]:
    """Each ``per_result`` consecutive episodes' returns of the agents that started in one of them (of batched
    episodes: ``started`` ``(episodes, agents)``, returns ``(episodes, agents, d)``)."""
    shape = (len(started) // per_result, per_result, len(agents))
    started_in = started.reshape(shape)
    every, present = started_in.all(axis=1).tolist(), started_in.any(axis=1).tolist()
    by_result = [returns.reshape(*shape, -1) for returns in (discounted, total)]
    results = []
    for r in range(shape[0]):
        rows = [
            {
                agent: block[r, :, k].copy() if every[r][k] else block[r, started_in[r, :, k], k]
                for k, agent in enumerate(agents)
                if present[r][k]
            }
            for block in by_result
        ]
        results.append(EpisodeReturns(*rows, infos[r * per_result : (r + 1) * per_result]))
    return results


def _row_masks(
    episodes: list[_Episode], stepped: list[tuple[int, dict, dict | None]], rows: list[tuple[int, str]]
) -> np.ndarray | None:
    """The action masks of a lockstep batch's rows (every action allowed where an episode has none), or None."""
    if all(masks is None for _, _, masks in stepped):
        return None

    def mask(j: int, agent: str) -> np.ndarray:
        k, _, masks = stepped[j]
        return np.ones(episodes[k].env.action_space(agent).n, dtype=bool) if masks is None else masks[agent]

    return np.stack([mask(j, agent) for j, agent in rows])


def _live_masks(
    env: ParallelEnv, live: list[str], infos: Mapping[str, Mapping[str, Any]]
) -> dict[str, np.ndarray] | None:
    """The live agents' action masks from their last infos, or None where no agent has one."""
    if not any(ACTION_MASK in infos.get(agent, ()) for agent in live):
        return None
    masks = {agent: info_mask(infos.get(agent, {}), env.action_space(agent).n, f"agent {agent!r}") for agent in live}
    return {
        agent: np.ones(env.action_space(agent).n, dtype=bool) if mask is None else mask for agent, mask in masks.items()
    }


def _record_step(trace: dict[str, dict[str, list[float]]], infos: Mapping[str, Mapping[str, Any]]) -> None:
    for agent, info in infos.items():
        columns = trace.setdefault(agent, {})
        for key, value in info.items():
            if isinstance(value, (numbers.Real, np.bool_)):  # bool and numpy scalars included
                columns.setdefault(key, []).append(float(value))

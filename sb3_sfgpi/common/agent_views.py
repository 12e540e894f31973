"""The views and logs of the multi-agent runner's learners: each learner's agents as a VecEnv, folderless loggers.

The runner (:class:`~sb3_sfgpi.multiagent.MultiAgentRunner`) steps one shared ParallelEnv for all agents; each
learner sees its agents through an :class:`AgentVecEnv`, which SB3 takes for the VecEnv it was built on, and is
handed each joint step's :class:`Transitions` as the :class:`Rows` its replay buffer stores.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from pettingzoo import ParallelEnv
from stable_baselines3.common.logger import Logger, make_output_format
from stable_baselines3.common.vec_env import VecEnv


class AgentVecEnv(VecEnv):
    """
    The agents of one learner, in a shared ParallelEnv, as the VecEnv their SFDQN expects: one slot per agent.

    With independent learners each agent has a view of its own (one slot); with parameter sharing one learner has
    all the agents as its slots (SB3's ``n_envs``). It is never stepped by the learner: the runner steps the shared
    env for all agents and hands each learner its transitions. ``reset()`` returns the agents' current
    observations.

    :param env: the shared env
    :param agents: the agent's name, or the names of the agents sharing the learner
    :param n_copies: copies of the env the runner steps (the view has a slot per agent and copy)
    """

    vector_rewards = True
    render_mode = None  # the shared env is rendered by the runner's owner, not through a view

    def __init__(self, env: ParallelEnv, agents: str | list[str], n_copies: int = 1):
        self.agents = [agents] if isinstance(agents, str) else list(agents)
        first = self.agents[0]
        super().__init__(n_copies * len(self.agents), env.observation_space(first), env.action_space(first))
        self.agent = first if len(self.agents) == 1 else f"{first}..{self.agents[-1]}"
        self.reward_space = env.reward_space(first)  # type: ignore[attr-defined]
        self.current_obs: np.ndarray | None = None

    def reset(self) -> np.ndarray:
        assert self.current_obs is not None, "the runner must reset the shared env first"
        return self.current_obs

    def step_async(self, actions: np.ndarray) -> None:
        raise RuntimeError(f"{self.agent}'s view cannot be stepped alone: MultiAgentRunner steps the shared env")

    def step_wait(self) -> Any:
        raise RuntimeError(f"{self.agent}'s view cannot be stepped alone: MultiAgentRunner steps the shared env")

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        raise RuntimeError(f"{self.agent}'s view has no env methods")

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))

    def get_images(self) -> list[np.ndarray | None]:
        return [None] * self.num_envs


def folderless_logger(verbose: int) -> Logger:
    """An SB3 logger writing to stdout (``verbose > 0``) or nowhere, without creating a folder."""
    return Logger(None, [make_output_format("stdout", "")] if verbose else [])


def remove_interrupted_logs(directory: str, log_name: str) -> None:
    """
    Delete the TensorBoard folders (``log_name_N``, SB3's naming) that an interrupted attempt at the same iteration
    left: the iteration is done again from its start, and its logs replace theirs instead of lying beside them.
    """
    for folder in Path(directory).glob(f"{log_name}_*"):
        if folder.name[len(log_name) + 1 :].isdigit() and folder.is_dir() and not folder.is_symlink():
            shutil.rmtree(folder)


class Transitions(NamedTuple):
    """A joint step as one learner sees it: its live slots, their ``(copy, agent)`` keys, what the copies returned."""

    agents: list[tuple[int, str]]
    slots: list[int]
    buffer_actions: np.ndarray
    obs: dict[tuple[int, str], Any]
    rewards: dict[tuple[int, str], Any]
    terminations: dict[tuple[int, str], bool]
    truncations: dict[tuple[int, str], bool]
    infos: dict[tuple[int, str], dict]


def replaced(rows: np.ndarray, slots: list[int], values: np.ndarray) -> np.ndarray:
    """A copy of ``rows`` with ``rows[slots] = values``."""
    rows = rows.copy()
    rows[slots] = values
    return rows


class Rows(NamedTuple):
    """Transitions as a replay buffer's ``add_rows`` takes them."""

    obs: np.ndarray
    next_obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    timeouts: np.ndarray
    next_masks: np.ndarray | None = None

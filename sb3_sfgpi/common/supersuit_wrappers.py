"""PettingZoo envs wrapped with SuperSuit, taken as they come.

SuperSuit's wrappers keep what MA-SFOLS needs out of reach or change it on the way:

* most of them go through PettingZoo's AEC conversion (``aec_to_parallel_wrapper`` around the wrapped AEC env),
  which drops the ``reward_space`` of a multi-objective env: :class:`UnwrappedRewardSpace` gives it back from the
  env inside (the reward's shape is the env's; a reward wrapper may change its values, not its length);
* ``black_death_v3`` keeps agents that left the episode with zero observations and a scalar reward 0:
  :class:`BlackDeathRewards` makes that reward the zero vector, for those agents only (a scalar reward anywhere
  else is an error, as it always was);
* ``pad_action_space_v0`` gives every agent the largest ``Discrete`` space and maps an agent's padded actions to its
  action 0: :class:`MaskPaddedActions` gives each agent the action mask of its own actions, so learners and GPI
  never take a padded one.

:func:`prepared` applies what an env needs; ``as_parallel_env`` calls it on every ParallelEnv.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo.utils.wrappers import BaseParallelWrapper

from sb3_sfgpi.common.action_masks import ACTION_MASK, info_mask

#: The attributes through which PettingZoo's and SuperSuit's wrappers hold the env they wrap.
_INNER = ("env", "aec_env", "par_env")


def wrapper_chain(env: Any) -> Iterator[Any]:
    """``env`` and every env it wraps, outermost first, through PettingZoo's and SuperSuit's wrappers."""
    seen: set[int] = set()
    while env is not None and id(env) not in seen:
        seen.add(id(env))
        yield env
        env = next((vars(env)[name] for name in _INNER if name in vars(env)), None)


def prepared(env: Any) -> Any:
    """
    ``env`` with what its SuperSuit wrappers took away given back (see the module); an env without them as it is.

    :raises ValueError: ``black_death_v3`` over observation spaces that are not ``Box`` (SuperSuit's own condition,
        checked here before an episode starts); a SuperSuit reward wrapper whose function does not map a vector
        reward to one of the same shape (``clip_reward_v0``'s ``max``/``min``)
    """
    if not hasattr(env, "reward_space") and hasattr(env.unwrapped, "reward_space"):
        env = UnwrappedRewardSpace(env)
    _check_reward_functions(env)
    black_death = next((inner for inner in wrapper_chain(env) if _is_black_death(inner)), None)
    if black_death is not None:
        env = BlackDeathRewards(env, black_death)
    own = _own_action_counts(env)
    if own:
        env = MaskPaddedActions(env, own)
    return env


def _check_reward_functions(env: Any) -> None:
    """Refuse a SuperSuit reward wrapper whose function fails on, or reshapes, the env's zero reward vector."""
    if not hasattr(env, "reward_space"):
        return
    for inner in wrapper_chain(env):
        change = vars(inner).get("_change_reward_fn")
        if change is None or not type(inner).__module__.startswith("supersuit."):
            continue
        for agent in env.possible_agents:
            zero = np.zeros(env.reward_space(agent).shape, dtype=np.float32)
            try:
                changed = np.shape(change(zero))
            except Exception as error:  # noqa: BLE001 - whatever the user's or SuperSuit's function raises
                changed = f"{type(error).__name__}: {error}"
            if changed != zero.shape:
                raise ValueError(
                    f"SuperSuit's reward wrapper ({type(inner).__name__}, e.g. clip_reward_v0) does not keep a vector "
                    f"reward of shape {zero.shape} for agent {agent!r} (got {changed}): multi-objective rewards need a "
                    "function of the whole vector (reward_lambda_v0 with numpy, e.g. np.clip)"
                )


def _is_black_death(env: Any) -> bool:
    return type(env).__name__ == "black_death_par" and type(env).__module__.startswith("supersuit.")


def _own_action_counts(env: Any) -> dict[str, int]:
    """
    Where SuperSuit padded ``Discrete`` action spaces (an action wrapper of SuperSuit's inside, a space larger than
    the env's own): each padded agent's own number of actions.

    :raises ValueError: a padded space with a ``start`` (SuperSuit's padding ignores it: the agent's actions would be
        others)
    """
    if not any(type(inner).__module__.startswith("supersuit.lambda_wrappers.action") for inner in wrapper_chain(env)):
        return {}
    own = {}
    for agent in env.possible_agents:
        outer_space, inner_space = env.action_space(agent), env.unwrapped.action_space(agent)
        if isinstance(outer_space, spaces.Discrete) and isinstance(inner_space, spaces.Discrete):
            if inner_space.n < outer_space.n:
                if inner_space.start != 0:
                    raise ValueError(
                        f"SuperSuit's pad_action_space_v0 ignores the start of {inner_space} (agent {agent!r}): its "
                        "padded actions are not the agent's; pad with sb3_sfgpi.PadActions instead"
                    )
                own[agent] = int(inner_space.n)
    return own


class UnwrappedRewardSpace(BaseParallelWrapper):
    """The ``reward_space`` of the env inside the wrappers, for wrappers that do not pass it on."""

    def reward_space(self, agent: str) -> spaces.Box:
        return self.env.unwrapped.reward_space(agent)


class BlackDeathRewards(BaseParallelWrapper):
    """
    The scalar reward 0 that SuperSuit's ``black_death_v3`` gives the agents that left the episode, as the zero
    vector of their reward space; every other reward as it is.

    :param env: the env (``black_death`` somewhere inside)
    :param black_death: the ``black_death`` wrapper: the agents of the env it wraps are those still in the episode
    :raises ValueError: an agent whose observation space is not a ``Box``
    """

    def __init__(self, env: Any, black_death: Any):
        super().__init__(env)
        for agent in env.possible_agents:
            space = env.observation_space(agent)
            if not isinstance(space, spaces.Box):
                raise ValueError(
                    f"SuperSuit's black_death_v3 needs Box observation spaces (it feeds zeros), agent {agent!r} has "
                    f"{space}: leave black_death out (MA-SFOLS handles agents that leave) or flatten first"
                )
        self._black_death = black_death

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        still_in = set(self._black_death.env.agents)
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        rewards = {
            agent: np.zeros(self.reward_space(agent).shape, dtype=np.float32)
            if agent not in still_in and np.ndim(reward) == 0
            else reward
            for agent, reward in rewards.items()
        }
        return observations, rewards, terminations, truncations, infos


class MaskPaddedActions(BaseParallelWrapper):
    """
    Action masks for agents whose actions were padded (SuperSuit's ``pad_action_space_v0``): each may take its own
    first ``n`` actions only (and, where the env gives masks of its own, only those of them).

    :param env: the env
    :param own: agent -> its own number of actions (the others are padding)
    """

    def __init__(self, env: Any, own: dict[str, int]):
        super().__init__(env)
        self._own = own

    def _masked(self, infos: dict[str, Any]) -> dict[str, Any]:
        masked_infos = dict(infos)
        for agent, n_own in self._own.items():
            if agent in infos:
                n = int(self.action_space(agent).n)
                given = info_mask(infos[agent], n, f"agent {agent!r}")
                mask = np.arange(n) < n_own
                masked_infos[agent] = {**infos[agent], ACTION_MASK: mask if given is None else mask & given}
        return masked_infos

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        observations, infos = self.env.reset(seed=seed, options=options)
        return observations, self._masked(infos)

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        return observations, rewards, terminations, truncations, self._masked(infos)

"""What an env hands the learners, checked where it appears: finite rewards and observations, known agents.

A NaN or inf reward stored in a replay buffer spreads into every successor feature that bootstraps from it, and the
failure shows much later (a policy set that cannot be saved, an OLS value that is not finite). An agent that was not
in the episode shows as a bare ``KeyError`` far from its cause. These checks raise a ``ValueError`` naming the env,
the agent and the step, before anything is stored.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces


def env_name(env: Any) -> str:
    """A short name of an env (a Gymnasium id, a PettingZoo ``metadata["name"]``, or its class)."""
    for candidate in (env, getattr(env, "unwrapped", None)):
        spec = getattr(candidate, "spec", None)
        if getattr(spec, "id", None):
            return str(spec.id)
        metadata = getattr(candidate, "metadata", None)
        if isinstance(metadata, Mapping) and isinstance(metadata.get("name"), str):
            return metadata["name"]
    return type(getattr(env, "unwrapped", env)).__name__


def check_finite(value: Any, what: str, env: Any, agent: Any, step: int) -> None:
    """
    Refuse a reward or an observation holding NaN or inf.

    :param env: the env, or its name (named only in the error: nothing is computed for a finite value)
    :raises ValueError: "<env>, agent <agent>, step <step>: the <what> is not finite (...)"
    """
    values = value.values() if isinstance(value, Mapping) else (value,)
    for part in values:
        array = np.asarray(part)
        if array.dtype.kind in "fc" and not np.isfinite(array).all():
            shown = np.array2string(array.ravel()[:8], precision=4, separator=", ")
            name = env if isinstance(env, str) else env_name(env)
            raise ValueError(
                f"{name}, agent {agent}, step {step}: the {what} is not finite ({shown}); it was not stored (NaN or "
                "inf would spread into every successor feature)"
            )


def check_homogeneous(env: Any, agents: Sequence[str]) -> None:
    """
    Refuse agents whose spaces differ (MA-SFOLS shares policies between agents), or actions that are not Discrete.

    :raises ValueError: naming the space, the agents and what to do
    """
    first = agents[0]
    for agent in agents:
        for kind in ("observation_space", "action_space", "reward_space"):
            if getattr(env, kind)(agent) != getattr(env, kind)(first):
                raise ValueError(
                    f"MA-SFOLS shares policies between agents: all agents need the same spaces, but the "
                    f"{kind.replace('_', ' ')} of {agent!r} is {getattr(env, kind)(agent)} and of {first!r} "
                    f"{getattr(env, kind)(first)}; pad them into one layout that means the same at every agent "
                    "(TrafficSignalEnv: observation_fn='padded'; Discrete actions: sb3_sfgpi.PadActions(env)), "
                    "and with sharing='shared' every policy learns at every agent"
                )
    if not isinstance(env.action_space(first), spaces.Discrete):
        raise ValueError(f"SFDQN needs Discrete actions, got {env.action_space(first)}")


def check_parallel_reset(env: Any, copy: int, observations: Mapping[str, Any], known: Collection[str]) -> None:
    """
    Refuse a reset that brings agents the learners do not know, or non-finite observations.

    :param known: the agents the learners were made for (the env's ``possible_agents``)
    :raises ValueError: naming the env, the agent and the step (0)
    """
    for agent, observation in observations.items():
        if agent not in known:
            raise ValueError(
                f"{env_name(env)}, agent {agent!r}, step 0 (reset of copy {copy}): not one of the env's "
                f"possible_agents {sorted(known)}; every agent must be declared in possible_agents"
            )
        check_finite(observation, "observation", env, repr(agent), 0)


def check_parallel_step(env: Any, copy: int, acted: Collection[str], results: tuple, agents: Any, step: int) -> None:
    """
    Refuse a ParallelEnv step whose results name an agent that did not act (one that left and came back, or an
    unknown one), that lack an agent that acted, or that hold non-finite observations or rewards, or rewards of
    another shape than the agent's ``reward_space``.

    :param acted: the agents that acted in this step (those live before it)
    :param results: what ``step`` returned: observations, rewards, terminations, truncations, infos
    :param agents: the env's agents after the step
    :raises ValueError: naming the env, the agent and the step
    """
    if not step_is_sound(env, acted, *results[:4], agents):  # the common case costs a few set and float operations
        _detailed_step_check(env, copy, acted, results, agents, step)


def _detailed_step_check(env: Any, copy: int, acted: Collection[str], results: tuple, agents: Any, step: int) -> None:
    """:func:`check_parallel_step`, every rule in turn: the first broken one raises."""
    observations, rewards, terminations, truncations = results[:4]
    for agent in {*observations, *rewards, *agents}:
        if agent not in acted:
            raise ValueError(
                f"{_where(env, agent, step, copy)}: in the step's results but it did not act (an agent that left the "
                "episode must not come back in it, and only agents of possible_agents present at reset may act)"
            )
    returned = (("observation", observations), ("reward", rewards), ("termination", terminations))
    for agent in acted:
        for what, values in (*returned, ("truncation", truncations)):
            if agent not in values:
                raise ValueError(f"{_where(env, agent, step, copy)}: it acted but the step returned no {what} for it")
        check_finite(rewards[agent], "reward", env, repr(agent), step)
        check_finite(observations[agent], "observation", env, repr(agent), step)
        expected = env.reward_space(agent).shape
        if np.shape(rewards[agent]) != expected:
            raise ValueError(
                f"{_where(env, agent, step, copy)}: the reward has shape {np.shape(rewards[agent])}, its "
                f"reward_space {expected}"
            )


def step_is_sound(
    env: Any,
    acted: Collection[str],
    observations: Mapping[str, Any],
    rewards: Mapping[str, Any],
    terminations: Mapping[str, Any],
    truncations: Mapping[str, Any],
    agents: Any,
) -> bool:
    """
    Whether :func:`check_parallel_step` would find nothing wrong, decided quickly for the usual results (numpy
    rewards and observations); False where it cannot tell at once (the full check then looks closer).

    A sum of finite values is finite, and NaN or inf in a value makes the sum NaN or inf: one sum per array tells
    finiteness (a sum that overflows sends the step to the full check, which finds nothing).
    """
    acted = acted if isinstance(acted, (set, frozenset)) else set(acted)
    if not (
        observations.keys() == acted == rewards.keys()
        and acted <= terminations.keys()
        and acted <= truncations.keys()
        and acted.issuperset(agents)
    ):
        return False
    for agent in acted:
        reward, observation = rewards[agent], observations[agent]
        if not (
            isinstance(reward, np.ndarray)
            and reward.shape == env.reward_space(agent).shape
            and _finite(reward)
            and isinstance(observation, np.ndarray)
            and _finite(observation)
        ):
            return False
    return True


def _finite(array: np.ndarray) -> bool:
    """Whether a real array holds no NaN or inf, at the cost of one sum for a small one (False for other dtypes)."""
    if array.dtype.kind in "biu":
        return True
    if array.dtype.kind != "f":
        return False
    if array.size <= 64:  # summed in Python floats: float64, so no sum of float32 values overflows
        return math.isfinite(sum(array.ravel().tolist()))
    return bool(np.isfinite(array).all())


def warn_of_swapped_flags(
    terminations: Mapping[str, bool], truncations: Mapping[str, bool], steps: int, time_limit: int
) -> bool:
    """
    Warn where an episode ended with every agent truncated, none terminated, before the env's declared time limit:
    terminations and truncations swapped?

    :param steps: the episode's steps
    :return: whether it warned
    """
    truncated = all(truncations.get(a, False) and not terminations.get(a, False) for a in truncations)
    if not truncated or steps >= time_limit:
        return False
    warnings.warn(
        f"every agent was truncated after {steps} steps, before the env's time limit ({time_limit}): does it return "
        "terminations and truncations swapped (MOMAland 0.2's item gathering and beach do)? Then wrap it in "
        "sb3_sfgpi.SwapTerminationsTruncations",
        stacklevel=3,  # the runner's learn(), where it stepped
    )
    return True


def _where(env: Any, agent: Any, step: int, copy: int) -> str:
    """Where a check failed: the env, the agent, the step (and the copy of the env, after the first)."""
    return f"{env_name(env)}, agent {agent!r}, step {step}" + (f" of copy {copy}" if copy else "")

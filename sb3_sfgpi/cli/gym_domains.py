"""Presets for single-agent Gymnasium ids with vector rewards: ``sb3-sfgpi train deep-sea-treasure-v0`` is SFOLS + GPI.

A domain the entry points do not name is looked up in Gymnasium's registry (MO-Gymnasium's ids join it when
``mo_gymnasium`` is installed). Its env must follow MO-Gymnasium's convention (a ``reward_space`` Box of shape
``(d,)``). The learners are tables where the observations are small integers (the planning and relative optimism of
the Four-Room presets, read against the env's own reward scale; every policy's table planned on the run's pooled
replay, :mod:`sb3_sfgpi.tabular.pooling`), else MLPs.
"""

from __future__ import annotations

import contextlib
import functools
import warnings
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.common.reward_space import env_reward_dim
from sb3_sfgpi.common.seeded_draws import with_seeded_draws
from sb3_sfgpi.common.single_agent import SingleAgentParallelEnv
from sb3_sfgpi.common.vec_env import import_registering_package
from sb3_sfgpi.run_settings import GAMMA

#: Packages whose import registers multi-objective ids in Gymnasium's registry (imported when installed).
REGISTERING_PACKAGES = ("mo_gymnasium",)
#: The most states a tabular learner is picked for (beyond, an MLP).
MAX_TABULAR_STATES = 1_000_000

TABULAR_LEARNER = {
    "policy": "TabularPolicy",
    "learning_rate": 0.1,
    "gamma": GAMMA,
    "buffer_size": 1_000_000,
    "learning_starts": 0,
    "train_freq": 1,
    "exploration_initial_eps": 1.0,
    "exploration_fraction": 0.5,
    "exploration_final_eps": 0.05,
    "planning_sweeps": 60,
    "optimistic_init": "rmax_1.25",
}
#: Whether runs with tables pool their replay across iterations and plan Π's SFs on it
#: (:mod:`sb3_sfgpi.tabular.pooling`; measured on the known-front problems: docs, experiments/known_fronts).
TABULAR_POOL_REPLAY = True
#: Deep learners (observations a table cannot hold): one network ψ(s, a, w) per agent for the whole run, trained over
#: OLS's weights and acting by GPI over them (``ConditionedMlpPolicy``, two heads), with GPI-LS's minecart settings
#: (γ 0.98, replay 200,000, target network every 200 steps, ε from 1 to 0.05 over the first 50,000 steps) on a
#: 3 × 128 network updated three times per env step (about the compute per step of GPI-LS's 4 × 256 updated once),
#: replay drawn by each transition's error for the learner's weights (GPI-PD's prioritised replay: the rare steps of a
#: mine the current weights value are drawn more); measured against one head, 4 × 256, one new MLP per iteration and
#: uniform replay on minecart: docs, experiments/deep_fronts.
MLP_LEARNER = {
    "policy": "ConditionedMlpPolicy",
    "policy_kwargs": {"net_arch": [128, 128, 128]},
    "learning_rate": 3e-4,
    "gamma": 0.98,
    "buffer_size": 200_000,
    "batch_size": 128,
    "learning_starts": 100,
    "train_freq": 1,
    "gradient_steps": 3,
    "target_update_interval": 200,
    "exploration_initial_eps": 1.0,
    "exploration_final_eps": 0.05,
    "exploration_steps": 50_000,
    "replay_buffer_class": "PrioritizedMOReplayBuffer",
}

#: The run settings of tables besides their learner's: a new policy joins Π only if GPI does no worse with it on 50
#: validation weights.
TABULAR_RUN = {"validation_weights": 50, "prune": False}
#: The run settings of deep learners besides their learner's: a member of Π is the conditioned network as it was when it
#: joined; it joins only if GPI does no worse with it on 200 validation weights, and members GPI does better without
#: retire (measured against members that follow the learner's latest network on minecart; 200 weights against 50 find
#: the members that make GPI wander between them on minecart-deterministic); every episode acts, and trains its half of
#: each minibatch, for a weight drawn from the learner's support, GPI-LS's behaviour; after every iteration the
#: learner's latest network is offered again at the support's earlier weights, for validation to admit (each measured on
#: minecart and deep-sea-treasure with MLP SFs: docs, experiments/levers).
MLP_RUN = {"validation_weights": 200, "prune": True, "episode_weights": "support", "rebind_support": True}


def make_gym_env(env_id: str, **env_kwargs: Any) -> SingleAgentParallelEnv:
    """The Gymnasium env ``env_id`` as a ParallelEnv of one agent (picklable with ``functools.partial``)."""
    _register_ids()
    # Gymnasium's env checker wants scalar rewards (MO-Gymnasium's own ``make`` turns it off too).
    return SingleAgentParallelEnv(with_seeded_draws(gym.make(env_id, **{"disable_env_checker": True, **env_kwargs})))


def gym_preset(env_id: str) -> dict[str, Any] | None:
    """
    The preset data of a registered Gymnasium id, or None where the registry does not know it.

    :raises UsageError: a registered env without a vector ``reward_space``
    """
    _register_ids()
    if env_id not in gym.registry:
        return None
    env = _made(env_id)
    try:
        reward_dim = env_reward_dim(env)
        tabular = _n_states(env.observation_space) <= MAX_TABULAR_STATES
    except ValueError as error:
        raise UsageError(f"{env_id}: {error}") from None
    finally:
        env.close()
    return {
        "make_env": functools.partial(make_gym_env, env_id),
        "env_kwargs": {},
        "learner_kwargs": dict(TABULAR_LEARNER if tabular else MLP_LEARNER),
        "steps_per_iteration": 10_000,
        "iterations": 20 if tabular else 15,  # deep: GPI-PD's budget on minecart
        "n_test_weights": 50,
        "value_episodes": 5,
        "eval_episodes": 5 if tabular else 1,  # deep episodes run to the time limit while a policy idles
        **(TABULAR_RUN if tabular else MLP_RUN),
        "pool_replay": tabular and TABULAR_POOL_REPLAY,
        "objectives": [f"objective {i}" for i in range(reward_dim)],
        "run_file_env_kwargs": [],  # a run file sets no env argument of an arbitrary env
    }


def _made(env_id: str) -> gym.Env:
    """
    ``gym.make(env_id)`` to read its spaces, without the warnings of its construction (the env the run trains on
    gives them).

    :raises UsageError: the env needs a package that is not installed (named, with the command that installs it)
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return gym.make(env_id, disable_env_checker=True)
    except ImportError as error:
        missing = error.name or str(error)
        raise UsageError(
            f"{env_id} needs {missing!r}, which is not installed: pip install {missing.replace('_', '-')}"
        ) from None
    except gym.error.DependencyNotInstalled as error:
        raise UsageError(f"{env_id} needs a package that is not installed: {error}") from None


def _n_states(observation_space: gym.Space) -> float:
    """How many observations a table would need (infinity for a space a table cannot hold)."""
    from sb3_sfgpi.tabular.network import observation_radices

    try:
        _, n_values = observation_radices(observation_space)
    except ValueError:
        return float("inf")
    return float(np.prod(n_values.astype(np.float64)))


def _register_ids() -> None:
    for package in REGISTERING_PACKAGES:
        with contextlib.suppress(ImportError):
            import_registering_package(package)

"""Ready-made domains for the ``sb3-sfgpi`` command line (entry-point group ``sb3_sfgpi.domains``).

Each function returns plain data plus an env constructor: the env, its keyword arguments, the SFDQN
arguments of the learners and the defaults of the MA-SFOLS run. Nothing here imports ``sb3_sfgpi``.
"""

from __future__ import annotations

from typing import Any


def four_room() -> dict[str, Any]:
    """The paper's two-agent Four-Room (Sec. 5.1): tabular multi-objective Q-learning, Table 1 parameters."""
    from sfgpi_envs.four_room import FourRoomParallelEnv

    return {
        "make_env": FourRoomParallelEnv,
        "env_kwargs": {"observation_mode": "xy"},
        "learner_kwargs": {
            "policy": "TabularPolicy",
            "learning_rate": 0.1,
            "gamma": 0.95,
            "buffer_size": 1_000_000,
            "batch_size": 32,
            "learning_starts": 0,
            "train_freq": 1,
            "exploration_initial_eps": 1.0,
            "exploration_fraction": 0.5,
            "exploration_final_eps": 0.05,
        },
        "steps_per_iteration": 10_000,
        "iterations": 12,
        "n_test_weights": 12,
        "value_episodes": 1,
        "eval_episodes": 1,
    }


def traffic() -> dict[str, Any]:
    """The paper's three-intersection SUMO scenario with pedestrians (Sec. 5.2): MLP SFDQN per traffic light."""
    from sfgpi_envs.traffic import TrafficSignalEnv

    return {
        "make_env": TrafficSignalEnv,
        "env_kwargs": {"num_seconds": 500, "delta_time": 5, "min_green": 10, "max_green": 50},
        "learner_kwargs": {
            "policy": "MlpPolicy",
            "learning_rate": 1e-3,
            "gamma": 0.95,
            "buffer_size": 1_000_000,
            "batch_size": 64,
            "learning_starts": 200,
            "train_freq": 1,
            "target_update_interval": 500,
            "exploration_initial_eps": 1.0,
            "exploration_fraction": 0.3,
            "exploration_final_eps": 0.05,
            "policy_kwargs": {"net_arch": [64, 64]},
        },
        "steps_per_iteration": 2_000,
        "iterations": 8,
        "n_test_weights": 25,
        "value_episodes": 1,
        "eval_episodes": 1,
    }

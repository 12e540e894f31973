"""Ready-made domains for the ``sb3-sfgpi`` command line (entry-point group ``sb3_sfgpi.domains``).

Each function returns plain data plus an env constructor: the env, its keyword arguments, the SFDQN
arguments of the learners and the defaults of the MA-SFOLS run. Nothing here imports ``sb3_sfgpi``.
"""

from __future__ import annotations

from typing import Any


def four_room() -> dict[str, Any]:
    """
    The paper's two-agent Four-Room (Sec. 5.1): tabular multi-objective Q-learning, Table 1 parameters.

    Each agent observes its cell and the objects it has collected itself (``observation_mode="own"``); the other
    agent stays unobserved, as in the paper. With the cell alone (``"xy"``) the task is not Markov even for one
    agent: a cell next to an object keeps the object's value after it is taken. With every gone object (``"full"``)
    a policy learns to wait for the other learner's collections, and under GPI, next to a partner that behaves
    differently, it waits for ever.

    The learners plan on their replay buffer's model and explore optimistically (``planning_sweeps``,
    ``optimistic_init``). A new policy joins Π only if GPI does no worse with it on the simplex extrema and 100
    Dirichlet(1) validation weights (enough that a policy which only ties on a few weights and is worse elsewhere
    stays out); after every iteration validation also retires the policies without which GPI does better
    (``prune``), and an iteration's policies left out one by one are tried together (``admit_together``: two
    agents' policies can mislead GPI alone and help it together). Once the simplex extrema are handed out, both
    agents train for the top corner weight (``ols_batch="same-after-extrema"``), beside a partner acting for it as
    at execution. Each agent has its own learner, as in the paper. What each choice was measured to do, and the
    alternatives that lost: docs, experiments/levers.
    """
    from sfgpi_envs.four_room import FourRoomParallelEnv

    return {
        "make_env": FourRoomParallelEnv,
        "env_kwargs": {"observation_mode": "own"},
        "learner_kwargs": {
            "policy": "TabularPolicy",
            "learning_rate": 0.1,
            "gamma": 0.95,
            "buffer_size": 1_000_000,
            "batch_size": 32,
            "learning_starts": 0,
            "train_freq": 1,
            "exploration_initial_eps": 1.0,
            "exploration_fraction": 0.5,  # ε falls over half of each learner's steps
            "exploration_final_eps": 0.05,
            "planning_sweeps": 60,  # Dyna: sweeps of the SF backup on the replay buffer's model, every 5,000 steps
            # optimism in the face of untried pairs, 1.25 x the largest reward (here 1), settled at the end of learn()
            "optimistic_init": "rmax_1.25",
        },
        "steps_per_iteration": 50_000,
        "iterations": 10,
        "n_test_weights": 12,
        "ols_batch": "same-after-extrema",  # the extrema one per agent (Algorithm 1), then the top corner for both
        "validation_weights": 100,  # a new policy joins Π only if GPI does no worse with it on these weights
        "prune": True,  # and a policy leaves Π when GPI does better without it
        "admit_together": True,  # an iteration's policies left out one by one are tried together
        "sharing": "independent",  # the paper's decentralised learners, one per agent
        "objectives": ["blue squares", "green triangles", "red circles"],  # objects collected, one reward each
        # what a run directory's run.json may set (sb3_sfgpi.trust): all but render_mode
        "run_file_env_kwargs": ["starts", "goal_reward", "max_steps", "observation_mode"],
        "value_episodes": 1,
        "eval_episodes": 1,
    }


def traffic() -> dict[str, Any]:
    """
    The paper's three-intersection SUMO scenario with pedestrians (Sec. 5.2): an MLP SFDQN per traffic light.

    Budget: up to ``iterations x steps_per_iteration`` joint steps (5 simulated seconds each) per agent, plus after
    every iteration one value episode per new policy, a GPI episode for each of the 25 test weights (in
    ``eval_workers`` processes) and the validation of the new policies.

    Each step's reward is minus the waiting spent in it (``objectives=["vehicle_delay", "pedestrian_delay"]``), a
    green cut short by the minimum green is deferred rather than ignored (``early_change="defer"``), and the learning
    rate falls from 10^-3 to 0 over each iteration (``"lin_0.001"``). Two long iterations rather than three short
    ones: the policies trained near the pedestrian-heavy weights need the steps. Rewards are scaled per objective
    to per-step values of order one, with a factor between the objectives that puts the knee of the front near the
    middle of the simplex; episode metrics and infos stay in seconds.

    Values are estimated with each new policy run at all three intersections (``value_mode="shared"``, comparable
    across agents) and GPI acts over the policies whose values form the CCS (``gpi_set="ccs"``): dominated
    policies' SFs only mislead it. Π is validated and pruned as in ``four-room``, on 12 validation weights.

    Eq. 24's rewards (the paper's: decreases of the accumulated waiting times): ``--env 'objectives=
    ["vehicle_waiting", "pedestrian_waiting"]'``. Another network: ``--env net_file=NET --env route_file=ROUTES``
    (and ``--env 'objectives=["vehicle_delay", "co2"]'`` where it has no pedestrian crossings); MA-SFOLS needs
    lights with the same observation and action spaces (the same lanes and green phases). Measurements: docs,
    experiments/traffic and experiments/levers.
    """
    from sfgpi_envs.traffic import TrafficSignalEnv

    return {
        "make_env": TrafficSignalEnv,
        "env_kwargs": {
            "num_seconds": 500,
            "delta_time": 5,
            "max_green": 50,
            "objectives": ["vehicle_delay", "pedestrian_delay"],  # minus the waiting spent in each step (see above)
            "early_change": "defer",  # a change asked before the minimum green is made when it ends
            # per-step rewards of order one; the other objectives of the menu (chosen with `--env objectives=[...]`)
            # scaled to the order of the vehicles' on the default network under random actions
            "reward_scale": {
                "vehicle_waiting": 0.01,
                "pedestrian_waiting": 0.25,
                "vehicle_delay": 0.01,
                "pedestrian_delay": 0.025,
                "vehicle_queue": 0.1,
                "co2": 0.005,
            },
        },
        "learner_kwargs": {
            "policy": "MlpPolicy",
            "learning_rate": "lin_0.001",  # from 10^-3 linearly to 0 over each iteration
            "gamma": 0.95,
            "buffer_size": 100_000,
            "batch_size": 64,
            "learning_starts": 200,
            "train_freq": 1,
            "target_update_interval": 500,
            "exploration_initial_eps": 1.0,
            "exploration_fraction": 0.3,
            "exploration_final_eps": 0.05,
            "policy_kwargs": {"net_arch": [64, 64]},
        },
        "steps_per_iteration": 12_000,  # two long iterations rather than three short ones (see above)
        "iterations": 2,
        "n_test_weights": 25,
        "value_episodes": 1,
        "value_mode": "shared",  # each new policy run at all three intersections: values comparable across agents
        "gpi_set": "ccs",  # GPI over the policies whose values form the CCS: dominated SFs only mislead it
        "validation_weights": 12,  # a new policy joins Π only if GPI does no worse with it on validation weights
        "prune": True,  # and a policy leaves Π when GPI does better without it
        "eval_episodes": 1,
        "eval_workers": 2,
        # for `sb3-sfgpi compare` and its plots
        "objectives": ["vehicles", "pedestrians"],  # rewards: minus their scaled waiting in each step
        "baselines": {
            "fixed-time": {"signal_control": "fixed-time"},
            "actuated": {"signal_control": "actuated"},
            "max-pressure": {"signal_control": "max-pressure"},
        },
        "episode_metrics": [
            ["vehicle_waiting_time_mean", "mean vehicle waiting time [s]"],
            ["pedestrian_waiting_time_mean", "mean pedestrian waiting time [s]"],
            ["co2_emitted_kg", "CO2 emitted [kg]"],
        ],
        "step_metrics": [
            ["vehicle_wait_total", "vehicle waiting time [s]"],
            ["pedestrian_wait_total", "pedestrian waiting time [s]"],
        ],
        "compare_weights": [[1.0, 0.0], [0.8, 0.2], [0.6, 0.4], [0.5, 0.5], [0.4, 0.6], [0.2, 0.8], [0.0, 1.0]],
        "fixed_weights": [[0.5, 0.5], [0.4, 0.6], [0.2, 0.8]],
        # what a run directory's run.json may set (sb3_sfgpi.trust): files SUMO only reads and numbers; never sumo_args,
        # additional or actuated files (SUMO writes the outputs they name), gui or render_mode (run sumo-gui)
        "run_file_env_kwargs": [
            "net_file",
            "route_file",
            "num_seconds",
            "begin_time",
            "mdp",
            "delta_time",
            "yellow_time",
            "min_green",
            "max_green",
            "early_change",
            "objectives",
            "action_mode",
            "observation_fn",  # only the string "padded" can come from a file: objects are refused by the env
            "signal_control",
            "backend",
            "seed",
            "sumo_warnings",
            "reward_scale",
        ],
    }

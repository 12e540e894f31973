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
    agent: a cell next to an object keeps the object's value after it is taken, and greedy tables walk back and
    forth onto the empty cell for the rest of the episode. With every gone object (``"full"``) a policy learns to
    wait for the other learner's collections, and under GPI, next to a partner that behaves differently, it waits
    for ever. Measured over 10 iterations of 3 seeds of both algorithms (README "Four-Room"): GPI's mean w·return
    0.20-0.54 with ``"xy"``, 0.65-1.08 with ``"full"``, 0.84-1.32 with ``"own"``.

    The learners plan on their replay buffer's model and explore optimistically (``planning_sweeps``,
    ``optimistic_init``), and a new policy joins Π only if GPI does no worse with it on the simplex extrema and 100
    Dirichlet(1) validation weights (``validation_weights``): without validation GPI fell from 1.289 at iteration 4
    to 1.159 at 10 (3 seeds), with it the curve ends at its best. After every iteration validation also retires the
    policies without which GPI does better (``prune``): 1.303 ± 0.015 → 1.322 ± 0.006 at iteration 10 with 12
    validation weights; 100 instead of 12 judge GPI over the Dirichlet(1) weights closely enough not to admit
    policies that only tie on a few: 1.330 ± 0.005 → 1.336 ± 0.000 (README "Four-Room"). An iteration's policies left
    out one by one are then tried together (``admit_together``): two agents' policies can each mislead GPI alone and
    help it together. The same on those three seeds; Random + GPI over seeds 0–5 1.290 ± 0.100 → 1.330 ± 0.012 (its
    seed 3 1.067 → 1.306).

    Each agent has its own learner, as in the paper. One learner that both agents act with and feed
    (``--sharing shared``, one weight per iteration) ends higher, 1.329 ± 0.001 → 1.336 ± 0.004 on today's code, and
    starts lower (iteration 1: 1.028 → 0.907, behind Random + GPI at every iteration; README "Four-Room"). A learner
    per agent fed the transitions of the agents training for its weights (``--sharing experience``) ends lower,
    1.313 ± 0.012.

    ε falls from 1 to 0.05 over half of each learner's steps. Over a tenth of them a pair of one iteration did as well
    at its own weight as a pair of ten (at [0.40, 0.59, 0.01]), but GPI ends lower: 1.294 ± 0.016 (0.3: 1.309 ± 0.016,
    0.8: 1.323 ± 0.009, the preset's 0.5: 1.329 ± 0.001; 3 seeds, README "Four-Room"). Ending at 0.01 instead of the
    paper's 0.05 raises GPI (1.334 ± 0.008) and the learners trained a priori alike (1.332 → 1.337): 0.998× either way.
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
            # ε falls over half of each learner's steps: over 0.1, 0.3 or 0.8 of them GPI ends lower (README)
            "exploration_fraction": 0.5,
            "exploration_final_eps": 0.05,
            "planning_sweeps": 60,  # Dyna: sweeps of the SF backup on the replay buffer's model, every 5,000 steps
            "optimistic_init": 1.25,  # optimism in the face of the untried pairs, settled at the end of learn()
        },
        "steps_per_iteration": 50_000,
        "iterations": 10,
        "n_test_weights": 12,
        # the extrema one per agent (Algorithm 1), then both agents train for the top corner weight, beside a partner
        # acting for it as at execution: 1.322 ± 0.006 -> 1.330 ± 0.005 at iteration 10, the same before (README)
        "ols_batch": "same-after-extrema",
        # a new policy joins Π only if GPI does no worse with it on validation weights: 100, not 12, so that a policy
        # that only ties on a few weights and is worse elsewhere stays out (1.330 ± 0.005 -> 1.336 ± 0.000, README)
        "validation_weights": 100,
        "prune": True,  # and a policy leaves Π when GPI does better without it
        # an iteration's policies left out one by one are tried together: two agents' policies can mislead GPI alone
        # and help it together (Random + GPI, seeds 0-5: 1.290 ± 0.100 -> 1.330 ± 0.012; MA-SFOLS the same, README)
        "admit_together": True,
        "sharing": "independent",  # the paper's decentralised learners, one per agent ("shared": see above)
        "objectives": ["blue squares", "green triangles", "red circles"],  # objects collected, one reward each
        # what a run directory's run.json may set (sb3_sfgpi.trust): all but render_mode
        "run_file_env_kwargs": ["starts", "goal_reward", "max_steps", "observation_mode"],
        "value_episodes": 1,
        "eval_episodes": 1,
    }


def traffic() -> dict[str, Any]:
    """
    The paper's three-intersection SUMO scenario with pedestrians (Sec. 5.2): an MLP SFDQN per traffic light.

    Budget: up to ``iterations x steps_per_iteration`` joint steps (5 simulated seconds each) per agent, plus
    after every iteration one value episode per new policy and a GPI episode for each of the 25 test weights
    (in ``eval_workers`` processes), and the validation of the new policies: about 15-30 minutes on two cores.

    Since 2026-11-25 (issue 10; README "Traffic", 3 seeds): each step's reward is minus the waiting spent in it
    (``objectives=["vehicle_delay", "pedestrian_delay"]``), a green cut short by the minimum green is deferred rather
    than ignored (``early_change="defer"``), the learning rate falls from 10^-3 to 0 over each iteration
    (``"lin_0.001"``), and MA-SFOLS trains 2 iterations of 12,000 steps rather than 3 of 8,000 (the same maximum). GPI
    at [1, 0] keeps vehicles waiting 4.00 s (SUMO's actuated program 4.48 s; the previous preset 5.56 s), pedestrians
    at [0, 1] 2.47 s (5.11 s), and GPI's w·return is within 5% of the scalarised learners at [0.5, 0.5], [0.4, 0.6]
    and [0.2, 0.8] (+1.4%, -4.3%, -3.5%). With 3 x 8,000 steps the same configuration kept GPI 9.6% below them at
    [0.2, 0.8]: the policies trained near that weight had 8,000 steps. Pessimistic SFs (``n_critics=2``) did worse.

    Rewards are scaled per objective, vehicles x 0.01 and pedestrians x 0.025: per-step rewards of order one for the
    networks, and a factor 2.5 between the objectives that puts the knee of the front near the middle of the simplex
    (with x 0.25, set for Eq. 24's rewards, the pedestrians outweigh the vehicles at every weight but [1, 0]).
    Episode metrics and infos stay in seconds.

    Values are estimated with each new policy run at all three intersections (``value_mode="shared"``) and GPI
    acts over the policies whose values form the CCS (``gpi_set="ccs"``): dominated policies' SFs only mislead it.
    Π is validated and pruned as in ``four-room`` (``validation_weights``, ``prune``): a policy joins Π only if GPI
    does no worse with it on 12 validation weights, and leaves it when GPI does better without it. Validation costs
    15 GPI episodes per candidate. Four-Room's ``admit_together`` is off: on the earlier preset's three seeds it tried
    an iteration's left-out policies together 4 times and kept them out every time (GPI 0.02-0.10 lower).

    Eq. 24's rewards (the paper's: decreases of the accumulated waiting times): ``--env 'objectives=
    ["vehicle_waiting", "pedestrian_waiting"]'`` (scaled x 0.01 and x 0.25). Another network: ``--env net_file=NET
    --env route_file=ROUTES`` (and ``--env 'objectives=["vehicle_delay", "co2"]'`` where it has no pedestrian
    crossings); MA-SFOLS needs lights with the same observation and action spaces (the same lanes and green phases).
    """
    from sfgpi_envs.traffic import TrafficSignalEnv

    return {
        "make_env": TrafficSignalEnv,
        "env_kwargs": {
            "num_seconds": 500,
            "delta_time": 5,
            "min_green": 10,
            "max_green": 50,
            "objectives": ["vehicle_delay", "pedestrian_delay"],  # minus the waiting spent in each step (see above)
            "early_change": "defer",  # a change asked before the minimum green is made when it ends
            # vehicles, pedestrians: see above; the other objectives of the menu (chosen with `--env objectives=[...]`)
            # scaled to per-step rewards of the order of the vehicles' on the default network under random actions
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
        "steps_per_iteration": 12_000,  # 2 x 12,000 rather than 3 x 8,000: longer-trained policies (see above)
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
        "baselines": {"fixed-time": {"signal_control": "fixed-time"}, "actuated": {"signal_control": "actuated"}},
        "episode_metrics": [
            ["vehicle_waiting_time_mean", "mean vehicle waiting time [s]"],
            ["pedestrian_waiting_time_mean", "mean pedestrian waiting time [s]"],
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
            "delta_time",
            "yellow_time",
            "min_green",
            "max_green",
            "early_change",
            "objectives",
            "action_mode",
            "signal_control",
            "backend",
            "seed",
            "sumo_warnings",
            "reward_scale",
        ],
    }

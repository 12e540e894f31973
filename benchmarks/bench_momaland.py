"""MOMAland's own baseline: MA-SFOLS + GPI on item gathering against MOMAland's centralised GPI-LS.

    python -m benchmarks momaland --seeds 0 1 2     # 15 × 10,000 joint steps each; with the morl extra, the peer too
    python -m benchmarks momaland --quick           # 2 × 1,500 steps

The env is ``moitem_gathering_v0.parallel_env()`` as MOMAland's ``momaland/learning/morl/train_ig_GPILS.py`` makes it
(its default 8 × 8 map, two agents, three item types, 50 steps) with terminations and truncations put back in their
places (:class:`~sb3_sfgpi.common.parallel_wrappers.SwapTerminationsTruncations`: MOMAland 0.2 returns them swapped,
so that a learner would bootstrap past the end of the items and not at the time limit), for both methods.

* **Ours**: :class:`~sb3_sfgpi.masfols.MASFOLS` with one learner shared by both agents (``sharing="shared"``: one
  weight an iteration, trained on both agents' transitions), the deep preset's (one weight-conditioned ψ(s, a, w),
  :data:`~sb3_sfgpi.cli.gym_domains.MLP_LEARNER`, :data:`~sb3_sfgpi.cli.gym_domains.MLP_RUN`) at MOMAland's γ 0.99;
  one Π over both agents, each seeing itself as the first (:class:`~sb3_sfgpi.SelfFirstAgentIds`: the env marks
  agents by their index). A member learned by one agent's own learner misleads the other agent's GPI where that
  learner never went (the agents start in opposite corners); a shared learner's members have seen both.
* **The peer** (where ``morl_baselines`` imports): morl-baselines' ``GPILS`` with the script's settings
  (:data:`PEER_SETTINGS`) on MOMAland's ``CentraliseAgent`` of the same env (one agent choosing the joint action from
  the map), 15 × 10,000 steps; its gradient updates per env step are the script's 10 unless ``peer_updates`` says.

Both are scored by the same protocol: GPI's greedy team on 50 Dirichlet(1) test weights (``random_weights(3, 50,
rng=0)``), one episode per weight from ``derive_seed(seed, "eval", i)``; **EU** is the mean of ``w ·`` the team's
discounted return (both agents' rewards summed, γ 0.99). Every item gathered gives at most ``mean w · (3, 3, 2)``
undiscounted (the ceiling in the rows); the discounted front is not known.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import MORL_MISSING, Row
from benchmarks.bench_known_fronts import (
    N_TEST_WEIGHTS,
    SEEDS,
    Outcome,
    drop_sampled_indices,
    learned,
    peer_device,
    seed_peer_generators,
    seed_row,
    seeded,
    summary_row,
)
from benchmarks.gpi_ls_runs import train_gpi_ls
from sb3_sfgpi import MASFOLS, SelfFirstAgentIds, SwapTerminationsTruncations
from sb3_sfgpi.cli.gym_domains import MLP_LEARNER, MLP_RUN
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights

NAME = "momaland"
ENV_ID = "moitem_gathering_v0"
GAMMA = 0.99  # MOMAland's script's
STEPS, ITERATIONS = 10_000, 15  # MOMAland's script's: 15 × 10,000
QUICK = (1_500, 2)
#: Items of each type on the default map: the undiscounted team return of every weight's best episode.
ITEMS = np.array([3.0, 3.0, 2.0])
#: ``train_ig_GPILS.py``'s GPILS arguments (MOMAland 0.2.0), those that are not the env, seed or logging.
PEER_SETTINGS = {
    "max_grad_norm": None,
    "learning_rate": 3e-4,
    "gamma": GAMMA,
    "batch_size": 256,
    "net_arch": [256, 256],
    "buffer_size": 200_000,
    "initial_epsilon": 1.0,
    "final_epsilon": 0.05,
    "epsilon_decay_steps": 75_000,
    "learning_starts": 100,
    "alpha_per": 0.6,
    "min_priority": 0.01,
    "per": False,
    "use_gpi": True,
    "gradient_updates": 10,
    "target_net_update_freq": 200,
    "tau": 1,
}


def make_env() -> Any:
    """Item gathering as MOMAland's script makes it, terminations and truncations in their places."""
    from momaland.envs.item_gathering import moitem_gathering_v0

    return SwapTerminationsTruncations(moitem_gathering_v0.parallel_env(num_timesteps=50, randomise=False))


def make_agents_env() -> Any:
    """Ours: :func:`make_env` with each agent seeing itself as the first (:class:`~sb3_sfgpi.SelfFirstAgentIds`), so
    that one Π serves both agents."""
    return SelfFirstAgentIds(make_env())


def run(
    quick: bool = False,
    seeds: Sequence[int] | None = None,
    peer_updates: int | None = None,
    runs: Path | None = None,
) -> list[Row]:
    """
    EU of MA-SFOLS + GPI and of MOMAland's GPI-LS on item gathering, at the same env steps.

    :param quick: the smoke run's tiny budget
    :param seeds: the seeds (default 0, 1, 2)
    :param peer_updates: the peer's gradient updates per env step (default: its script's 10)
    :param runs: where our runs keep their run directories, ``item-gathering-s<seed>``, and the peer its checkpoints,
        and both go on from them (None: no files; see :func:`~benchmarks.bench_known_fronts.learned`)
    """
    try:
        import momaland  # noqa: F401 - the env's package: pip install momaland
    except ImportError:
        return [Row(NAME, ENV_ID, "not run: pip install momaland")]
    seeds = list(SEEDS if seeds is None else seeds)
    steps, iterations = QUICK if quick else (STEPS, ITERATIONS)
    weights = random_weights(len(ITEMS), N_TEST_WEIGHTS, rng=0)
    ceiling = f"every item: {float(np.mean(weights @ ITEMS)):.4f} undiscounted"
    ours = [_train_ours(weights, seed, steps, iterations, runs) for seed in seeds]
    case = f"{ENV_ID} (2 agents, d=3), MA-SFOLS + GPI, one learner shared, {iterations} × {steps:,} joint steps"
    rows = [summary_row(NAME, case, ours, None, ceiling, seeds)]
    rows += [seed_row(NAME, f"{ENV_ID} seed {seed}", o, None) for seed, o in zip(seeds, ours, strict=True)]
    return rows + _peer_rows(weights, seeds, steps, iterations, peer_updates, ceiling, runs)


def _train_ours(weights: np.ndarray, seed: int, steps: int, iterations: int, runs: Path | None) -> Outcome:
    """One MA-SFOLS run with the deep preset at γ 0.99, its learner shared by the agents (in ``runs`` where given); its
    team's EU over the final Π."""
    learner = {key: value for key, value in MLP_LEARNER.items() if key != "policy"} | {"gamma": GAMMA}

    def build(run_dir: Path | None) -> MASFOLS:
        return MASFOLS(
            make_agents_env(), policy=MLP_LEARNER["policy"], steps_per_iteration=steps, learner_kwargs=learner,
            value_episodes=5, **MLP_RUN, test_weights=weights, eval_episodes=1, seed=seed, run_dir=run_dir, verbose=1,
            sharing="shared",
        )  # fmt: skip

    masfols = learned(build, make_agents_env, runs, f"item-gathering-s{seed}", iterations)
    by_iteration = tuple(_team_expected_utility(entry["test"]) for entry in masfols.history)
    last = masfols.history[-1]
    return Outcome(
        by_iteration[-1], None, last["wall_time"], int(last["timesteps"]), len(masfols.policy_set),
        len(masfols.history), by_iteration,
    )  # fmt: skip


def _team_expected_utility(test: list[dict[str, Any]]) -> float:
    """The mean over an evaluation's test weights of ``w ·`` the agents' discounted returns summed."""
    return float(np.mean([
        np.dot(entry["weights"], np.sum([agent["discounted"] for agent in entry["agents"].values()], axis=0))
        for entry in test
    ]))  # fmt: skip


# --- MOMAland's GPI-LS (optional: pip install morl-baselines) --------------------------------------------------------
def _peer_rows(
    weights: np.ndarray,
    seeds: list[int],
    steps: int,
    iterations: int,
    updates: int | None,
    ceiling: str,
    runs: Path | None = None,
) -> list[Row]:
    """The peer's summary row and a row per seed (its checkpoints in ``runs``, ``item-gathering-GPILS-s<seed>.pkl``,
    where given); one row where morl-baselines is missing."""
    settings = PEER_SETTINGS | ({} if updates is None else {"gradient_updates": updates})
    case = (
        f"{ENV_ID}, MOMAland's GPI-LS (morl-baselines, centralised), {iterations} × {steps:,} steps, "
        f"{settings['gradient_updates']} updates per step"
    )
    try:
        from momaland.utils.parallel_wrappers import CentraliseAgent
        from morl_baselines.multi_policy.gpi_pd.gpi_pd import GPILS
    except ImportError:
        return [Row(NAME, case, MORL_MISSING)]

    def centralised() -> Any:
        return CentraliseAgent(make_env(), action_mapping=True)

    outcomes = [_train_peer(GPILS, centralised, settings, weights, seed, steps, iterations, runs) for seed in seeds]
    rows = [summary_row(NAME, case, outcomes, None, ceiling, seeds)]
    return rows + [
        seed_row(NAME, f"{ENV_ID} GPI-LS seed {seed}", o, None) for seed, o in zip(seeds, outcomes, strict=True)
    ]


def _train_peer(
    algorithm: Any, make: Callable[[], Any], settings: dict[str, Any], weights: np.ndarray, seed: int, steps: int,
    iterations: int, runs: Path | None,
) -> Outcome:  # fmt: skip
    """One seeded run of the peer (its global generators seeded, as MOMAland's script does not), scored as ours; with
    ``runs``, continued from its checkpoint there (:func:`~benchmarks.gpi_ls_runs.train_gpi_ls`)."""
    seed_peer_generators(seed)

    def agent() -> Any:
        made = algorithm(seeded(make(), seed), seed=seed, log=False, device=peer_device(), **settings)
        drop_sampled_indices(made)
        return made

    def eval_env() -> Any:
        env = make()
        env.reset(seed=derive_seed(seed, "peer eval"))
        return env

    checkpoint = None if runs is None else Path(runs) / f"item-gathering-GPILS-s{seed}.pkl"
    stored = settings | {"seed": seed, "steps_per_iteration": steps}
    run = train_gpi_ls(agent, eval_env, stored, steps, iterations, checkpoint)
    scoring = make()  # one env: each episode's seeded reset decides it
    eu = float(np.mean([_centralised_return(scoring, run.agent.eval, w, derive_seed(seed, "eval", i)) @ w
                        for i, w in enumerate(weights)]))  # fmt: skip
    return Outcome(eu, None, run.wall_time, int(run.agent.global_step), len(run.agent.weight_support), iterations)


def _centralised_return(env: Any, act: Callable[[Any, np.ndarray], int], w: np.ndarray, seed: int) -> np.ndarray:
    """The discounted team return of one greedy episode of a centralised agent acting for ``w``."""
    obs, _ = env.reset(seed=seed)
    total, discount, done = np.zeros(len(ITEMS)), 1.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(act(obs, w))
        total += discount * np.asarray(reward, dtype=np.float64)
        discount *= GAMMA
        done = terminated or truncated
    return total

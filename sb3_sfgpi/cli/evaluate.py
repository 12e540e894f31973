"""``sb3-sfgpi evaluate RUN --w ...`` (or ``--random-weights N``): GPI over a run's policy set acting for any
weights."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sb3_sfgpi.cli.compare import episode_metrics
from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import CLI_SETTINGS, MAX_COUNT, WEIGHT_HELP, DomainPreset, load_domain
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.weights import random_weights, validate_weights
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import load_policy_set
from sb3_sfgpi.run_settings import GAMMA

if TYPE_CHECKING:
    from sb3_sfgpi.gpi import GPIPolicy


def add_parser(sub: Any) -> None:
    """The ``evaluate`` sub-command's arguments."""
    evaluate = sub.add_parser("evaluate", help="run GPI from a saved run for preference weights w")
    evaluate.add_argument("run_dir", type=Path)
    which_weights = evaluate.add_mutually_exclusive_group(required=True)
    which_weights.add_argument("--w", type=float, nargs="+", help=f"preference weights, {WEIGHT_HELP}")
    which_weights.add_argument(
        "--random-weights",
        type=int,
        metavar="N",
        help="N weights drawn from Dirichlet(1) with --seed: print GPI's mean w·return over them",
    )
    evaluate.add_argument("--episodes", type=int, default=1)
    evaluate.add_argument("--seed", type=int, default=0)
    evaluate.add_argument("--device", default="cpu", help="where the policy set acts: cpu, auto, cuda, cuda:N")
    evaluate.add_argument("--gpi-set", choices=["all", "ccs"], help="GPI over all of Π or its CCS (default: the run's)")
    evaluate.add_argument(
        "--members",
        action="store_true",
        help="with --w: also run each policy of the GPI set alone (does GPI beat its best member?)",
    )


def run(args: argparse.Namespace) -> int:
    """Run GPI for ``--w`` and print every agent's vector return, or its mean w·return over random weights."""
    run_dir = RunDirectory(args.run_dir)
    config = run_dir.read_config(required=CLI_SETTINGS)
    which = args.gpi_set or config.get("gpi_set", "all")
    state = run_dir.read_checkpoint() if run_dir.has_checkpoint() else {"n_policies": None, "iteration": None}
    if args.random_weights is not None and not 1 <= args.random_weights <= MAX_COUNT:
        raise UsageError(f"--random-weights must be in [1, {MAX_COUNT}], got {args.random_weights}")
    if args.members and args.w is None:
        raise UsageError("--members needs --w (each policy is run alone for those weights)")
    if args.episodes < 1:
        raise UsageError(f"--episodes must be positive, got {args.episodes}")
    if args.seed < 0:
        raise UsageError(f"--seed must be 0 or more (the environment's reset seed), got {args.seed}")
    policy_set = load_policy_set(run_dir, state["n_policies"], args.device, state["iteration"])  # Π at the checkpoint
    if which == "ccs":
        policy_set = policy_set.ccs_policies()
    w = None if args.w is None else validate_weights(args.w, policy_set.reward_dim, "--w")
    preset = load_domain(config["domain"])
    env = preset.build_env(preset.run_file_env(config["env_kwargs"], run_dir))
    gamma = config["learner_kwargs"].get("gamma", GAMMA)
    print(f"GPI over {len(policy_set)} policies ({which}), {args.episodes} episode(s) per weight")
    try:
        if w is None:
            _print_random_weights(env, policy_set, args.random_weights, args.episodes, gamma, args.seed)
        else:
            _print_one_weight(env, policy_set, w, preset, config, args.episodes, gamma, args.seed)
            if args.members:
                _print_members(env, policy_set, w, args.episodes, gamma, args.seed)
    finally:
        env.close()
    return 0


def _print_one_weight(
    env: Any,
    policy_set: GPIPolicy,
    w: np.ndarray,
    preset: DomainPreset,
    config: dict,
    episodes: int,
    gamma: float,
    seed: int,
) -> None:
    """Every agent's vector return acting by GPI for ``w``, and the preset's episode metrics."""
    result = run_episodes(env, policy_set.joint_policy(w), episodes, gamma, seed=seed)
    print(f"  w={np.round(w, 4).tolist()}")
    names = preset.objective_names(config["env_kwargs"])
    if names and len(names) == len(w):
        print(f"  objectives: {', '.join(names)}")
    for agent in result.discounted:
        disc, total = result.mean_discounted(agent), result.mean_undiscounted(agent)
        print(
            f"  {agent}: return {np.round(total, 4).tolist()}  discounted {np.round(disc, 4).tolist()}  "
            f"w·return (discounted, γ={gamma}) {float(w @ disc):.4f}"
        )
    metrics = episode_metrics(result, preset.episode_metrics)
    for key, label in preset.episode_metrics:
        if key in metrics:
            print(f"  {label}: {metrics[key]['mean']:.2f} ± {metrics[key]['std']:.2f} over episodes")


def _mean_scalarized(env: Any, policy_set: GPIPolicy, w: np.ndarray, episodes: int, gamma: float, seed: int) -> float:
    """w · discounted return of GPI over ``policy_set`` for ``w``, mean over agents and episodes."""
    result = run_episodes(env, policy_set.joint_policy(w), episodes, gamma, seed=seed)
    return float(w @ result.mean_discounted_over())


def _print_members(env: Any, policy_set: GPIPolicy, w: np.ndarray, episodes: int, gamma: float, seed: int) -> None:
    """GPI's w·return against each policy of its set acting alone for ``w`` (every agent follows it), same episodes."""
    gpi = _mean_scalarized(env, policy_set, w, episodes, gamma, seed)
    print(f"  GPI: w·return (discounted, mean over agents) {gpi:.4f}")
    for index, info in enumerate(policy_set.infos):
        alone = _mean_scalarized(env, policy_set.subset([index]), w, episodes, gamma, seed)
        trained = np.round(info.weights, 2).tolist()
        print(f"  alone: {info.agent}'s policy of iteration {info.iteration} (trained for {trained}) {alone:.4f}")


def _print_random_weights(env: Any, policy_set: GPIPolicy, n: int, episodes: int, gamma: float, seed: int) -> None:
    """GPI's w · discounted return (mean over agents) for ``n`` Dirichlet(1) weights of ``seed``: mean ± std."""
    values = [
        _mean_scalarized(env, policy_set, w, episodes, gamma, seed)
        for w in random_weights(policy_set.reward_dim, n, rng=seed)
    ]
    print(
        f"  {n} Dirichlet(1) weights (seed {seed}): w·return (discounted, γ={gamma}, mean over agents) "
        f"{np.mean(values):.4f} ± {np.std(values):.4f} (std over weights)"
    )

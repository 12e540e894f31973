"""``sb3-sfgpi evaluate RUN --w ...``: GPI over a run's policy set acting for any weights."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi.cli.compare import episode_metrics
from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import CLI_SETTINGS, WEIGHT_HELP, load_domain
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.run_directory import RunDirectory


def add_parser(sub: Any) -> None:
    """The ``evaluate`` sub-command's arguments."""
    evaluate = sub.add_parser("evaluate", help="run GPI from a saved run for preference weights w")
    evaluate.add_argument("run_dir", type=Path)
    evaluate.add_argument("--w", type=float, nargs="+", required=True, help=f"preference weights, {WEIGHT_HELP}")
    evaluate.add_argument("--episodes", type=int, default=1)
    evaluate.add_argument("--seed", type=int, default=0)
    evaluate.add_argument("--device", default="cpu", help="where the policy set acts: cpu, auto, cuda, cuda:N")
    evaluate.add_argument("--gpi-set", choices=["all", "ccs"], help="GPI over all of Π or its CCS (default: the run's)")


def run(args: argparse.Namespace) -> int:
    """Run GPI for ``--w`` and print every agent's vector return."""
    run_dir = RunDirectory(args.run_dir)
    config = run_dir.read_config(required=CLI_SETTINGS)
    which = args.gpi_set or config.get("gpi_set", "all")
    state = run_dir.read_checkpoint() if run_dir.has_checkpoint() else {"n_policies": None, "iteration": None}
    policy_set = run_dir.load_policy_set(state["n_policies"], args.device, state["iteration"])  # Π at the checkpoint
    if which == "ccs":
        policy_set = policy_set.ccs_policies()
    w = validate_weights(args.w, policy_set.reward_dim, "--w")
    if args.episodes < 1:
        raise UsageError(f"--episodes must be positive, got {args.episodes}")
    if args.seed < 0:
        raise UsageError(f"--seed must be 0 or more (the environment's reset seed), got {args.seed}")
    preset = load_domain(config["domain"])
    env = preset.build_env(config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)
    try:
        result = run_episodes(env, policy_set.joint_policy(w), args.episodes, gamma, seed=args.seed)
    finally:
        env.close()
    print(f"GPI over {len(policy_set)} policies ({which}), w={np.round(w, 4).tolist()}, {args.episodes} episode(s)")
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
    return 0

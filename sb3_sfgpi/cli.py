"""Command line: ``sb3-sfgpi train | evaluate | plot``.

Domains (``four-room``, ``traffic``, ...) are found through the entry-point group ``sb3_sfgpi.domains``:
each entry is a callable returning a :class:`dict` with ``make_env`` (a callable building the PettingZoo
ParallelEnv from ``env_kwargs``), ``env_kwargs``, ``learner_kwargs`` (SFDQN arguments) and the defaults of
``steps_per_iteration``, ``iterations``, ``n_test_weights``, ``value_episodes`` and ``eval_episodes``. This
keeps the algorithm package free of any import of the environments.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi.common.serialization import atomic_write_json, read_json

ENTRY_POINT_GROUP = "sb3_sfgpi.domains"
RUN_FILE = "run.json"


class UsageError(Exception):
    """A user mistake: reported as one line on stderr with exit code 2."""


def available_domains() -> dict[str, Any]:
    """Domain name -> entry point, from the ``sb3_sfgpi.domains`` entry-point group."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load_domain(name: str) -> dict[str, Any]:
    """
    The preset of a domain.

    :raises UsageError: unknown domain
    """
    domains = available_domains()
    if name not in domains:
        raise UsageError(f"unknown domain {name!r}; available: {', '.join(sorted(domains)) or 'none installed'}")
    return domains[name].load()()


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="sb3-sfgpi", description="MA-SFOLS + GPI with Stable-Baselines3")
    sub = parser.add_subparsers(dest="command", required=True)

    train = sub.add_parser("train", help="build a policy set with MA-SFOLS (or random weights)")
    train.add_argument("domain", help="four-room, traffic, or another installed domain")
    train.add_argument("--algo", choices=["ma-sfols", "random"], default="ma-sfols")
    train.add_argument("--iterations", type=int, help="maximum number of iterations (default: the domain's)")
    train.add_argument("--steps-per-iteration", type=int, help="joint env steps per iteration (default: the domain's)")
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--out", type=Path, help="run directory (default: runs/<domain>-<algo>-s<seed>)")
    train.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    train.add_argument("--transfer", action="store_true", help="start new learners from the best policy in the set")
    train.add_argument("--no-progress", action="store_true", help="no progress bars")

    evaluate = sub.add_parser("evaluate", help="run GPI from a saved run for preference weights w")
    evaluate.add_argument("run_dir", type=Path)
    evaluate.add_argument("--w", type=float, nargs="+", required=True, help="preference weights, one per objective")
    evaluate.add_argument("--episodes", type=int, default=1)
    evaluate.add_argument("--seed", type=int, default=0)

    plot = sub.add_parser("plot", help="draw return over iterations, mean ± std over seeds, one line per algorithm")
    plot.add_argument("run_dirs", type=Path, nargs="+")
    plot.add_argument("-o", "--output", type=Path, required=True)
    plot.add_argument(
        "--metric",
        default="mean_return",
        choices=["mean_return", "mean_return_undiscounted", "expected_utility", "ccs_size", "n_policies"],
    )
    plot.add_argument("--title", default=None)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-sfgpi`` console script."""
    args = _parse_args(argv)
    try:
        if args.command == "train":
            return _train(args)
        if args.command == "evaluate":
            return _evaluate(args)
        return _plot(args)
    except (UsageError, ValueError) as error:
        print(f"sb3-sfgpi {args.command}: error: {error}", file=sys.stderr)
        return 2


def _train(args: argparse.Namespace) -> int:
    from stable_baselines3.common.logger import configure

    from sb3_sfgpi.callbacks import CHECKPOINT, OLSCallback
    from sb3_sfgpi.common.weights import random_weights
    from sb3_sfgpi.multiagent import MultiAgentRunner, default_learner_factory

    domain = load_domain(args.domain)
    out: Path = args.out or Path("runs") / f"{args.domain}-{args.algo}-s{args.seed}"
    config = {
        "domain": args.domain,
        "algorithm": args.algo,
        "seed": args.seed,
        "iterations": args.iterations or domain["iterations"],
        "steps_per_iteration": args.steps_per_iteration or domain["steps_per_iteration"],
        "transfer": args.transfer,
        "env_kwargs": domain["env_kwargs"],
        "learner_kwargs": domain["learner_kwargs"],
        "n_test_weights": domain["n_test_weights"],
        "value_episodes": domain["value_episodes"],
        "eval_episodes": domain["eval_episodes"],
    }
    for key in ("iterations", "steps_per_iteration"):
        if config[key] < 1:
            raise UsageError(f"--{key.replace('_', '-')} must be positive, got {config[key]}")
    if args.resume:
        if not (out / RUN_FILE).exists():
            raise UsageError(f"--resume: {out} is not a run directory (no {RUN_FILE})")
        saved = read_json(out / RUN_FILE, "run description")
        for key in ("domain", "algorithm", "seed"):
            if saved[key] != config[key]:
                raise UsageError(f"--resume: {out} is a run with {key}={saved[key]!r}, not {config[key]!r}")
        config = {**saved, "iterations": config["iterations"]}
    elif (out / CHECKPOINT).exists():
        raise UsageError(f"{out} already holds a run: pass --resume to continue it or choose another --out")
    atomic_write_json(out / RUN_FILE, config)

    env = domain["make_env"](**config["env_kwargs"])
    learner_kwargs = dict(config["learner_kwargs"])
    runner = MultiAgentRunner(
        env,
        default_learner_factory(**learner_kwargs),
        seed=config["seed"],
        gamma=learner_kwargs.get("gamma", 0.99),
        tensorboard_log=str(out / "tensorboard"),
    )
    runner.set_logger(configure(str(out / "logs"), ["csv", "tensorboard"]))
    reward_dim = runner.reward_dim
    callback = OLSCallback(
        steps_per_iteration=config["steps_per_iteration"],
        test_weights=random_weights(reward_dim, config["n_test_weights"], rng=0),
        algorithm=config["algorithm"],
        max_iterations=config["iterations"],
        value_episodes=config["value_episodes"],
        eval_episodes=config["eval_episodes"],
        transfer=config["transfer"],
        run_dir=out,
        resume=args.resume,
        progress_bar=not args.no_progress,
        verbose=1,
    )
    try:
        runner.learn(config["iterations"] * config["steps_per_iteration"], callback, progress_bar=not args.no_progress)
    finally:
        env.close()
    last = callback.history[-1] if callback.history else None
    if last is None:
        print(f"{out}: nothing to do")
    else:
        print(
            f"{out}: {last['iteration'] + 1} iterations, |Π|={last['n_policies']}, CCS={last['ccs_size']}, "
            f"mean w·return={last['mean_return']:.4f}, {last['wall_time']:.1f}s"
            + (" (OLS ended: the set is a CCS)" if callback.finished and not callback._reached_max_iterations() else "")
        )
    return 0


def _read_run(run_dir: Path) -> dict[str, Any]:
    if not (run_dir / RUN_FILE).exists():
        raise UsageError(f"{run_dir} is not a run directory (no {RUN_FILE})")
    return read_json(run_dir / RUN_FILE, "run description")


def _evaluate(args: argparse.Namespace) -> int:
    from sb3_sfgpi.common.evaluation import run_episodes
    from sb3_sfgpi.common.weights import validate_weights
    from sb3_sfgpi.gpi import GPIPolicy

    config = _read_run(args.run_dir)
    policy_set = GPIPolicy.load(args.run_dir / "policy_set")
    w = validate_weights(args.w, policy_set.reward_dim, "--w")
    if args.episodes < 1:
        raise UsageError(f"--episodes must be positive, got {args.episodes}")
    env = load_domain(config["domain"])["make_env"](**config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)

    def act(observations: dict[str, Any]) -> dict[str, int]:
        agents = list(observations)
        actions, _ = policy_set.predict(np.stack([observations[a] for a in agents]), w)
        return dict(zip(agents, actions.tolist()))

    try:
        result = run_episodes(env, act, args.episodes, gamma, seed=args.seed)
    finally:
        env.close()
    print(f"GPI over {len(policy_set)} policies, w={np.round(w, 4).tolist()}, {args.episodes} episode(s)")
    for agent in result.discounted:
        disc, total = result.mean_discounted(agent), result.mean_undiscounted(agent)
        print(
            f"  {agent}: return {np.round(total, 4).tolist()}  discounted {np.round(disc, 4).tolist()}  "
            f"w·return {float(w @ total):.4f}"
        )
    return 0


def align_runs(runs: list[dict[int, float]]) -> np.ndarray:
    """
    One row per run over the union of their iterations; a run that stopped early (OLS ended: its set is
    complete) keeps its last value.

    :param runs: per run, iteration -> value
    :return: shape ``(n_runs, n_iterations)``
    """
    iterations = sorted(set().union(*runs))
    rows = []
    for run in runs:
        last, row = np.nan, []
        for i in iterations:
            last = run.get(i, last)
            row.append(last)
        rows.append(row)
    return np.array(rows)


def _plot(args: argparse.Namespace) -> int:
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves: dict[str, list[dict[int, float]]] = {}
    for run_dir in args.run_dirs:
        config = _read_run(run_dir)
        if not (run_dir / "evaluation.csv").exists():
            raise UsageError(f"{run_dir} has no evaluation.csv yet")
        with open(run_dir / "evaluation.csv") as handle:
            rows = list(csv.DictReader(handle))
        curves.setdefault(config["algorithm"], []).append(
            {int(row["iteration"]) + 1: float(row[args.metric]) for row in rows if row[args.metric] != ""}
        )
    labels = {"ma-sfols": "MA-SFOLS + GPI", "random": "Random + GPI"}
    fig, ax = plt.subplots(figsize=(6, 4))
    for algorithm, runs in sorted(curves.items()):
        values = align_runs(runs)
        iterations = sorted(set().union(*runs))
        mean, std = values.mean(axis=0), values.std(axis=0)
        ax.plot(iterations, mean, marker="o", label=f"{labels.get(algorithm, algorithm)} ({len(runs)} seeds)")
        ax.fill_between(iterations, mean - std, mean + std, alpha=0.2)
    ax.set_xlabel("iteration")
    ax.set_ylabel(args.metric.replace("_", " "))
    ax.set_title(args.title or "GPI over the policy set, mean over test weights and agents")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=120)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

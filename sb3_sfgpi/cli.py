"""Command line: ``sb3-sfgpi train | evaluate | compare | plot``.

Domains (``four-room``, ``traffic``, ...) are found through the entry-point group ``sb3_sfgpi.domains``:
each entry is a callable returning a :class:`dict` with ``make_env`` (a picklable callable building the
PettingZoo ParallelEnv from ``env_kwargs``), ``env_kwargs``, ``learner_kwargs`` (SFDQN arguments) and the
defaults of ``steps_per_iteration``, ``iterations``, ``n_test_weights``, ``value_episodes`` and
``eval_episodes``. Optional entries: ``eval_workers`` (default of ``--eval-workers``), and for ``compare``
and its plots ``objectives`` (names), ``baselines`` (name -> env keyword arguments of a controller that
needs no actions), ``episode_metrics`` and ``step_metrics`` (``[info key, label]`` pairs, one per
objective: the ``"episode"`` entry of the last info, and the per-step info summed over agents),
``compare_weights`` and ``fixed_weights``. This keeps the algorithm package free of any import of the
environments.

``compare`` writes a comparison file (JSON)::

    {"format": "sb3-sfgpi/compare", "version": 1, "domain", "run_dir", "env_kwargs", "gamma", "episodes",
     "seed", "gpi_set", "objectives", "episode_metrics", "step_metrics",
     "rows": [{"method": "gpi" | "fixed" | "baseline", "label", "run_dir", "weights" (null for baselines),
               "return_discounted", "return_undiscounted" (mean over agents and episodes),
               "scalarized_discounted" (w · return_discounted, null for baselines),
               "agents": {agent: {"discounted", "undiscounted"}},
               "episode_metrics": {key: {"mean", "std"}} (over episodes),
               "traces": {"time": [...], key: {"mean": [...], "std": [...]}} (per step, summed over agents)}]}
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi.common.serialization import atomic_write_json, read_json
from sb3_sfgpi.plots import align_runs

ENTRY_POINT_GROUP = "sb3_sfgpi.domains"
RUN_FILE = "run.json"
COMPARE_FORMAT = "sb3-sfgpi/compare"
PLOT_KINDS = ("returns", "steps", "versus", "tradeoff")

__all__ = ["align_runs", "available_domains", "load_domain", "main"]


class UsageError(Exception):
    """A user mistake: reported as one line on stderr with exit code 2."""


class TrainingStopped(Exception):
    """Training stopped by an error (e.g. the simulator died): reported as one line with exit code 1."""


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
    train.add_argument(
        "--algo",
        choices=["ma-sfols", "random", "fixed"],
        default="ma-sfols",
        help="ma-sfols: OLS corner weights; random: Dirichlet(1) weights; fixed: every agent learns for --w from "
        "scratch (a priori scalarisation), in one iteration of iterations x steps-per-iteration steps",
    )
    train.add_argument("--w", type=float, nargs="+", help="the preference weights of --algo fixed")
    train.add_argument(
        "--budget-from",
        type=Path,
        metavar="RUN",
        help="--algo fixed: train as many steps per agent as the run in RUN did (e.g. an MA-SFOLS run that OLS "
        "ended before its iteration cap)",
    )
    train.add_argument("--iterations", type=int, help="maximum number of iterations (default: the domain's)")
    train.add_argument("--steps-per-iteration", type=int, help="joint env steps per iteration (default: the domain's)")
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--out", type=Path, help="run directory (default: runs/<domain>-<algo>-s<seed>)")
    train.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    train.add_argument("--transfer", action="store_true", help="start new learners from the best policy in the set")
    train.add_argument("--no-progress", action="store_true", help="no progress bars")
    train.add_argument(
        "--env",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override an env argument of the domain (VALUE is read as JSON, else as a string), e.g. num_seconds=200",
    )
    train.add_argument("--learner", metavar="KEY=VALUE", action="append", default=[], help="override an SFDQN argument")
    train.add_argument("--n-test-weights", type=int, help="test weights of the GPI evaluation (default: the domain's)")
    train.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="torch threads of the training process (default 1: the networks are small, and more threads only "
        "contend with the simulator and the evaluation workers)",
    )
    train.add_argument(
        "--eval-workers",
        type=int,
        help="evaluate GPI in this many worker processes, each with its own env (0: in the training process; "
        "default: the domain's)",
    )

    evaluate = sub.add_parser("evaluate", help="run GPI from a saved run for preference weights w")
    evaluate.add_argument("run_dir", type=Path)
    evaluate.add_argument("--w", type=float, nargs="+", required=True, help="preference weights, one per objective")
    evaluate.add_argument("--episodes", type=int, default=1)
    evaluate.add_argument("--seed", type=int, default=0)
    evaluate.add_argument("--gpi-set", choices=["all", "ccs"], help="GPI over all of Π or its CCS (default: the run's)")

    compare = sub.add_parser(
        "compare",
        help="evaluate GPI at several weights, fixed-weight learners and the domain's baselines on the same episodes",
    )
    compare.add_argument("run_dir", type=Path, help="the MA-SFOLS (or random) run whose policy set GPI uses")
    compare.add_argument("--fixed", type=Path, nargs="+", default=[], help="run directories of `train --algo fixed`")
    compare.add_argument(
        "--w",
        type=float,
        nargs="+",
        action="append",
        help="weights GPI is evaluated at (repeat the option; default: the domain's; the --fixed runs' are added)",
    )
    compare.add_argument("--no-baselines", action="store_true", help="skip the domain's baselines")
    compare.add_argument("--gpi-set", choices=["all", "ccs"], help="GPI over all of Π or its CCS (default: the run's)")
    compare.add_argument("--episodes", type=int, default=3, help="episodes per method (seeds seed, seed+1, ...)")
    compare.add_argument("--seed", type=int, default=1000)
    compare.add_argument("--workers", type=int, help="worker processes (0: in this process; default: the domain's)")
    compare.add_argument("-o", "--output", type=Path, help="comparison file (default: RUN_DIR/compare.json)")

    plot = sub.add_parser(
        "plot",
        help="returns: GPI return over iterations, mean ± std over seeds (run directories); steps, versus, "
        "tradeoff: from a comparison file",
    )
    plot.add_argument("run_dirs", type=Path, nargs="+", metavar="INPUT", help="run directories, or a comparison file")
    plot.add_argument(
        "-o", "--output", type=Path, required=True, help="PNG file (returns, tradeoff) or directory (steps, versus)"
    )
    plot.add_argument("--kind", choices=PLOT_KINDS, default="returns")
    plot.add_argument(
        "--smooth", type=int, default=10, help="steps, versus: moving average over this many steps (1: raw curves)"
    )
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
        if args.command == "compare":
            return _compare(args)
        return _plot(args)
    except (UsageError, ValueError) as error:
        print(f"sb3-sfgpi {args.command}: error: {error}", file=sys.stderr)
        return 2
    except TrainingStopped as error:
        print(f"sb3-sfgpi {args.command}: error: {error}", file=sys.stderr)
        return 1


def _train(args: argparse.Namespace) -> int:
    from stable_baselines3.common.logger import configure

    from sb3_sfgpi.callbacks import CHECKPOINT, OLSCallback
    from sb3_sfgpi.common.weights import random_weights
    from sb3_sfgpi.multiagent import MultiAgentRunner, default_learner_factory

    if args.torch_threads < 1:
        raise UsageError(f"--torch-threads must be positive, got {args.torch_threads}")
    domain = load_domain(args.domain)
    iterations = args.iterations or domain["iterations"]
    steps_per_iteration = args.steps_per_iteration or domain["steps_per_iteration"]
    eval_workers = domain.get("eval_workers", 0) if args.eval_workers is None else args.eval_workers
    n_test_weights = domain["n_test_weights"] if args.n_test_weights is None else args.n_test_weights
    for name, value in (
        ("--iterations", iterations),
        ("--steps-per-iteration", steps_per_iteration),
        ("--n-test-weights", n_test_weights),
    ):
        if value < 1:
            raise UsageError(f"{name} must be positive, got {value}")
    if eval_workers < 0:
        raise UsageError(f"--eval-workers must be 0 or more, got {eval_workers}")
    fixed_weights = None
    if args.algo == "fixed":
        if args.w is None:
            raise UsageError("--algo fixed needs the preference weights --w")
        fixed_weights = _check_weights(args.w, "--w")
    elif args.w is not None or args.budget_from is not None:
        raise UsageError("--w and --budget-from are only for --algo fixed")
    default_name = f"{args.domain}-{args.algo}" + (f"-w{_tag(fixed_weights)}" if fixed_weights else "")
    out: Path = args.out or Path("runs") / f"{default_name}-s{args.seed}"
    config = {
        "domain": args.domain,
        "algorithm": args.algo,
        "seed": args.seed,
        "iterations": iterations,
        "steps_per_iteration": steps_per_iteration,
        "transfer": args.transfer,
        "env_kwargs": {**domain["env_kwargs"], **_key_values(args.env, "--env")},
        "learner_kwargs": {**domain["learner_kwargs"], **_key_values(args.learner, "--learner")},
        "n_test_weights": n_test_weights,
        "value_episodes": domain["value_episodes"],
        "value_mode": domain.get("value_mode", "joint"),
        "gpi_set": domain.get("gpi_set", "all"),
        "eval_episodes": domain["eval_episodes"],
    }
    if fixed_weights is not None:
        # The same number of steps per agent as an MA-SFOLS run of `iterations` iterations, in one iteration.
        budget: dict[str, Any] = {"iterations": iterations, "steps_per_iteration": steps_per_iteration}
        steps = iterations * steps_per_iteration
        if args.budget_from is not None:
            checkpoint = args.budget_from / CHECKPOINT
            if not checkpoint.exists():
                raise UsageError(f"--budget-from: {args.budget_from} has no checkpoint")
            steps = int(read_json(checkpoint, "checkpoint")["timesteps"])
            budget = {"from": str(args.budget_from), "timesteps": steps}
        config.update(iterations=1, steps_per_iteration=steps, fixed_weights=fixed_weights, budget=budget)
    if args.resume:
        if not (out / RUN_FILE).exists():
            raise UsageError(f"--resume: {out} is not a run directory (no {RUN_FILE})")
        saved = read_json(out / RUN_FILE, "run description")
        for option, key in (("--env", "env_kwargs"), ("--learner", "learner_kwargs")):
            if getattr(args, option[2:]) and config[key] != saved[key]:
                raise UsageError(f"--resume: {option} would change the run's {key} ({saved[key]})")
        for key in ("domain", "algorithm", "seed", "fixed_weights"):
            if saved.get(key) != config.get(key):
                raise UsageError(f"--resume: {out} is a run with {key}={saved.get(key)!r}, not {config.get(key)!r}")
        config = {**saved, "iterations": config["iterations"]}
    elif (out / CHECKPOINT).exists():
        raise UsageError(f"{out} already holds a run: pass --resume to continue it or choose another --out")
    config["eval_workers"] = eval_workers  # does not change the results: may differ on resume
    atomic_write_json(out / RUN_FILE, config)

    import torch as th

    th.set_num_threads(args.torch_threads)
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
    fixed = config.get("fixed_weights")
    if fixed is not None and len(fixed) != reward_dim:
        raise UsageError(f"--w must have length {reward_dim} (one weight per objective), got {len(fixed)}")
    callback = OLSCallback(
        steps_per_iteration=config["steps_per_iteration"],
        # fixed-weight learners are evaluated at their own weight, each agent with its own policy
        test_weights=np.array([fixed]) if fixed else random_weights(reward_dim, config["n_test_weights"], rng=0),
        algorithm=config["algorithm"],
        max_iterations=config["iterations"],
        value_episodes=config["value_episodes"],
        value_mode=config.get("value_mode", "joint"),
        eval_episodes=config["eval_episodes"],
        transfer=config["transfer"],
        run_dir=out,
        resume=args.resume,
        progress_bar=not args.no_progress,
        verbose=1,
        fixed_weights=fixed,
        eval_policies="own" if fixed else "shared",
        gpi_set=config.get("gpi_set", "all"),
        eval_workers=eval_workers,
        eval_env_fn=domain["make_env"] if eval_workers else None,
        eval_env_kwargs=config["env_kwargs"],
    )
    try:
        runner.learn(config["iterations"] * config["steps_per_iteration"], callback, progress_bar=not args.no_progress)
    except (RuntimeError, KeyboardInterrupt) as error:
        done = read_json(out / CHECKPOINT, "checkpoint")["iteration"] if (out / CHECKPOINT).exists() else 0
        reason = "interrupted" if isinstance(error, KeyboardInterrupt) else f"{type(error).__name__}: {error}"
        reason = " ".join(reason.split())  # one line
        raise TrainingStopped(
            f"training stopped in iteration {callback.iteration} ({reason}). The checkpoint of the last finished "
            f"iteration ({done} done) in {out} is intact: continue with "
            f"`sb3-sfgpi train {args.domain} --algo {args.algo} --seed {args.seed} --out {out} --resume`"
            + (" --w " + " ".join(f"{x:g}" for x in fixed) if fixed else "")
        ) from error
    finally:
        callback.close()
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


def _key_values(items: Sequence[str], option: str) -> dict[str, Any]:
    """``KEY=VALUE`` strings as a dict; a VALUE that is valid JSON is read as JSON, else kept as a string."""
    import json

    parsed = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"{option} expects KEY=VALUE, got {item!r}")
        try:
            parsed[key] = json.loads(value)
        except json.JSONDecodeError:
            parsed[key] = value
    return parsed


def _check_weights(values: Sequence[float], name: str) -> list[float]:
    """Weights of unknown length (checked against the domain later): non-negative, finite, summing to 1."""
    from sb3_sfgpi.common.weights import validate_weights

    return validate_weights(values, len(values), name).tolist()


def _tag(weights: Sequence[float]) -> str:
    return "-".join(f"{x:g}" for x in np.round(weights, 4))


def _read_run(run_dir: Path) -> dict[str, Any]:
    if not (run_dir / RUN_FILE).exists():
        raise UsageError(f"{run_dir} is not a run directory (no {RUN_FILE})")
    return read_json(run_dir / RUN_FILE, "run description")


def _evaluate(args: argparse.Namespace) -> int:
    from sb3_sfgpi.common.evaluation import ccs_subset, gpi_joint_policy, run_episodes
    from sb3_sfgpi.common.weights import validate_weights
    from sb3_sfgpi.gpi import GPIPolicy

    config = _read_run(args.run_dir)
    policy_set = GPIPolicy.load(args.run_dir / "policy_set")
    if (args.gpi_set or config.get("gpi_set", "all")) == "ccs":
        policy_set = ccs_subset(policy_set)
    w = validate_weights(args.w, policy_set.reward_dim, "--w")
    if args.episodes < 1:
        raise UsageError(f"--episodes must be positive, got {args.episodes}")
    env = load_domain(config["domain"])["make_env"](**config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)

    try:
        result = run_episodes(env, gpi_joint_policy(policy_set, w), args.episodes, gamma, seed=args.seed)
    finally:
        env.close()
    which = args.gpi_set or config.get("gpi_set", "all")
    print(f"GPI over {len(policy_set)} policies ({which}), w={np.round(w, 4).tolist()}, {args.episodes} episode(s)")
    for agent in result.discounted:
        disc, total = result.mean_discounted(agent), result.mean_undiscounted(agent)
        print(
            f"  {agent}: return {np.round(total, 4).tolist()}  discounted {np.round(disc, 4).tolist()}  "
            f"w·return {float(w @ total):.4f}"
        )
    return 0


def _summarize(job_result: Any, weights: Sequence[float] | None, compare: dict[str, Any]) -> dict[str, Any]:
    """One row of a comparison file from an :class:`~sb3_sfgpi.common.evaluation.EpisodeReturns`."""
    agents = list(job_result.discounted)
    disc = np.mean([job_result.mean_discounted(a) for a in agents], axis=0)
    undisc = np.mean([job_result.mean_undiscounted(a) for a in agents], axis=0)
    episode_metrics = {}
    for key, _ in compare["episode_metrics"]:
        values = []
        for infos in job_result.final_infos:
            episode = next((info["episode"] for info in infos.values() if "episode" in info), None)
            if episode is not None and key in episode:
                values.append(float(episode[key]))
        if values:
            episode_metrics[key] = {"mean": float(np.mean(values)), "std": float(np.std(values))}
    traces: dict[str, Any] = {}
    if job_result.step_infos:
        first = job_result.step_infos[0][agents[0]]
        if "time" in first:
            traces["time"] = first["time"]
        for key, _ in compare["step_metrics"]:
            per_episode = [np.sum([trace[a][key] for a in agents], axis=0) for trace in job_result.step_infos]
            traces[key] = {"mean": np.mean(per_episode, axis=0).tolist(), "std": np.std(per_episode, axis=0).tolist()}
    return {
        "weights": None if weights is None else list(weights),
        "return_discounted": disc.tolist(),
        "return_undiscounted": undisc.tolist(),
        "scalarized_discounted": None if weights is None else float(np.dot(weights, disc)),
        "agents": {
            a: {
                "discounted": job_result.mean_discounted(a).tolist(),
                "undiscounted": job_result.mean_undiscounted(a).tolist(),
            }
            for a in agents
        },
        "episode_metrics": episode_metrics,
        "traces": traces,
    }


def _compare(args: argparse.Namespace) -> int:
    from sb3_sfgpi.common.evaluation import EvaluationJob, ParallelEvaluator, run_job

    config = _read_run(args.run_dir)
    if config["algorithm"] == "fixed":
        raise UsageError(f"{args.run_dir} is a fixed-weight run: pass it with --fixed, after an MA-SFOLS run")
    domain = load_domain(config["domain"])
    if args.episodes < 1:
        raise UsageError(f"--episodes must be positive, got {args.episodes}")
    workers = domain.get("eval_workers", 0) if args.workers is None else args.workers
    if workers < 0:
        raise UsageError(f"--workers must be 0 or more, got {workers}")
    gamma = config["learner_kwargs"].get("gamma", 0.99)
    env_kwargs = config["env_kwargs"]
    gpi_set = args.gpi_set or config.get("gpi_set", "all")
    n_objectives = len(domain.get("objectives") or [])
    compare: dict[str, Any] = {
        "format": COMPARE_FORMAT,
        "version": 1,
        "domain": config["domain"],
        "run_dir": str(args.run_dir),
        "env_kwargs": env_kwargs,
        "gamma": gamma,
        "episodes": args.episodes,
        "seed": args.seed,
        "gpi_set": gpi_set,
        "objectives": domain.get("objectives"),
        "episode_metrics": domain.get("episode_metrics", []),
        "step_metrics": domain.get("step_metrics", []),
        "rows": [],
    }
    # (row header, job) pairs; every method is evaluated on the same episode seeds.
    planned: list[tuple[dict[str, Any], EvaluationJob]] = []
    fixed_runs = []
    for run_dir in args.fixed:
        fixed = _read_run(run_dir)
        if fixed["algorithm"] != "fixed" or fixed["domain"] != config["domain"]:
            raise UsageError(f"--fixed {run_dir} is not a fixed-weight run of {config['domain']}")
        if fixed["env_kwargs"] != env_kwargs:
            raise UsageError(f"--fixed {run_dir} was trained on another env configuration than {args.run_dir}")
        fixed_runs.append((run_dir, fixed))
    weights: list[list[float]] = [_check_weights(w, "--w") for w in (args.w or domain.get("compare_weights") or [])]
    for _, fixed in fixed_runs:
        if not any(np.allclose(fixed["fixed_weights"], w) for w in weights):
            weights.append(list(fixed["fixed_weights"]))
    if not weights:
        raise UsageError("no weights to evaluate GPI at: pass --w")
    for w in weights:
        if n_objectives and len(w) != n_objectives:
            raise UsageError(f"--w must have length {n_objectives} (one weight per objective), got {len(w)}")

    def job(weights: Sequence[float] | None, policy_dir: Path | None = None, **kwargs: Any) -> EvaluationJob:
        return EvaluationJob(
            args.seed, None if weights is None else tuple(weights), args.episodes,
            None if policy_dir is None else str(policy_dir), record_infos=True, **kwargs,
        )

    for w in weights:
        header = {"method": "gpi", "label": f"GPI w={_format(w)}", "run_dir": str(args.run_dir)}
        planned.append((header, job(w, args.run_dir / "policy_set", ccs_only=gpi_set == "ccs")))
    for run_dir, fixed in fixed_runs:
        w = fixed["fixed_weights"]
        header = {"method": "fixed", "label": f"scalarized w={_format(w)}", "run_dir": str(run_dir)}
        planned.append((header, job(w, run_dir / "policy_set", own_policies=True)))
    if not args.no_baselines:
        for name, overrides in (domain.get("baselines") or {}).items():
            header = {"method": "baseline", "label": name, "run_dir": None}
            planned.append((header, job(None, env_overrides=tuple(sorted(overrides.items())))))
    for _, planned_job in planned:
        if planned_job.policy_dir is not None and not (Path(planned_job.policy_dir) / "manifest.json").exists():
            raise UsageError(f"{Path(planned_job.policy_dir).parent} has no policy set yet")

    print(f"evaluating {len(planned)} methods x {args.episodes} episode(s) in {workers or 'this'} process(es)")
    if workers:
        with ParallelEvaluator(domain["make_env"], env_kwargs, workers, gamma) as evaluator:
            results = evaluator.run([j for _, j in planned])
    else:
        results = []
        for _, planned_job in planned:
            env = domain["make_env"](**{**env_kwargs, **dict(planned_job.env_overrides)})
            try:
                results.append(run_job(env, planned_job, gamma))
            finally:
                env.close()
    for (header, planned_job), result in zip(planned, results, strict=True):
        compare["rows"].append({**header, **_summarize(result, planned_job.weights, compare)})
    output = args.output or args.run_dir / "compare.json"
    atomic_write_json(output, compare)
    print(format_comparison(compare))
    print(f"wrote {output}")
    return 0


def _format(w: Sequence[float]) -> str:
    return "[" + ",".join(f"{x:g}" for x in np.round(w, 3)) + "]"


def format_comparison(compare: dict[str, Any]) -> str:
    """
    A Markdown table of a comparison: per method its episode metrics and its scalarised discounted return
    (mean over agents), then for every fixed-weight learner the gap of GPI to it at its weight.
    """
    metrics = compare["episode_metrics"]
    head = ["method", *[label for _, label in metrics], "w·G (discounted)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in compare["rows"]:
        cells = [row["label"]]
        for key, _ in metrics:
            m = row["episode_metrics"].get(key)
            cells.append("-" if m is None else f"{m['mean']:.2f} ± {m['std']:.2f}")
        scalarized = row["scalarized_discounted"]
        cells.append("-" if scalarized is None else f"{scalarized:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    gpi = {tuple(np.round(r["weights"], 6)): r for r in compare["rows"] if r["method"] == "gpi"}
    for row in compare["rows"]:
        if row["method"] != "fixed":
            continue
        w = row["weights"]
        match = gpi.get(tuple(np.round(w, 6)))
        if match is None:
            continue
        ours, theirs = match["scalarized_discounted"], row["scalarized_discounted"]
        gap = (ours - theirs) / abs(theirs) if theirs else float("nan")
        lines.append(
            f"\nw={_format(w)}: GPI w·G = {ours:.3f}, scalarized learner {theirs:.3f} "
            f"(GPI {'above' if gap >= 0 else 'below'} by {abs(gap):.1%} of |learner|)"
        )
    return "\n".join(lines)


def _plot(args: argparse.Namespace) -> int:
    from sb3_sfgpi import plots

    if args.kind == "returns":
        runs = []
        for run_dir in args.run_dirs:
            config = _read_run(run_dir)
            if not (run_dir / "evaluation.csv").exists():
                raise UsageError(f"{run_dir} has no evaluation.csv yet")
            runs.append((config["algorithm"], run_dir))
        written = [plots.plot_returns(runs, args.output, args.metric, args.title)]
    else:
        if len(args.run_dirs) != 1:
            raise UsageError(f"--kind {args.kind} draws one comparison file, got {len(args.run_dirs)} inputs")
        path = args.run_dirs[0]
        if not path.is_file():
            raise UsageError(f"{path} is not a comparison file (written by sb3-sfgpi compare)")
        compare = read_json(path, "comparison")
        if not isinstance(compare, dict) or compare.get("format") != COMPARE_FORMAT:
            raise UsageError(f"{path} is not a comparison file (written by sb3-sfgpi compare)")
        if args.smooth < 1:
            raise UsageError(f"--smooth must be positive, got {args.smooth}")
        draw: dict[str, Callable[[dict[str, Any], Path], Any]] = {
            "steps": lambda c, o: plots.plot_step_metrics(c, o, smooth=args.smooth),
            "versus": lambda c, o: plots.plot_versus(c, o, smooth=args.smooth),
            "tradeoff": plots.plot_tradeoff,
        }
        result = draw[args.kind](compare, args.output)
        written = result if isinstance(result, list) else [result]
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

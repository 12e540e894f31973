"""``sb3-sfgpi compare RUN``: GPI at several weights, fixed-weight learners and the domain's baselines, same episodes.

The comparison file (JSON)::

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
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import CLI_SETTINGS, DomainPreset, load_domain
from sb3_sfgpi.cli.values import check_weights
from sb3_sfgpi.common.serialization import atomic_write_json
from sb3_sfgpi.common.weights import format_weights, same_weight
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import policy_set_manifest
from sb3_sfgpi.run_settings import GAMMA, acts_by_own_policies

if TYPE_CHECKING:
    from sb3_sfgpi.common.rollouts import EpisodeReturns
    from sb3_sfgpi.evaluation_jobs import EvaluationJob

COMPARE_FORMAT = "sb3-sfgpi/compare"
#: (row header, job): what one row of the comparison evaluates
Planned = tuple[dict[str, Any], "EvaluationJob"]


def add_parser(sub: Any) -> None:
    """The ``compare`` sub-command's arguments."""
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


def run(args: argparse.Namespace) -> int:
    """Evaluate every method on the same episodes; write the comparison file and print its table."""
    run_dir = RunDirectory(args.run_dir)
    config = run_dir.read_config(required=CLI_SETTINGS)
    if config.get("algorithm") == "fixed":
        raise UsageError(f"{args.run_dir} is a fixed-weight run: pass it with --fixed, after an MA-SFOLS run")
    preset = load_domain(config["domain"])
    env_kwargs = preset.run_file_env(config["env_kwargs"], run_dir)  # an allow-list: run files come from elsewhere
    preset.build_env(env_kwargs).close()  # a damaged run.json: one line here, not in a worker
    if args.episodes < 1:
        raise UsageError(f"--episodes must be positive, got {args.episodes}")
    if args.seed < 0:
        raise UsageError(f"--seed must be 0 or more (the environment's reset seed), got {args.seed}")
    workers = preset.eval_workers if args.workers is None else args.workers
    if workers < 0:
        raise UsageError(f"--workers must be 0 or more, got {workers}")
    gamma = config["learner_kwargs"].get("gamma", GAMMA)
    compare: dict[str, Any] = {
        "format": COMPARE_FORMAT,
        "version": 1,
        "domain": config["domain"],
        "run_dir": str(args.run_dir),
        "env_kwargs": config["env_kwargs"],
        "gamma": gamma,
        "episodes": args.episodes,
        "seed": args.seed,
        "gpi_set": args.gpi_set or config.get("gpi_set", "all"),
        "objectives": preset.objective_names(config["env_kwargs"]),
        "episode_metrics": preset.episode_metrics,
        "step_metrics": preset.step_metrics,
        "rows": [],
    }
    planned = _planned(args, run_dir, config, preset, compare["gpi_set"])
    print(f"evaluating {len(planned)} methods x {args.episodes} episode(s) in {workers or 'this'} process(es)")
    results = _run(planned, preset, config["env_kwargs"], gamma, workers)
    for (header, job), result in zip(planned, results, strict=True):
        compare["rows"].append({**header, **summarize_row(result, job.weights, compare)})
    reported = {key for row in compare["rows"] for key in row["episode_metrics"]}  # no pedestrians' without crossings
    compare["episode_metrics"] = [metric for metric in compare["episode_metrics"] if metric[0] in reported]
    output = args.output or run_dir.compare_file
    atomic_write_json(output, compare)
    print(format_comparison(compare))
    print(f"wrote {output}")
    return 0


def _fixed_runs(
    args: argparse.Namespace, config: dict[str, Any], preset: DomainPreset
) -> list[tuple[RunDirectory, dict[str, Any]]]:
    runs = []
    for path in args.fixed:
        fixed = RunDirectory(path)
        fixed_config = fixed.read_config(required=CLI_SETTINGS)
        preset.run_file_env(fixed_config["env_kwargs"], fixed)
        if fixed_config.get("algorithm") != "fixed" or fixed_config.get("domain") != config["domain"]:
            raise UsageError(f"--fixed {path} is not a fixed-weight run of {config['domain']}")
        if not preset.same_env(fixed_config["env_kwargs"], config["env_kwargs"]):
            raise UsageError(f"--fixed {path} was trained on another env configuration than {args.run_dir}")
        runs.append((fixed, fixed_config))
    return runs


def _planned(
    args: argparse.Namespace, run_dir: RunDirectory, config: dict[str, Any], preset: DomainPreset, gpi_set: str
) -> list[Planned]:
    """Every method as a job on the same episode seeds: GPI at each weight, the fixed learners, the baselines."""
    from sb3_sfgpi.evaluation_jobs import EvaluationJob  # torch: once the options are checked

    fixed_runs = _fixed_runs(args, config, preset)
    weights = [check_weights(w, "--w") for w in (args.w or preset.compare_weights)]
    for _, fixed in fixed_runs:
        if not any(same_weight(fixed["weights"], w) for w in weights):
            weights.append(list(fixed["weights"]))
    if not weights:
        raise UsageError("no weights to evaluate GPI at: pass --w")
    n_objectives = len(preset.objective_names(config["env_kwargs"]) or [])
    for w in weights:
        if n_objectives and len(w) != n_objectives:
            raise UsageError(f"--w must have length {n_objectives} (one weight per objective), got {len(w)}")

    def job(weights: Any, source: RunDirectory | None = None, **kwargs: Any) -> EvaluationJob:
        manifest = None if source is None else policy_set_manifest(source)
        if source is not None and manifest is None:
            raise UsageError(f"{source} has no policy set yet")
        policy_dir = None if manifest is None else str(manifest)
        weights = None if weights is None else tuple(weights)
        return EvaluationJob(args.seed, weights, args.episodes, policy_dir, record_infos=True, **kwargs)

    planned: list[Planned] = []
    for w in weights:
        header = {"method": "gpi", "label": f"GPI w={format_weights(w)}", "run_dir": str(args.run_dir)}
        planned.append((header, job(w, run_dir, ccs_only=gpi_set == "ccs")))
    for fixed, fixed_config in fixed_runs:
        w = fixed_config["weights"]
        header = {"method": "fixed", "label": f"scalarized w={format_weights(w)}", "run_dir": str(fixed)}
        own = acts_by_own_policies(fixed=True, sharing=fixed_config.get("sharing"))
        planned.append((header, job(w, fixed, own_policies=own)))
    if not args.no_baselines:
        for name, overrides in preset.baselines.items():
            header = {"method": "baseline", "label": name, "run_dir": None}
            planned.append((header, job(None, env_overrides=tuple(sorted(overrides.items())))))
    return planned


def _run(
    planned: list[Planned], preset: DomainPreset, env_kwargs: dict[str, Any], gamma: float, workers: int
) -> list[EpisodeReturns]:
    from sb3_sfgpi.evaluation_jobs import ParallelEvaluator, run_job  # torch: here, not to read or plot a comparison

    if workers:
        with ParallelEvaluator(preset.make_env, env_kwargs, workers, gamma) as evaluator:
            return evaluator.run([job for _, job in planned])
    results = []
    for _, job in planned:
        env = preset.build_env({**env_kwargs, **dict(job.env_overrides)})
        try:
            results.append(run_job(env, job, gamma))
        finally:
            env.close()
    return results


def summarize_row(result: EpisodeReturns, weights: Any, compare: dict[str, Any]) -> dict[str, Any]:
    """One row of a comparison file from a method's episodes."""
    agents = list(result.discounted)
    disc = result.mean_discounted_over(agents)
    return {
        "weights": None if weights is None else list(weights),
        "return_discounted": disc.tolist(),
        "return_undiscounted": np.mean([result.mean_undiscounted(a) for a in agents], axis=0).tolist(),
        "scalarized_discounted": None if weights is None else float(np.dot(weights, disc)),
        "agents": {
            a: {"discounted": result.mean_discounted(a).tolist(), "undiscounted": result.mean_undiscounted(a).tolist()}
            for a in agents
        },
        "episode_metrics": episode_metrics(result, compare["episode_metrics"]),
        "traces": _traces(result, compare["step_metrics"]),
    }


def episode_metrics(result: EpisodeReturns, metrics: list[list[str]]) -> dict[str, dict[str, float]]:
    """Mean and std over episodes of each metric of the ``"episode"`` entry of the last infos."""
    summary = {}
    for key, _ in metrics:
        values = []
        for infos in result.final_infos:
            episode = next((info["episode"] for info in infos.values() if "episode" in info), None)
            if episode is not None and key in episode:
                values.append(float(episode[key]))
        if values:
            summary[key] = {"mean": float(np.mean(values)), "std": float(np.std(values))}
    return summary


def _traces(result: EpisodeReturns, metrics: list[list[str]]) -> dict[str, Any]:
    """Per step, each metric summed over agents: mean and std over episodes (and the time axis, if recorded)."""
    traces: dict[str, Any] = {}
    if not result.step_infos:
        return traces
    agents = list(result.discounted)
    first = result.step_infos[0][agents[0]]
    if "time" in first:
        traces["time"] = first["time"]
    for key, _ in metrics:
        per_episode = [np.sum([trace[a][key] for a in agents], axis=0) for trace in result.step_infos]
        traces[key] = {"mean": np.mean(per_episode, axis=0).tolist(), "std": np.std(per_episode, axis=0).tolist()}
    return traces


#: What the comparisons merged by :func:`merge_comparisons` must share.
SHARED_SETTINGS = ("format", "domain", "episodes", "seed", "objectives", "episode_metrics", "step_metrics")


def merge_comparisons(compares: list[dict[str, Any]]) -> dict[str, Any]:
    """
    One comparison from several of the same methods on the same episodes, one per training seed: each row's means
    are the means over the files, its stds the std over the episodes of all files (pooled), and ``w·G`` gets its std
    over the files (``scalarized_discounted_std``). ``merged`` counts the files.

    :raises ValueError: comparisons of other settings, or whose methods differ (the message names the first)
    """
    first = compares[0]
    for other in compares[1:]:
        for key in SHARED_SETTINGS:
            if other.get(key) != first.get(key):
                raise ValueError(f"the comparisons differ in {key!r}: {first.get(key)!r} and {other.get(key)!r}")
    by_key = [{_row_key(r): r for r in c["rows"]} for c in compares]
    if any(
        len(rows) != len(c["rows"]) or rows.keys() != by_key[0].keys() for rows, c in zip(by_key, compares, strict=True)
    ):
        raise ValueError("the comparisons hold different methods or weights; compare each run the same way")
    rows = [_merged_row([rows[_row_key(row)] for rows in by_key]) for row in first["rows"]]
    return {**first, "run_dir": [c["run_dir"] for c in compares], "merged": len(compares), "rows": rows}


def _row_key(row: dict[str, Any]) -> tuple[Any, ...]:
    weights = None if row["weights"] is None else tuple(np.round(row["weights"], 6))
    return row["method"], weights, row["label"] if row["method"] == "baseline" else None


def _pooled(stats: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and std over all episodes of equally many episodes per file, from each file's mean and std."""
    means, stds = np.array([s["mean"] for s in stats], dtype=float), np.array([s["std"] for s in stats], dtype=float)
    std = np.sqrt(np.mean(stds**2, axis=0) + np.var(means, axis=0))
    return {"mean": np.mean(means, axis=0).tolist(), "std": std.tolist()}


def _merged_row(rows: list[dict[str, Any]]) -> dict[str, Any]:
    first = rows[0]
    scalarized = [r["scalarized_discounted"] for r in rows]
    traces = {key: _pooled([r["traces"][key] for r in rows]) for key in first["traces"] if key != "time"}
    metrics = {key: _pooled([r["episode_metrics"][key] for r in rows]) for key in first["episode_metrics"]}
    return {
        **first,
        "run_dir": [r["run_dir"] for r in rows],
        "return_discounted": np.mean([r["return_discounted"] for r in rows], axis=0).tolist(),
        "return_undiscounted": np.mean([r["return_undiscounted"] for r in rows], axis=0).tolist(),
        "scalarized_discounted": None if first["weights"] is None else float(np.mean(scalarized)),
        "scalarized_discounted_std": None if first["weights"] is None else float(np.std(scalarized)),
        "episode_metrics": metrics,
        "traces": {**first["traces"], **traces},
    }


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
        scalarized, spread = row["scalarized_discounted"], row.get("scalarized_discounted_std")
        cells.append("-" if scalarized is None else f"{scalarized:.3f}" + (f" ± {spread:.3f}" if spread else ""))
        lines.append("| " + " | ".join(cells) + " |")
    gpi = {tuple(np.round(r["weights"], 6)): r for r in compare["rows"] if r["method"] == "gpi"}
    for row in compare["rows"]:
        match = gpi.get(tuple(np.round(row["weights"], 6))) if row["method"] == "fixed" else None
        if match is None:
            continue
        ours, theirs = match["scalarized_discounted"], row["scalarized_discounted"]
        gap = (ours - theirs) / abs(theirs) if theirs else float("nan")
        lines.append(
            f"\nw={format_weights(row['weights'])}: GPI w·G = {ours:.3f}, scalarized learner {theirs:.3f} "
            f"(GPI {'above' if gap >= 0 else 'below'} by {abs(gap):.1%} of |learner|)"
        )
    return "\n".join(lines)

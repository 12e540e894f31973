"""Reproduce the traffic-signal section of the paper (Sec. 5.2, Figs. 7-15) with the ``sb3-sfgpi`` command line.

1. MA-SFOLS + GPI on the three-intersection SUMO scenario, one run per seed (Fig. 7: GPI return over
   iterations on 25 test weights);
2. per seed, the a priori scalarised baselines: SFDQN learners trained from scratch on one fixed weight (the
   paper's Q-learning baselines), w in {[0.5, 0.5], [0.4, 0.6], [0.2, 0.8]}, with as many steps per agent as
   that seed's MA-SFOLS run;
3. per seed, ``sb3-sfgpi compare``: GPI at several weights, the scalarised learners and SUMO's fixed-time and
   actuated programs on the same evaluation episodes (per-objective waiting times, per-step traces);
4. the figures, from all seeds (mean ± std over the episodes of all): Fig. 7 (returns), Figs. 8-10 (waiting
   times over the episode for GPI at several w), Figs. 11-15 (GPI vs the scalarised learners), a trade-off;
5. the checks of the section and of issue 10's goals, on all seeds: more pedestrian weight means less pedestrian
   waiting, GPI beats fixed-time on vehicles at w = [1, 0] and on pedestrians at w = [0, 1] (there by half),
   GPI at w = [1, 0] waits no longer than actuated for vehicles, and GPI is within 5% of the scalarised
   learners at their weights.

The training runs go through ``sb3_sfgpi.cli.sweep_runner`` (a local Ray, or the cluster at ``--address``): first the
MA-SFOLS runs of all seeds, then the scalarised learners of all seeds (their budget is their seed's MA-SFOLS run).
Runs that already exist are resumed (finished ones are skipped), so the script can be interrupted and re-run.

Example (the defaults; about two hours on two cores)::

    python examples/traffic.py --out runs/traffic-paper --figures docs/figures
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from sb3_sfgpi.cli import load_domain, main
from sb3_sfgpi.cli.compare import format_comparison, merge_comparisons
from sb3_sfgpi.cli.sweep_runner import RunSpec, run_sweep
from sb3_sfgpi.run_directory import RunDirectory


def _run(argv: list[str]) -> None:
    print("$ sb3-sfgpi " + " ".join(argv), flush=True)
    code = main(argv)
    if code != 0:
        sys.exit(code)


def _train(args: argparse.Namespace, specs: list[RunSpec]) -> None:
    """Train (or continue) the runs as one sweep; stop if one failed."""
    for spec in specs:
        print(f"$ sb3-sfgpi {' '.join(spec.train_argv(args.out / spec.run_name, resume=False))}", flush=True)
    cpus = 1 + args.eval_workers  # a run and its evaluation processes
    outcomes = run_sweep(specs, args.out, address=args.address, cpus_per_run=cpus, progress_bar=False)
    failed = [f"{o.spec.run_name}: {o.error}" for o in outcomes if o.status == "failed"]
    if failed:
        sys.exit("runs failed: " + "; ".join(failed))


def _tag(w: list[float]) -> str:
    return "-".join(f"{x:g}" for x in w)


VEHICLE_WAIT, PEDESTRIAN_WAIT = "vehicle_waiting_time_mean", "pedestrian_waiting_time_mean"
Check = tuple[str, bool, str]
"""A claim, whether it holds, and the numbers behind it."""


def checks(compare: dict) -> list[Check]:
    """The section's claims, each as (claim, holds, numbers), from a comparison file of the traffic domain."""
    rows = compare["rows"]
    gpi = {tuple(np.round(r["weights"], 6)): r for r in rows if r["method"] == "gpi"}
    baseline = {r["label"]: r for r in rows if r["method"] == "baseline"}
    fixed = [(r, gpi[w]) for r in rows if r["method"] == "fixed" and (w := tuple(np.round(r["weights"], 6))) in gpi]
    return [
        *trend_checks(gpi),
        *baseline_checks(gpi, baseline),
        *[check for row, match in fixed for check in scalarised_checks(row, match)],
    ]


def metric(row: dict, key: str) -> float:
    """The mean over episodes of one of a comparison row's episode metrics."""
    return row["episode_metrics"][key]["mean"]


def trend_checks(gpi: dict[tuple, dict]) -> list[Check]:
    """Pedestrians wait less and vehicles more as the pedestrian weight grows: on the three main weights, then all."""
    results = []
    for weights, strict in (([(1.0, 0.0), (0.5, 0.5), (0.0, 1.0)], True), (sorted(gpi, key=lambda w: w[1]), False)):
        order = [w for w in weights if w in gpi]  # increasing pedestrian weight
        if len(order) < 2:
            continue
        scope = "w in {[1,0], [0.5,0.5], [0,1]}" if strict else f"all {len(order)} weights (noise: 1 std ≈ 0.5 s)"
        for key, name, trend, sign in (
            (PEDESTRIAN_WAIT, "pedestrian", "decreases", -1),
            (VEHICLE_WAIT, "vehicle", "increases", 1),
        ):
            values = [metric(gpi[w], key) for w in order]
            results.append(
                (
                    f"GPI {name} waiting {trend} as w1 grows, {scope}",
                    bool(np.all(sign * np.diff(values) > 0)),
                    ", ".join(f"w1={w[1]:g}: {v:.2f}" for w, v in zip(order, values, strict=True)),
                )
            )
    return results


def baseline_checks(gpi: dict[tuple, dict], baseline: dict[str, dict]) -> list[Check]:
    """GPI at the simplex extrema against SUMO's fixed-time and actuated programs."""
    results = []
    if "fixed-time" in baseline:
        fixed_time = baseline["fixed-time"]
        for w, key, name in (((1.0, 0.0), VEHICLE_WAIT, "vehicles"), ((0.0, 1.0), PEDESTRIAN_WAIT, "pedestrians")):
            if w in gpi:
                ours, theirs = metric(gpi[w], key), metric(fixed_time, key)
                results.append(
                    (f"GPI at w={list(w)} beats fixed-time on {name}", ours < theirs, f"{ours:.2f} vs {theirs:.2f} s")
                )
        if (0.0, 1.0) in gpi:
            ours, theirs = metric(gpi[(0.0, 1.0)], PEDESTRIAN_WAIT), metric(fixed_time, PEDESTRIAN_WAIT)
            claim = "GPI at w=[0, 1] keeps pedestrians waiting at most half as long as fixed-time"
            results.append((claim, ours <= theirs / 2, f"{ours:.2f} vs {theirs:.2f} s"))
    if "actuated" in baseline and (1.0, 0.0) in gpi:
        ours, theirs = metric(gpi[(1.0, 0.0)], VEHICLE_WAIT), metric(baseline["actuated"], VEHICLE_WAIT)
        claim = "GPI at w=[1, 0] keeps vehicles waiting no longer than actuated"
        results.append((claim, ours <= theirs, f"{ours:.2f} vs {theirs:.2f} s"))
    return results


def scalarised_checks(row: dict, match: dict) -> list[Check]:
    """GPI within 5% of the learner trained a priori for the same weight, in w·return and in w·(mean waiting)."""
    ours, theirs = match["scalarized_discounted"], row["scalarized_discounted"]
    gap = (theirs - ours) / abs(theirs)
    w = np.asarray(row["weights"])
    cost_ours = float(w @ [metric(match, VEHICLE_WAIT), metric(match, PEDESTRIAN_WAIT)])
    cost_theirs = float(w @ [metric(row, VEHICLE_WAIT), metric(row, PEDESTRIAN_WAIT)])
    return [
        (
            f"GPI within 5% of the scalarised learner's w·return at w={row['weights']}",
            bool(gap <= 0.05),
            f"{ours:.4f} vs {theirs:.4f} (GPI {'below' if gap > 0 else 'above'} by {abs(gap):.1%})",
        ),
        (
            f"GPI within 5% of the scalarised learner's w·(mean waiting) at w={row['weights']}",
            bool(cost_ours <= 1.05 * cost_theirs),
            f"{cost_ours:.2f} vs {cost_theirs:.2f} s",
        ),
    ]


def env_speed(episodes: int = 3, seed: int = 0) -> float:
    """Simulated seconds per wall-clock second of the traffic env alone (random keep/change actions, resets
    included), with the domain's env settings."""
    import time

    domain = load_domain("traffic")
    env = domain.make_env(**domain.env_kwargs)
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    simulated = 0.0
    try:
        for episode in range(episodes):
            env.reset(seed=seed + episode)
            while env.agents:
                env.step({a: int(rng.integers(2)) for a in env.agents})
            simulated += env.sim_time
    finally:
        env.close()
    return simulated / (time.perf_counter() - start)


def evaluation_speed(run_dir: Path, workers: int = 2) -> dict[str, float]:
    """Wall seconds of GPI on the run's 25 test weights (one episode each, its training seeds), in this process
    and in ``workers`` worker processes (pool started beforehand); checks that the returns are identical."""
    import time

    from sb3_sfgpi.common.seeding import derive_seed
    from sb3_sfgpi.evaluation_jobs import EvaluationJob, ParallelEvaluator, run_job

    run = RunDirectory(run_dir)
    config = run.read_config()
    domain = load_domain("traffic")
    gamma = config["learner_kwargs"]["gamma"]
    jobs = [
        EvaluationJob(derive_seed(config["seed"], "eval", i), tuple(w), 1, str(run.policy_set_dir),
                      ccs_only=config.get("gpi_set") == "ccs")
        for i, w in enumerate(config["test_weights"])
    ]  # fmt: skip
    start = time.perf_counter()
    env = domain.make_env(**config["env_kwargs"])
    try:
        in_process = [run_job(env, job, gamma) for job in jobs]
    finally:
        env.close()
    seconds = {"in-process": time.perf_counter() - start}
    with ParallelEvaluator(domain.make_env, config["env_kwargs"], workers, gamma) as evaluator:
        evaluator.run(jobs[:workers])  # start the pool
        start = time.perf_counter()
        parallel = evaluator.run(jobs)
        seconds[f"{workers} workers"] = time.perf_counter() - start
    for a, b in zip(in_process, parallel, strict=True):
        assert all(np.array_equal(a.discounted[k], b.discounted[k]) for k in a.discounted), "results differ"
    return seconds


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    domain = load_domain("traffic")
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/traffic-paper"), help="folder of all the runs")
    parser.add_argument("--figures", type=Path, default=Path("docs/figures"), help="folder of the PNGs")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="one MA-SFOLS run per seed (Fig. 7)")
    parser.add_argument("--iterations", type=int, default=domain.iterations, help="MA-SFOLS iterations")
    parser.add_argument("--steps-per-iteration", type=int, default=domain.settings.steps_per_iteration)
    parser.add_argument(
        "--fixed-weights", type=float, nargs=2, action="append", help="weights of the scalarised learners (repeat)"
    )
    parser.add_argument("--no-fixed", action="store_true", help="skip the scalarised learners")
    parser.add_argument("--episodes", type=int, default=5, help="evaluation episodes per method in the comparison")
    parser.add_argument("--eval-workers", type=int, default=domain.eval_workers, help="evaluation processes")
    parser.add_argument("--address", help="a Ray cluster to train on (default: RAY_ADDRESS, else a local Ray)")
    parser.add_argument(
        "--speed",
        action="store_true",
        help="only measure the env's simulated seconds per second and, if the first seed's MA-SFOLS run exists, "
        "the time of its GPI evaluation in-process and in --eval-workers processes",
    )
    args = parser.parse_args(argv)
    args.fixed_weights = [] if args.no_fixed else (args.fixed_weights or domain.fixed_weights)
    return args


def run(args: argparse.Namespace) -> list[tuple[str, bool, str]]:
    budget = ["--iterations", str(args.iterations), "--steps-per-iteration", str(args.steps_per_iteration)]
    common = (*budget, "--set", f"eval_workers={args.eval_workers}")
    masfols = [args.out / f"ma-sfols-s{seed}" for seed in args.seeds]
    runs = list(zip(args.seeds, masfols, strict=True))
    _train(args, [RunSpec("traffic", "ma-sfols", seed, None, common, run_dir.name) for seed, run_dir in runs])
    _train(args, [spec for seed, run_dir in runs for spec in fixed_specs(args, common, seed, run_dir)])
    compare_files = [compare_seed(args, seed, run_dir) for seed, run_dir in runs]

    figures = args.figures
    figures.mkdir(parents=True, exist_ok=True)  # `sb3-sfgpi plot` writes only into directories that exist
    _run(["plot", *map(str, masfols), "-o", str(figures / "traffic_returns.png"),
          "--title", "Traffic: GPI return over iterations (25 test weights)"])  # fmt: skip
    compares = list(map(str, compare_files))
    _run(["plot", *compares, "--kind", "steps", "-o", str(figures / "traffic")])
    if args.fixed_weights:
        _run(["plot", *compares, "--kind", "versus", "-o", str(figures / "traffic")])
    _run(["plot", *compares, "--kind", "tradeoff", "-o", str(figures / "traffic_tradeoff.png")])

    merged = merge_comparisons([json.loads(path.read_text()) for path in compare_files])
    print(f"\n{len(compare_files)} seed(s), mean ± std over the episodes of all:\n{format_comparison(merged)}")
    results = checks(merged)
    print("\nchecks:")
    for claim, holds, numbers in results:
        print(f"  [{'ok' if holds else 'NOT MET'}] {claim}: {numbers}")
    return results


def fixed_paths(args: argparse.Namespace, seed: int) -> list[Path]:
    return [args.out / f"fixed-w{_tag(w)}-s{seed}" for w in args.fixed_weights]


def fixed_specs(args: argparse.Namespace, common: tuple[str, ...], seed: int, run_dir: Path) -> list[RunSpec]:
    """The scalarised learners of ``seed``: as many steps per agent as its MA-SFOLS run in ``run_dir`` took."""
    options = (*common, "--budget-from", str(run_dir.resolve()))  # the sweep's workers may run elsewhere
    return [
        RunSpec("traffic", "fixed", seed, tuple(w), options, out.name)
        for w, out in zip(args.fixed_weights, fixed_paths(args, seed), strict=True)
    ]


def compare_seed(args: argparse.Namespace, seed: int, run_dir: Path) -> Path:
    """The comparison of ``seed``'s methods (GPI, the scalarised learners, SUMO's programs) on common episodes."""
    fixed = fixed_paths(args, seed)
    compare_file = args.out / f"compare-s{seed}.json"
    if not compare_file.is_file():
        argv = ["compare", str(run_dir), "--episodes", str(args.episodes), "--workers", str(max(args.eval_workers, 1))]
        _run([*argv, *(["--fixed", *map(str, fixed)] if fixed else []), "-o", str(compare_file)])
    return compare_file


if __name__ == "__main__":  # the evaluation workers are spawned: they re-import this file
    arguments = parse_args()
    if arguments.speed:
        print(f"traffic env: {env_speed():.0f} simulated seconds per second (random actions, 3 episodes of 500 s)")
        run_dir = arguments.out / f"ma-sfols-s{arguments.seeds[0]}"
        if RunDirectory(run_dir).has_checkpoint():
            timing = evaluation_speed(run_dir, max(arguments.eval_workers, 1))
            print(
                f"GPI on the test weights of {run_dir}: "
                + ", ".join(f"{k} {v:.1f} s" for k, v in timing.items())
                + " (identical returns)"
            )
    else:
        run(arguments)

"""``sb3-sfgpi sweep``: many ``train`` runs on Ray (domains × algorithms × seeds × weights, or a spec file)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from sb3_sfgpi.cli.errors import TrainingStopped, UsageError
from sb3_sfgpi.cli.presets import WEIGHT_HELP
from sb3_sfgpi.cli.sweep_runner import ALGORITHMS, RunOutcome, grid, read_spec, run_sweep


def add_parser(sub: Any) -> None:
    """The ``sweep`` sub-command's arguments."""
    sweep = sub.add_parser(
        "sweep",
        help="train many runs as Ray tasks (resumable; finished runs are skipped)",
        description="Every run is `sb3-sfgpi train` in a Ray worker, into OUT/<domain>-<algo>[-w…]-s<seed>. Options "
        "after `--` go to every run, e.g. `sb3-sfgpi sweep --domains four-room --algos ma-sfols random --seeds 0 1 2 "
        "--out runs/fig4 -- --iterations 5`.",
    )
    sweep.add_argument("--domains", nargs="+", default=[], help="four-room, traffic, or other installed domains")
    sweep.add_argument("--algos", nargs="+", choices=ALGORITHMS, default=["ma-sfols"], help="default: ma-sfols")
    sweep.add_argument("--seeds", type=int, nargs="+", default=[0], help="default: 0")
    sweep.add_argument(
        "--w", type=float, nargs="+", action="append", default=[], help=f"weights of --algos fixed (repeat for more; "
        f"{WEIGHT_HELP})",
    )  # fmt: skip
    sweep.add_argument(
        "--spec", type=Path, help="a JSON sweep file instead of the grid options (see sb3_sfgpi.cli.sweep_runner)"
    )
    sweep.add_argument("--out", type=Path, required=True, help="the sweep's directory: one run directory per run")
    sweep.add_argument(
        "--address", help="join this Ray cluster (default: RAY_ADDRESS, else a local Ray with --num-cpus CPUs)"
    )
    sweep.add_argument(
        "--no-shared-filesystem", action="store_true", help="the cluster's nodes do not all see --out: each run works "
        "in its node's temporary directory and sends its run directory to --out on this machine after every checkpoint"
        " (a retried run continues from the last one that arrived)",
    )  # fmt: skip
    sweep.add_argument("--num-cpus", type=int, help="CPUs of the local Ray (default: the machine's)")
    sweep.add_argument("--cpus-per-run", type=float, default=1.0, help="CPUs reserved for each run (default 1)")
    sweep.add_argument("--max-retries", type=int, default=3, help="tries after a run's worker died (default 3)")
    sweep.add_argument("--no-progress", action="store_true", help="no progress bar")
    sweep.add_argument("train_options", nargs=argparse.REMAINDER, help="after --: options of every `train`")


def run(args: argparse.Namespace) -> int:
    """Run the sweep; print one line per run; exit code 1 if a run failed."""
    for name, value, least in (("--num-cpus", args.num_cpus, 1), ("--max-retries", args.max_retries, 0)):
        if value is not None and value < least:
            raise UsageError(f"{name} must be at least {least}, got {value}")
    if args.cpus_per_run <= 0:
        raise UsageError(f"--cpus-per-run must be positive, got {args.cpus_per_run}")
    options = args.train_options[1:] if args.train_options[:1] == ["--"] else args.train_options
    if args.spec is not None:
        if args.domains or args.w or options:
            raise UsageError("--spec holds the whole sweep: no --domains, --w or train options beside it")
        specs = read_spec(args.spec)
    elif not args.domains:
        raise UsageError("give --domains (and --algos, --seeds, --w) or a --spec file")
    else:
        specs = grid(args.domains, args.algos, args.seeds, args.w, options)
    outcomes = run_sweep(
        specs, args.out, args.address, args.num_cpus, args.cpus_per_run, args.max_retries, not args.no_progress,
        shared_filesystem=not args.no_shared_filesystem,
    )  # fmt: skip
    print(_table(outcomes))
    interrupted = sum(outcome.status == "interrupted" for outcome in outcomes)
    if interrupted:
        raise TrainingStopped(
            f"interrupted: {interrupted} run(s) did not end (their checkpoints are intact); run the same sweep again "
            "to continue them (finished runs are skipped)"
        )
    return 1 if any(outcome.status == "failed" for outcome in outcomes) else 0


def _table(outcomes: list[RunOutcome]) -> str:
    """One markdown row per run: status, attempts, iterations, |Π|, final mean w·return, wall time."""
    lines = [
        "| run | status | attempts | iterations | |Π| | mean w·return (discounted) | wall time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for outcome in outcomes:
        row = outcome.summary
        cells = [row.get("iteration", ""), row.get("n_policies", ""), row.get("mean_return", ""), row.get("wall_time")]
        if cells[2]:
            cells[2] = f"{float(cells[2]):.4f}"
        cells[3] = f"{float(cells[3]):.0f}" if cells[3] else ""
        status = outcome.status + (f": {outcome.error}" if outcome.error else "")
        lines.append(
            f"| {outcome.spec.run_name} | {status} | {outcome.attempts} | " + " | ".join(map(str, cells)) + " |"
        )
    return "\n".join(lines)

"""``sb3-sfgpi plot``: GPI's return over iterations from run directories, or a comparison file's figures."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi import plots
from sb3_sfgpi.cli.compare import COMPARE_FORMAT, merge_comparisons
from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.common.serialization import read_json
from sb3_sfgpi.common.weights import same_weight
from sb3_sfgpi.run_directory import SUMMARY_FIELDS, RunDirectory

PLOT_KINDS = ("returns", "steps", "versus", "tradeoff")


def add_parser(sub: Any) -> None:
    """The ``plot`` sub-command's arguments."""
    plot = sub.add_parser(
        "plot",
        help="returns: GPI return over iterations, mean ± std over seeds (run directories); steps, versus, "
        "tradeoff: from a comparison file",
    )
    plot.add_argument(
        "run_dirs",
        type=Path,
        nargs="+",
        metavar="INPUT",
        help="run directories, or comparison files (several: one per training seed, drawn as mean ± std over the "
        "episodes of all)",
    )
    plot.add_argument(
        "-o", "--output", type=Path, required=True, help="PNG file (returns, tradeoff) or directory (steps, versus)"
    )
    plot.add_argument("--kind", choices=PLOT_KINDS, default="returns")
    plot.add_argument(
        "--smooth", type=int, default=10, help="steps, versus: moving average over this many steps (1: raw curves)"
    )
    metrics = [field for field in SUMMARY_FIELDS if field not in ("iteration", "timesteps", "wall_time", "eval_time")]
    plot.add_argument("--metric", default="mean_return", choices=metrics)
    plot.add_argument("--title", default=None)
    plot.add_argument(
        "--fixed",
        type=Path,
        nargs="+",
        default=[],
        metavar="RUN",
        help="returns: runs of `train --algo fixed`, one per test weight and seed; the mean over the weights of "
        "each learner's return at its own weight is drawn as the a-priori reference (mean ± std over seeds)",
    )
    plot.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="LABEL=VALUE",
        help="returns: a horizontal line at VALUE, e.g. 'exact optimum=1.3548' (repeat the option for more)",
    )


def run(args: argparse.Namespace) -> int:
    """Draw the figure(s) and print the files written."""
    _check_output(args.output, args.kind)
    written = _returns(args) if args.kind == "returns" else _from_comparison(args)
    for path in written:
        print(f"wrote {path}")
    return 0


def _check_output(output: Path, kind: str) -> None:
    """Write exactly where asked: a .png file (returns, tradeoff) or a directory (steps, versus) in a directory that
    exists."""
    if kind in ("returns", "tradeoff") and (output.suffix.lower() != ".png" or output.is_dir()):
        raise UsageError(f"-o {output}: --kind {kind} writes one .png file")
    if kind not in ("returns", "tradeoff") and output.exists() and not output.is_dir():
        raise UsageError(f"-o {output} is a file: --kind {kind} writes a directory of figures")
    if not output.parent.is_dir():
        raise UsageError(f"-o {output}: the directory {output.parent} does not exist")


def _returns(args: argparse.Namespace) -> list[Path]:
    runs = []
    for path in args.run_dirs:
        run_dir = RunDirectory(path)
        config = run_dir.read_config()
        if not run_dir.has_evaluations():
            raise UsageError(f"{path} has no evaluation yet")
        runs.append((config.get("algorithm", "run"), run_dir))
    references = [_reference(item) for item in args.reference]
    if args.fixed:
        if args.metric != "mean_return":
            raise UsageError(f"--fixed draws the a-priori learners' mean_return, not {args.metric}")
        references.insert(0, a_priori_reference(args.fixed))
    return [plots.plot_returns(runs, args.output, args.metric, args.title, references)]


def _reference(item: str) -> plots.Reference:
    label, _, value = item.rpartition("=")
    try:
        number = float(value)
    except ValueError:
        number = float("nan")
    if not label or not np.isfinite(number):
        raise UsageError(f"--reference expects LABEL=NUMBER, got {item!r}")
    return plots.Reference(label, number)


def a_priori_reference(paths: list[Path]) -> plots.Reference:
    """
    The learners trained a priori for each test weight: per seed, the mean over the fixed-weight runs of their
    last evaluation's ``w · discounted return`` at their own weight ``w`` (the test weight within 1e-3 of it, max-norm;
    mean over agents); mean ± std over seeds.

    :raises UsageError: a run that is not a fixed-weight run, or whose weight is not among its test weights
    """
    by_seed: dict[int, list[float]] = {}
    for path in paths:
        run_dir = RunDirectory(path)
        config = run_dir.read_config()
        if config.get("algorithm") != "fixed":
            raise UsageError(f"--fixed: {path} is not a run of `train --algo fixed`")
        by_seed.setdefault(int(config["seed"]), []).append(own_weight_return(run_dir)[1])
    means = [np.mean(values) for values in by_seed.values()]
    n = len(means)
    label = f"learners trained a priori ({len(paths)} runs, {n} seed{'s' * (n > 1)})"
    return plots.Reference(label, float(np.mean(means)), float(np.std(means)))


def own_weight_return(run_dir: RunDirectory) -> tuple[np.ndarray, float]:
    """
    A fixed-weight run's weight ``w`` and its last evaluation's ``w · discounted return`` there (the test weight
    within 1e-3 of ``w``, max-norm; mean over agents).

    :raises UsageError: the run has no evaluation, or none at its own weight
    """
    w = np.asarray(run_dir.read_config()["weights"], dtype=np.float64)
    if not run_dir.has_evaluations():
        raise UsageError(f"--fixed: {run_dir} has no evaluation yet")
    at_w = [vector for test_w, vector in final_test_returns(run_dir) if same_weight(test_w, w)]
    if not at_w:
        raise UsageError(f"--fixed: {run_dir} was not evaluated at its own weight {w.tolist()}")
    return w, float(w @ at_w[0])


def final_test_returns(run_dir: RunDirectory) -> list[tuple[np.ndarray, np.ndarray]]:
    """
    The run's last evaluation: every test weight with the discounted return vector there, mean over agents.

    :param run_dir: a run with at least one evaluation
    """
    return [
        (
            np.asarray(row["weights"], dtype=np.float64),
            np.mean([np.asarray(agent["discounted"], dtype=np.float64) for agent in row["agents"].values()], axis=0),
        )
        for row in run_dir.read_history()[-1]["test"]
    ]


def _from_comparison(args: argparse.Namespace) -> list[Path]:
    compares = []
    for path in args.run_dirs:
        compare = read_json(path, "comparison") if path.is_file() else None
        if not isinstance(compare, dict) or compare.get("format") != COMPARE_FORMAT:
            raise UsageError(f"{path} is not a comparison file (written by sb3-sfgpi compare)")
        compares.append(compare)
    try:
        compare = merge_comparisons(compares) if len(compares) > 1 else compares[0]
    except (KeyError, TypeError, ValueError) as error:
        raise UsageError(f"cannot draw {', '.join(map(str, args.run_dirs))} together: {error}") from error
    if args.smooth < 1:
        raise UsageError(f"--smooth must be positive, got {args.smooth}")
    draw: dict[str, Callable[[dict[str, Any], Path], Any]] = {
        "steps": lambda c, o: plots.plot_step_metrics(c, o, smooth=args.smooth),
        "versus": lambda c, o: plots.plot_versus(c, o, smooth=args.smooth),
        "tradeoff": plots.plot_tradeoff,
    }
    result = draw[args.kind](compare, args.output)
    return result if isinstance(result, list) else [result]

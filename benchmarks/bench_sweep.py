"""Sweeps on a local Ray vs a plain loop: 8 tiny Four-Room runs; and the Fig. 4 runs (``run_fig4``).

The loop trains the runs one after another in this process (:func:`~sb3_sfgpi.cli.sweep_runner.train_run`, what a
sweep's task does); the sweep starts a local Ray with the machine's cores, runs them as tasks and shuts Ray down. The
runs are small (a few seconds each), so the ratio shows the sweep's overhead (starting Ray and a worker process per
run) against its parallelism.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from benchmarks._common import Row
from sb3_sfgpi.cli.sweep_runner import RunSpec, grid, run_sweep, train_run

#: About 3 s per run on one core: short episodes, two small iterations, two test weights, no validation.
TINY = ("--env", "max_steps=30", "--iterations", "2", "--steps-per-iteration", "1000",
        "--set", "n_test_weights=2", "--set", "validation_weights=0")  # fmt: skip


def run(quick: bool = False) -> list[Row]:
    """Wall time of 8 tiny runs (4 with --quick): a sweep on a local Ray vs one after another in this process."""
    try:
        import ray
    except ImportError:
        return [Row("sweep", "8 tiny Four-Room runs", "skipped: ray is not installed")]
    specs = grid(["four-room"], ["ma-sfols", "random"], range(2 if quick else 4), options=TINY)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        for spec in specs:
            train_run(spec, Path(tmp) / "loop" / spec.run_name)
        loop = time.perf_counter() - start
        start = time.perf_counter()
        run_sweep(specs, Path(tmp) / "sweep", num_cpus=os.cpu_count(), progress_bar=False)
        ray.shutdown()
        sweep = time.perf_counter() - start
    return [
        Row(
            "sweep",
            f"{len(specs)} tiny Four-Room runs: local Ray ({os.cpu_count()} CPUs) vs a loop in one process",
            f"{sweep:.1f} s",
            f"{loop:.1f} s",
            loop / sweep,
            "",
            None,
            f"one measurement each; the sweep's time includes starting and stopping Ray ({loop / len(specs):.1f} s "
            "per run in the loop)",
        )
    ]


def _train_command(spec: RunSpec, run_dir: Path) -> list[str]:
    return [sys.executable, "-m", "sb3_sfgpi.cli", *spec.train_argv(run_dir, resume=False)]


def run_fig4(quick: bool = False) -> list[Row]:
    """
    The Fig. 4 sweep (MA-SFOLS and Random + GPI, seeds 0-2) with a reduced budget: on a local Ray with the machine's
    cores, one run after another, and two at a time as ``examples/four_room.py`` did before the sweep.
    """
    steps = 5000 if quick else 25000
    budget = ("--iterations", "2", "--steps-per-iteration", str(steps))
    return _fig4(budget, f"2 × {steps:,} joint steps", ("one after another", "two at a time"))


def run_fig4_preset(quick: bool = False) -> list[Row]:
    """
    The Fig. 4 sweep with the ``four-room`` preset's budget (10 iterations of 50,000 joint steps per run; about
    50 minutes on 2 cores): on a local Ray against one run after another (``--quick``: the reduced budget's runs).
    """
    if quick:
        budget = ("--iterations", "2", "--steps-per-iteration", "5000")
        return _fig4(budget, "2 × 5,000 joint steps", ("one after another",))
    return _fig4((), "the preset's 10 × 50,000 joint steps", ("one after another",))


def _fig4(budget: tuple[str, ...], described: str, baselines: tuple[str, ...]) -> list[Row]:
    """The six Fig. 4 runs with the ``train`` options ``budget``: as a sweep and in each of the ``baselines``."""
    try:
        import ray
    except ImportError:
        return [Row("sweep", "Fig. 4 runs", "skipped: ray is not installed")]
    specs = grid(["four-room"], ["ma-sfols", "random"], range(3), options=budget)
    parallel = {"one after another": 1, "two at a time": 2}
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        for baseline in baselines:
            start = time.perf_counter()
            with ThreadPoolExecutor(parallel[baseline]) as pool:
                commands = [_train_command(spec, Path(tmp) / baseline / spec.run_name) for spec in specs]
                list(pool.map(lambda command: subprocess.run(command, check=True, capture_output=True), commands))
            times[baseline] = time.perf_counter() - start
        start = time.perf_counter()
        run_sweep(specs, Path(tmp) / "sweep", num_cpus=os.cpu_count(), progress_bar=False)
        ray.shutdown()
        times["sweep"] = time.perf_counter() - start
    case = f"6 Fig. 4 runs of {described}: local Ray ({os.cpu_count()} CPUs)"
    return [
        Row(
            "sweep",
            f"{case} vs {baseline}",
            f"{times['sweep']:.0f} s",
            f"{times[baseline]:.0f} s",
            times[baseline] / times["sweep"],
            "≥ 1.82× (≤ 0.55 of the time)" if baseline == "one after another" else "",
            times[baseline] / times["sweep"] >= 1 / 0.55 if baseline == "one after another" else None,
            "one measurement each, the sweep's time includes starting and stopping Ray",
        )
        for baseline in baselines
    ]

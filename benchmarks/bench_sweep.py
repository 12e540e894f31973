"""Sweeps on a local Ray vs a plain loop: 8 tiny Four-Room runs.

The loop trains the runs one after another in this process (:func:`~sb3_sfgpi.sweep.train_run`, what a sweep's task
does); the sweep starts a local Ray with the machine's cores, runs them as tasks and shuts Ray down. The runs are
small (a few seconds each), so the ratio shows the sweep's overhead (starting Ray and a worker process per run)
against its parallelism.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from benchmarks._common import Row
from sb3_sfgpi.sweep import grid, run_sweep, train_run

#: About 3 s per run on one core: short episodes, two small iterations, two test weights, no validation.
TINY = ("--env", "max_steps=30", "--iterations", "2", "--steps-per-iteration", "1000", "--n-test-weights", "2",
        "--validation-weights", "0")  # fmt: skip


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

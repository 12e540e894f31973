"""Run the benchmarks and print one markdown table.

    python -m benchmarks                 # everything (about 26 minutes on 2 cores, 13 of them sweep-fig4)
    python -m benchmarks --quick         # shorter runs
    python -m benchmarks gpi ols         # some: gpi training planning ols traffic memory optimum sharing
                                         # copies ray-eval startup admission tabular tabular-peer sweep
                                         # sweep-fig4, and sweep-fig4-preset,
                                         # known-fronts, deep-fronts, momaland, deep-peer (only when named)
    python -m benchmarks --output results.md
    python -m benchmarks known-fronts --seeds 0 1 2 --envs deep-sea-treasure resource-gathering fruit-tree
    python -m benchmarks deep-fronts --seeds 0 1 2        # minecart(-deterministic), lunar lander: 15 × 10,000 steps
    python -m benchmarks momaland --seeds 0 1 2           # item gathering against MOMAland's GPI-LS (15 × 10,000)
    python -m benchmarks deep-fronts --runs runs/bench    # our runs in runs/bench; run it again to resume them

Every row compares a candidate with a baseline measured in the same process, interleaved, with medians over
repeats; the ratio is candidate speed / baseline speed (or baseline bytes / candidate bytes for memory),
so > 1 means the candidate is better. The known-fronts rows measure learning instead: expected utility of GPI
against the exact optimum (EU/EU*) on MO-Gymnasium problems, per seed; ``--seeds``, ``--envs`` and ``--peer-steps``
go to the benchmarks that take them.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import inspect
import os
import platform
import sys
import time
import traceback
from pathlib import Path

from benchmarks._common import Row, single_thread_torch
from sb3_sfgpi.common.cpu_arithmetic import mkl_code_path
from sb3_sfgpi.common.software import DISTRIBUTIONS, cpu_model, software_versions

BENCHMARKS = {
    "gpi": "benchmarks.bench_gpi",
    "training": "benchmarks.bench_training",
    "planning": "benchmarks.bench_planning",
    "ols": "benchmarks.bench_ols",
    "traffic": "benchmarks.bench_traffic",
    "memory": "benchmarks.bench_memory",
    "optimum": "benchmarks.bench_optimum",
    "sharing": "benchmarks.bench_sharing",
    "sweep": "benchmarks.bench_sweep",
    "copies": "benchmarks.bench_copies",
    "ray-eval": "benchmarks.bench_ray_eval",
    "startup": "benchmarks.bench_startup",
    "admission": "benchmarks.bench_admission",
    "tabular": "benchmarks.bench_tabular",
    "tabular-peer": "benchmarks.bench_tabular_peer",
    "deep-peer": "benchmarks.bench_deep_peer",
    "sweep-fig4": "benchmarks.bench_sweep:run_fig4",
    "sweep-fig4-preset": "benchmarks.bench_sweep:run_fig4_preset",
    "known-fronts": "benchmarks.bench_known_fronts",
    "deep-fronts": "benchmarks.bench_known_fronts:run_deep",
    "momaland": "benchmarks.bench_momaland",
}
#: Run only when named (each takes many minutes on 2 cores), not in the default "everything".
ON_REQUEST = ("sweep-fig4-preset", "known-fronts", "deep-fronts", "momaland", "deep-peer")


def _gpu() -> str:
    """The CUDA card the deep learners use by default (``device="auto"``), or none."""
    import torch

    if not torch.cuda.is_available():
        return "none (the deep learners run on the CPU)"
    return f"{torch.cuda.get_device_name(0)} (CUDA {torch.version.cuda}; the deep learners' device='auto')"


def _versions() -> str:
    """The versions of what the numbers depend on (:func:`~sb3_sfgpi.common.software.software_versions`)."""
    versions = software_versions()
    return ", ".join(f"{name} {versions[name]}" for name in ("python", *DISTRIBUTIONS) if name in versions)


def header(argv: list[str]) -> str:
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    gpu = _gpu()  # imports torch, whose MKL the machine's line names
    return "\n".join(
        [
            f"- Machine: {cpu_model()}, {os.cpu_count()} logical cores ({platform.system()} {platform.release()}), "
            f"load average at start {load}; torch limited to 1 thread, its MKL code path {mkl_code_path() or 'none'}",
            f"- GPU: {gpu}",
            f"- Versions: {_versions()}",
            f"- Date: {datetime.date.today().isoformat()}",
            f"- Command: `python -m benchmarks{' ' + ' '.join(argv) if argv else ''}`",
        ]
    )


def markdown(rows: list[Row]) -> str:
    lines = [
        "| Benchmark | Case | Candidate | Baseline | Ratio | Target | Notes |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        ratio = "" if row.ratio is None else f"{row.ratio:.2f}×"
        target = row.target
        if row.met is not None:
            target = f"{target} {'✓' if row.met else '✗'}".strip()
        cells = [row.benchmark, row.case, row.candidate, row.baseline, ratio, target, row.note]
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n\n")[0])
    default = f"all but {', '.join(ON_REQUEST)}"
    parser.add_argument("names", nargs="*", choices=[*BENCHMARKS, []], help=f"benchmarks to run (default: {default})")
    parser.add_argument("--quick", action="store_true", help="shorter runs")
    parser.add_argument("--output", type=Path, help="also write the markdown (header + table) to this file")
    parser.add_argument("--seeds", type=int, nargs="+", help="seeds of the benchmarks that train (known-fronts)")
    parser.add_argument("--envs", nargs="+", help="envs of the benchmarks that take some (known-fronts)")
    parser.add_argument("--peer-steps", type=int, help="env steps of the morl-baselines peers (default: ours)")
    parser.add_argument("--peer-updates", type=int, help="gradient updates per step of momaland's peer (default: 10)")
    parser.add_argument(
        "--runs", type=Path, help="known-fronts, deep-fronts, momaland: our runs' directories and GPI-LS's checkpoints "
        "go here, one per problem and seed, and a run found there goes on from its last checkpoint (an interrupted "
        "benchmark resumes)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    given = (
        ("seeds", args.seeds),
        ("envs", args.envs),
        ("peer_steps", args.peer_steps),
        ("peer_updates", args.peer_updates),
        ("runs", args.runs),
    )
    options = {key: value for key, value in given if value is not None}
    single_thread_torch()
    names = args.names or [name for name in BENCHMARKS if name not in ON_REQUEST]
    rows: list[Row] = []
    failed = False
    start = time.perf_counter()
    for name in names:
        print(f"[benchmarks] {name} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            module, _, function = BENCHMARKS[name].partition(":")  # "module" runs module.run
            run = getattr(importlib.import_module(module), function or "run")
            taken = {key: value for key, value in options.items() if key in inspect.signature(run).parameters}
            rows.extend(run(quick=args.quick, **taken))
        except Exception:  # noqa: BLE001 - report and go on with the other benchmarks
            failed = True
            traceback.print_exc()
            rows.append(Row(name, "failed", "see the traceback above"))
        print(f"[benchmarks] {name} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    text = f"{header(argv)}\n- Wall time: {time.perf_counter() - start:.0f} s\n\n{markdown(rows)}\n"
    print(text)
    if args.output is not None:
        args.output.write_text(text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Shared helpers of the benchmarks: interleaved timing with medians, result rows, formatting.

The machine the benchmarks run on may be shared, so absolute times drift from run to run. Only ratios
measured side by side mean something: every comparison here runs its candidate and its baseline in the same
process, alternately (``interleaved``), several times, and reports medians.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: The repository (the candidate's source tree).
ROOT = Path(__file__).resolve().parent.parent
#: The row of a comparison whose morl-baselines peer is not installed (an optional extra, never a runtime dependency).
MORL_MISSING = 'morl-baselines not installed: pip install "sb3-sfgpi[morl]"'


@dataclass
class Row:
    """
    One line of the results table.

    :param benchmark: which question (``"GPI predict"``, ``"training"``, ...)
    :param case: the configuration (``"MLP |Π|=64 batch=1"``)
    :param candidate: the measured value of the code under test, formatted with its unit
    :param baseline: the value of the baseline, formatted, or ``""``
    :param ratio: candidate speed / baseline speed (> 1: the candidate is faster), or None
    :param target: the target ratio as text (``"≥ 5×"``), or ``""``
    :param met: whether the target holds (None: no target)
    :param note: anything else worth a column (before/after, caveats)
    """

    benchmark: str
    case: str
    candidate: str
    baseline: str = ""
    ratio: float | None = None
    target: str = ""
    met: bool | None = None
    note: str = ""


def interleaved_samples(
    functions: dict[str, Callable[[], Any]],
    repeats: int,
    number: int = 1,
    warmup: int = 1,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, list[float]]:
    """
    Seconds per call of each function, timed alternately (A B C, B C A, ...) in ``repeats`` rounds.

    :param functions: name -> function without arguments
    :param repeats: how many rounds (samples of each function)
    :param number: calls per sample (the sample is their mean)
    :param warmup: untimed calls of each function first
    :param clock: what a second is read from: wall time (default) or ``time.process_time`` (this process's CPU)
    :return: name -> one sample per round, in round order
    """
    names = list(functions)
    for name in names:
        for _ in range(warmup):
            functions[name]()
    samples: dict[str, list[float]] = {name: [] for name in names}
    for r in range(repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for name in order:
            fn = functions[name]
            start = clock()
            for _ in range(number):
                fn()
            samples[name].append((clock() - start) / number)
    return samples


def interleaved(
    functions: dict[str, Callable[[], Any]], repeats: int, number: int = 1, warmup: int = 1
) -> dict[str, float]:
    """Median seconds per call of each function over interleaved rounds (see :func:`interleaved_samples`)."""
    samples = interleaved_samples(functions, repeats, number, warmup)
    return {name: statistics.median(values) for name, values in samples.items()}


def paired_ratio(samples: dict[str, list[float]], slow: str, fast: str) -> tuple[float, float, float]:
    """
    ``slow / fast`` time ratio per round (both timed in the same round), as (median, first quartile, third quartile).

    Pairing by round cancels slow drifts of a shared machine's load better than a ratio of medians.
    """
    ratios = sorted(a / b for a, b in zip(samples[slow], samples[fast], strict=True))
    if len(ratios) == 1:
        return ratios[0], ratios[0], ratios[0]
    q1, _, q3 = statistics.quantiles(ratios, n=4, method="inclusive")
    return statistics.median(ratios), q1, q3


def baseline_tree(into: Path, commit: str) -> bool:
    """
    The source of ``commit`` of this repository (``git archive``) extracted into ``into``, for a baseline run with
    ``PYTHONPATH=into``; False where it cannot be read (no git, a shallow clone).
    """
    try:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    except (OSError, subprocess.CalledProcessError):
        return False
    return (into / "sb3_sfgpi" / "__init__.py").is_file()


def calls_for(fn: Callable[[], Any], seconds: float, cap: int = 100_000) -> int:
    """How many calls of ``fn`` take about ``seconds`` (at least 1), from one timed call after a warm-up call."""
    fn()
    start = time.perf_counter()
    fn()
    once = max(time.perf_counter() - start, 1e-7)
    return max(1, min(cap, int(seconds / once)))


def fmt_time(seconds: float) -> str:
    """``12.3 µs`` / ``4.56 ms`` / ``1.23 s``."""
    if seconds < 1e-3:
        return f"{seconds * 1e6:.1f} µs"
    if seconds < 1.0:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def fmt_rate(per_second: float, unit: str) -> str:
    """``12,345 steps/s``."""
    return f"{per_second:,.0f} {unit}/s" if per_second >= 100 else f"{per_second:.2f} {unit}/s"


def fmt_bytes(n: float) -> str:
    """``12.3 MB`` (10^6 bytes)."""
    if abs(n) >= 1e6:
        return f"{n / 1e6:.1f} MB"
    return f"{n / 1e3:.1f} kB"


def rss_bytes() -> int:
    """Resident set size of this process (Linux ``/proc``; falls back to ``ru_maxrss`` elsewhere)."""
    try:
        with open(f"/proc/{os.getpid()}/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def single_thread_torch() -> None:
    """One torch thread: the networks are small and the machine may be shared (same setting for every side)."""
    import torch as th

    th.set_num_threads(1)

"""The exact optimum of single-agent ``four-room-v0`` (``sfgpi_envs.four_room_optimum``), γ = 0.95.

* **Value per weight**: ``FourRoomOptimum.value(w)`` (the backward pass over the collected sets, on distances built
  once) for fresh random weights, against brute-force value iteration over all 169 · 4096 states (cell, collected
  set) with MO-Gymnasium's transitions (``tests/four_room_reference.py``; its sweeps stop at the exact fixed
  point). Both give the same start value (checked).
* **Exact CCS**: OLS with the exact oracle until its queue is empty: the CCS size and the number of OLS iterations a
  perfect learner would need, and the exact optimal mean of ``w · V*`` over the 12 test weights of
  ``examples/sfols_four_room.py`` (the quality reference of its GPI curve).
* **Rounds of two weights** (two agents, as MA-SFOLS hands them out): with the exact oracle, the best value over the
  policies found, as a fraction of the optimum (mean over the 12 test weights), after each of the first 8 rounds, for
  ``OLSSchedule(batch="top")`` (Algorithm 1) and ``batch="same-after-extrema"``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from mo_gymnasium.envs.four_room.four_room import MAZE
from sfgpi_envs.four_room_optimum import FourRoomOptimum

from benchmarks._common import Row, fmt_time, interleaved_samples
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.schedules import OLS_BATCHES, OLSSchedule

NAME = "optimum"
GAMMA = 0.95
START = 12 * 13  # the start cell (12, 0) as a flat index
ROUNDS = 8


def _reference():
    tests = str(Path(__file__).resolve().parents[1] / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    import four_room_reference

    return four_room_reference


def run(quick: bool = False) -> list[Row]:
    reference = _reference()
    start = time.perf_counter()
    optimum = FourRoomOptimum(gamma=GAMMA)
    build = time.perf_counter() - start
    per_call, repeats = 20, 2 if quick else 5
    rng = np.random.default_rng(0)
    w = np.array([0.2, 0.5, 0.3])
    samples = interleaved_samples(
        {
            "candidate": lambda: [optimum.value(u) for u in rng.dirichlet(np.ones(3), size=per_call)],
            "baseline": lambda: reference.value_iteration(MAZE, w, GAMMA),
        },
        repeats=repeats,
        warmup=0,
    )
    candidate, baseline = np.median(samples["candidate"]) / per_call, np.median(samples["baseline"])
    gap = abs(reference.value_iteration(MAZE, w, GAMMA)[1][START, 0] - optimum.value(w))
    assert gap <= 1e-12, gap

    start = time.perf_counter()
    ccs, iterations = reference.exact_ccs(optimum)
    ols_time = time.perf_counter() - start
    test_weights = random_weights(3, 12, rng=0)  # the example's draw: default_rng(0).dirichlet(ones(3), size=12)
    optimal = np.array([optimum.value(u) for u in test_weights])
    mean = optimal.mean()
    rounds = {batch: _rounds_of_two(optimum, batch, test_weights, optimal) for batch in OLS_BATCHES}
    return [
        Row(
            "four-room optimum",
            "value per weight (w·V* at the start, exact)",
            fmt_time(candidate),
            fmt_time(baseline),
            baseline / candidate,
            note=f"distances built once in {fmt_time(build)}; baseline: value iteration over all 692,224 states; "
            f"same start value (|Δ| = {gap:.0e})",
        ),
        Row(
            "four-room optimum",
            "exact CCS (OLS + exact oracle)",
            f"|CCS| = {len(ccs)}, {iterations} OLS iterations",
            note=f"{fmt_time(ols_time)}; exact mean w·V* over the example's 12 test weights: {mean:.4f}",
        ),
        *(
            Row(
                "four-room optimum",
                f"OLS rounds of 2 weights (batch={batch}), exact oracle: best found / optimum after rounds 1-{ROUNDS}",
                " ".join(f"{x:.3f}" for x in fractions),
                note="mean over the example's 12 test weights",
            )
            for batch, fractions in rounds.items()
        ),
    ]


def _rounds_of_two(optimum: FourRoomOptimum, batch: str, test_weights: np.ndarray, optimal: np.ndarray) -> list[float]:
    """After each round of two weights solved exactly: max over the values found of w·V, / w·V* (``optimal``), mean
    over the test weights."""
    schedule = OLSSchedule(batch)
    schedule.start(3)
    rng, fractions = np.random.default_rng(0), []
    for _ in range(ROUNDS):
        for w in schedule.next_weights(["agent_0", "agent_1"], rng).values():
            schedule.add(optimum.vector_value(w), w)
        fractions.append(float(np.mean(np.max(test_weights @ np.array(schedule.ols.values).T, axis=1) / optimal)))
    return fractions

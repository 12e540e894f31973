"""OLS: corner weights against the brute-force enumeration of ``tests/ols_reference.py``, and the whole OLS step.

Value sets: ``n`` points on the positive orthant of the unit sphere in ``d`` dimensions (seeded). Every such point
is the unique best value for the weight along it, so all ``n`` are in the CCS (``|CCS| = n``).

* **Corner weights**: ``OLS.corner_weights()`` (Qhull halfspace intersection, then deduplication) vs
  ``brute_force_corner_weights`` (one linear solve per ``d``-subset of the ``n + d`` hyperplanes:
  ``C(n + d, d)`` solves). Both give the same corners (checked when both run). The brute force is not run when
  its estimated time (``C(n + d, d)`` times the measured time per subset) exceeds the budget; the table then
  gives the estimate.
* **OLS step**: one ``OLS.add_solution`` (corner weights, optimistic priority LPs of the new corners, coverage
  LPs of the new value and of the CCS members whose witness weight it beats) for a new CCS value, the OLS
  already holding the ``n`` values and their ``n`` visited weights: the cost of one MA-SFOLS iteration's
  bookkeeping at that size, with the time of each part.
"""

from __future__ import annotations

import copy
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import HalfspaceIntersection

from benchmarks._common import Row, fmt_time
from sb3_sfgpi import ols as ols_module
from sb3_sfgpi.ols import OLS

NAME = "ols"
TOL = 1e-6


def _brute_force():
    tests = str(Path(__file__).resolve().parents[1] / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    from ols_reference import brute_force_corner_weights

    return brute_force_corner_weights


def sphere_values(n: int, d: int, seed: int = 0) -> np.ndarray:
    """``n`` points of the positive orthant of the unit sphere: all of them in the CCS."""
    g = np.abs(np.random.default_rng(seed).normal(size=(n, d))) + 1e-3
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def qhull_vertices(values: np.ndarray) -> int:
    """How many vertices Qhull hands to the deduplication (the same halfspaces as ``ols._corner_weights``)."""
    n, d = values.shape
    scaled = (values - values.min()) / (values.max() - values.min())
    last = scaled[:, -1:]
    cap = ols_module._CAP
    halfspaces = np.vstack(
        [
            np.hstack([scaled[:, :-1] - last, -np.ones((n, 1)), last]),
            np.hstack([-np.eye(d - 1), np.zeros((d - 1, 2))]),
            np.concatenate([np.ones(d - 1), [0.0, -1.0]]),
            np.concatenate([np.zeros(d - 1), [1.0, -cap]]),
        ]
    )
    center = np.full(d, 1.0 / d)
    interior = np.append(center[:-1], (np.max(scaled @ center) + cap) / 2)
    vertices = HalfspaceIntersection(halfspaces, interior).intersections
    return int(np.sum(vertices[:, -1] < (1.0 + cap) / 2))


def _time(fn, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return float(np.median(samples))


def _timed(method, spent: dict[str, float], name: str):
    def timed(*args, **kwargs):
        start = time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            spent[name] += time.perf_counter() - start

    return timed


def run(quick: bool = False) -> list[Row]:
    """Corner weights against the brute force, then the whole OLS step, for d in (2, 3, 4, 6) and |CCS| up to 500."""
    brute_force = _brute_force()
    # Brute force: seconds per d-subset, measured on a small case.
    small = sphere_values(8, 3)
    per_subset = _time(lambda: brute_force(small, TOL), 3) / math.comb(8 + 3, 3)
    sizes = [(d, n) for d in (2, 3, 4, 6) for n in (10, 100, 500)]
    corner_rows = [_corner_weights_row(d, n, brute_force, per_subset, quick) for d, n in sizes]
    return corner_rows + [_step_row(d, n, quick) for d, n in sizes]


def _corner_weights_row(d: int, n: int, brute_force, per_subset: float, quick: bool) -> Row:
    """OLS's corner weights of n values against the brute force (run when its estimate fits the budget)."""
    budget, repeats = (2.0, 3) if quick else (60.0, 5)
    values = sphere_values(n, d)
    m = qhull_vertices(values)
    ols = OLS(d, tolerance=TOL)
    ols._values = list(values)  # the corner weights depend on the values only
    subsets = math.comb(n + d, d)
    estimate_bf = subsets * per_subset
    run_bf = estimate_bf <= budget
    t_ols = _time(ols.corner_weights, repeats)
    t_bf = _time(lambda v=values: brute_force(v, TOL), 1) if run_bf else estimate_bf
    corners = len(ols.corner_weights())
    agree = ""
    if run_bf:
        # Every corner OLS finds is one of the brute force's; the brute force also keeps intersections
        # within its feasibility slack (1e-6) below the surface, hence sometimes a few more points.
        found, expected = np.array(ols.corner_weights()), brute_force(values, TOL)
        gaps = [np.min(np.max(np.abs(expected - w), axis=1)) for w in found]
        assert max(gaps) <= 1e-5, (d, n, max(gaps))
        agree = f"all {len(found)} in the brute force's {len(expected)}; "
    t_qhull = _time(lambda v=values: qhull_vertices(v), repeats)
    notes = [f"{agree}{corners} corners, {m} Qhull vertices; Qhull alone {fmt_time(t_qhull)}"]
    if not run_bf:
        notes.append(f"brute force not run: C({n + d},{d}) = {subsets:.3g} solves")
    return Row(
        "OLS corner weights",
        f"d={d} |CCS|={n}",
        fmt_time(t_ols),
        fmt_time(t_bf) + ("" if run_bf else " (estimated)"),
        t_bf / t_ols if run_bf else None,
        "",
        None,
        "; ".join(notes),
    )


def _step_row(d: int, n: int, quick: bool) -> Row:
    """The whole OLS step that adds a value to n others, with the time of its three parts."""
    values = sphere_values(n + 1, d, seed=d)
    base = OLS.from_state_dict(  # n values, their n weights visited, nothing queued (CCS LPs not timed)
        {
            "reward_dim": d,
            "tolerance": TOL,
            "values": values[:n].tolist(),
            "weights": (values[:n] / values[:n].sum(axis=1, keepdims=True)).tolist(),
            "queue": [],
        }
    )
    new_value, new_weight = values[n], values[n] / values[n].sum()
    samples: list[float] = []
    parts: dict[str, list[float]] = {"corner_weights": [], "_priority": [], "_witness": []}
    for _ in range(1 if quick or n >= 500 else 3):
        ols = copy.deepcopy(base)
        spent = {name: 0.0 for name in parts}
        for name in parts:  # time the three parts inside the step (instance attributes shadow the methods)
            setattr(ols, name, _timed(getattr(ols, name), spent, name))
        start = time.perf_counter()
        ols.add_solution(new_value, new_weight)
        samples.append(time.perf_counter() - start)
        for name in parts:
            parts[name].append(spent[name])
    step = float(np.median(samples))
    share = {name: float(np.median(times)) for name, times in parts.items()}
    rest = max(step - sum(share.values()), 0.0)
    return Row(
        "OLS step",
        f"d={d} |CCS|={n}",
        f"{fmt_time(step)}/iteration",
        note=f"corner weights {fmt_time(share['corner_weights'])}, priority LPs "
        f"{fmt_time(share['_priority'])}, CCS LPs {fmt_time(share['_witness'])}, "
        f"rest {fmt_time(rest)}; {len(ols.queue)} corners queued",
    )

"""Tabular SFDQN against morl-baselines' tabular MO Q-learning: steps per CPU-second at equal TD updates per step.

morl-baselines' MPMOQLearning (the known-fronts peer on tabular problems) trains one ``MOQLearning`` per weight. Its
step is ε-greedy acting, one Q-learning update on the step's own transition and, with Dyna, ``dyna_updates`` more
on transitions drawn from its learned model. Ours is the paper's tabular SFDQN: one TD update of a replay batch per
step. Two pairs at equal TD updates per env step, on MO-Gymnasium's ``four-room-v0`` seen as "xy" cells, weights
(0.5, 0.3, 0.2), α 0.1, γ 0.95, constant ε 0.1 (both sides' defaults for it):

* **32 per step**: SFDQN with the paper's batch of 32 against MOQLearning with Dyna and 31 model updates;
* **1 per step**: SFDQN with a batch of 1 against MOQLearning without Dyna (its plain online update).

Each learner is timed in interleaved chunks of steps, in CPU seconds of this process (``time.process_time``); the
ratio is the median of the paired per-chunk ratios. morl-baselines is optional (``pip install "sb3-sfgpi[morl]"``):
without it, one row says so.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from benchmarks._common import MORL_MISSING, Row, fmt_rate, paired_ratio
from benchmarks.bench_training import TABULAR_KWARGS, WEIGHTS, _silent, chunked_interleaved
from benchmarks.envs import four_room
from sb3_sfgpi import SFDQN

NAME = "tabular peer"
#: TD updates per env step of each pair: (SFDQN's batch size, MOQLearning's Dyna updates after its own).
PAIRS = {32: (32, 31), 1: (1, 0)}

Advance = Callable[[int], None]


def run(quick: bool = False) -> list[Row]:
    """One row per number of TD updates per step: SFDQN's steps per CPU-second against MOQLearning's."""
    try:
        from morl_baselines.single_policy.ser.mo_q_learning import MOQLearning
    except ImportError:
        return [Row(NAME, "tabular SFDQN vs morl-baselines MOQLearning", MORL_MISSING)]
    repeats, chunk = (5, 500) if quick else (7, 2_000)
    makers: dict[str, Callable[[], Advance]] = {}
    for updates, (batch_size, dyna_updates) in PAIRS.items():
        makers[f"ours {updates}"] = lambda b=batch_size: _sfdqn(b)
        makers[f"peer {updates}"] = lambda n=dyna_updates: _moq_learning(MOQLearning, n)
    samples = chunked_interleaved(makers, chunk, repeats, clock=time.process_time)
    return [_row(samples, updates, chunk, repeats) for updates in PAIRS]


def _sfdqn(batch_size: int) -> Advance:
    """The paper's tabular SFDQN with ``batch_size``; ``advance(n)`` trains it ``n`` more steps."""
    kwargs = {**TABULAR_KWARGS, "batch_size": batch_size}
    model = _silent(SFDQN("TabularPolicy", four_room(xy=True), weights=WEIGHTS, seed=0, **kwargs))
    return lambda n: model.learn(n, reset_num_timesteps=False)


def _moq_learning(algorithm: type, dyna_updates: int) -> Advance:
    """morl-baselines' MOQLearning with the same α, γ and ε (Dyna where ``dyna_updates`` > 0), no logging."""
    agent = algorithm(
        four_room(xy=True), weights=WEIGHTS, learning_rate=TABULAR_KWARGS["learning_rate"],
        gamma=TABULAR_KWARGS["gamma"], initial_epsilon=TABULAR_KWARGS["exploration_final_eps"],
        final_epsilon=TABULAR_KWARGS["exploration_final_eps"], dyna=dyna_updates > 0, dyna_updates=dyna_updates,
        log=False, seed=0,
    )  # fmt: skip
    return lambda n: agent.train(start_time=time.time(), total_timesteps=n, reset_num_timesteps=agent.global_step == 0)


def _row(samples: dict[str, list[float]], updates: int, chunk: int, repeats: int) -> Row:
    ours, peer = f"ours {updates}", f"peer {updates}"
    ratio, low, high = paired_ratio(samples, peer, ours)
    batch_size, dyna_updates = PAIRS[updates]
    peer_case = f"Dyna with {dyna_updates} model updates" if dyna_updates else "no Dyna"
    per_step = f"{updates} TD update{'s' * (updates > 1)} per step"
    return Row(
        NAME,
        f"{per_step}: SFDQN batch {batch_size} vs MOQLearning, {peer_case}; four-room xy",
        fmt_rate(chunk / float(np.median(samples[ours])), "steps") + " of CPU",
        fmt_rate(chunk / float(np.median(samples[peer])), "steps") + " of CPU",
        ratio,
        "≥ 1×",
        ratio >= 1,
        f"paired ratios {low:.2f}–{high:.2f} (quartiles); {repeats} interleaved chunks of {chunk} steps",
    )

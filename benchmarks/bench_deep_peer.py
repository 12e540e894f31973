"""The deep learner against morl-baselines' GPI-LS: env steps per CPU-second at equal gradient updates per step.

Ours is the deep preset's learner (:data:`~sb3_sfgpi.cli.gym_domains.MLP_LEARNER`: one weight-conditioned
ψ(s, a, w) with two heads of 3 × 128 units, prioritised replay, 3 gradient updates of a batch of 128 per env step);
the peer is the deep-fronts benchmark's GPI-LS (morl-baselines' ``GPIPD`` with
:data:`~benchmarks.bench_known_fronts.GPI_LS_SETTINGS`: two 4 × 256 networks conditioned on the weight, batch 128)
at the same 3 updates per step. Both train on minecart-v0 for the weight (0.5, 0.3, 0.2) and act by GPI over the same
support of 6 weights (GPI-LS redraws its weight from it every episode, as in its training), with the same ε
schedule; each side with its own published network, so the ratio is what a user's run of each costs per env step.

Each is trained untimed past :data:`WARMUP` steps first: GPI-LS makes one update per step until its
``dynamics_rollout_starts`` (5,000) and its ``gradient_updates`` after. Then both are timed in interleaved chunks of
steps, in CPU seconds of this process; the ratio is the median of the paired per-chunk ratios. Ours scores its whole
replay again at each ``learn()`` (a run does so once per iteration of 10,000 steps; here once per chunk), which the
ratio counts against it. Issue 57's goal is GPI-LS's quality in at most a fifth of its wall time: at equal env steps,
where ours is at least as good, that is a ratio of 5× or more. morl-baselines is optional (``pip install
"sb3-sfgpi[morl]"``): without it, one row says so.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from benchmarks._common import MORL_MISSING, Row, fmt_rate, paired_ratio
from benchmarks.bench_known_fronts import GPI_LS_SETTINGS, PROBLEMS, _learner_of, _make_env, drop_sampled_indices
from benchmarks.bench_training import _silent, chunked_interleaved
from sb3_sfgpi import SFDQN
from sb3_sfgpi.cli.gym_domains import MLP_LEARNER
from sb3_sfgpi.common.weights import random_weights

NAME = "deep peer"
MINECART = PROBLEMS["minecart"]
WEIGHTS = np.array([0.5, 0.3, 0.2])
#: The support both act over by GPI and draw their episodes' weights from: the weight and 5 Dirichlet(1) draws.
SUPPORT = np.vstack([WEIGHTS, random_weights(3, 5, rng=0)])
#: Untimed steps before the chunks: past GPI-LS's 5,000 steps of one update each.
WARMUP = 5_100
TARGET = 5.0

Advance = Callable[[int], None]


def run(quick: bool = False) -> list[Row]:
    """One row: our deep learner's env steps per CPU-second against GPI-LS's, both at 3 updates per step."""
    updates = MLP_LEARNER["gradient_steps"]
    case = f"{updates} gradient updates per step: the deep preset's learner vs morl-baselines GPI-LS; {MINECART.env_id}"
    try:
        from morl_baselines.multi_policy.gpi_pd.gpi_pd import GPIPD
    except ImportError:
        return [Row(NAME, case, MORL_MISSING)]
    repeats, chunk = (3, 300) if quick else (5, 2_000)
    makers = {"ours": _ours, "peer": lambda: _gpi_ls(GPIPD, updates)}
    samples = chunked_interleaved(makers, chunk, repeats, clock=time.process_time)
    ratio, low, high = paired_ratio(samples, "peer", "ours")
    return [
        Row(
            NAME, case, fmt_rate(chunk / float(np.median(samples["ours"])), "steps") + " of CPU",
            fmt_rate(chunk / float(np.median(samples["peer"])), "steps") + " of CPU", ratio, f"≥ {TARGET:g}×",
            ratio >= TARGET,
            f"paired ratios {low:.2f}–{high:.2f} (quartiles); {repeats} interleaved chunks of {chunk} steps after "
            f"{WARMUP:,} untimed; support of {len(SUPPORT)} weights",
        )
    ]  # fmt: skip


def _ours() -> Advance:
    """The deep preset's learner for :data:`WEIGHTS` over :data:`SUPPORT`, trained :data:`WARMUP` steps."""
    policy, kwargs = _learner_of(MINECART)
    model = _silent(SFDQN(policy, _make_env(MINECART), weights=WEIGHTS, seed=0, **kwargs))
    model.set_weight_support(SUPPORT)
    model.learn(WARMUP)
    return lambda n: model.learn(n, reset_num_timesteps=False)


def _gpi_ls(algorithm: type, updates: int) -> Advance:
    """GPI-LS at ``updates`` gradient updates per step for :data:`WEIGHTS` over :data:`SUPPORT`, trained
    :data:`WARMUP` steps; its weight redrawn from the support every episode, as in its own training."""
    agent = algorithm(
        _make_env(MINECART), gamma=MLP_LEARNER["gamma"], gradient_updates=updates, seed=0, log=False, device="cpu",
        **GPI_LS_SETTINGS,
    )  # fmt: skip
    drop_sampled_indices(agent)

    def advance(n: int) -> None:
        agent.train_iteration(n, weight=WEIGHTS, weight_support=list(SUPPORT), reset_num_timesteps=False)

    advance(WARMUP)
    return advance

"""Parameter sharing: one SFDQN fed by every agent vs one SFDQN per agent, on MOMAland's beach (100 agents).

Both runners train MLP SF learners with the same settings on the same env, in interleaved chunks of joint steps,
after a warm-up chunk that takes every learner past ``learning_starts``. With sharing, one batched forward pass
picks the 100 actions and the learner makes one gradient step per ``train_freq`` joint steps (SB3's semantics for
``n_envs`` envs); independent learners make one forward pass and one gradient step each.
"""

from __future__ import annotations

import numpy as np

from benchmarks._common import Row, fmt_rate, paired_ratio
from benchmarks.bench_training import FixedWeights, chunked_interleaved
from sb3_sfgpi import SwapTerminationsTruncations
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner

#: SFDQN's defaults (MLP [64, 64], train_freq 4, batch 32) with a smaller buffer and learning from the start.
LEARNER_KWARGS = dict(policy="MlpPolicy", buffer_size=100_000, learning_starts=0, device="cpu")
TARGET = 20.0


def _runner(sharing: str, n_agents: int):
    from momaland.envs.beach import mobeach_v0

    env = SwapTerminationsTruncations(mobeach_v0.parallel_env(num_agents=n_agents))
    runner = MultiAgentRunner(env, default_learner_factory(**LEARNER_KWARGS), seed=0, sharing=sharing)
    callback = FixedWeights({name: np.array([0.5, 0.5]) for name in runner.learner_names}, 10**9)
    return lambda n: runner.learn(n, callback)


def run(quick: bool = False) -> list[Row]:
    """Joint steps per second of shared vs independent learners on beach (its default: 100 agents)."""
    try:
        import momaland  # noqa: F401
    except ImportError:
        return [Row("sharing", "beach, 100 agents", "skipped: momaland is not installed")]
    repeats, chunk, n_agents = (3, 5, 100) if quick else (5, 20, 100)
    makers = {sharing: (lambda s=sharing: _runner(s, n_agents)) for sharing in ("shared", "independent")}
    samples = chunked_interleaved(makers, chunk, repeats)
    ratio = paired_ratio(samples, "independent", "shared")[0]
    rates = {name: chunk / float(np.median(times)) for name, times in samples.items()}
    return [
        Row(
            "sharing",
            f"beach, {n_agents} agents, MLP SFDQN: one shared learner vs one per agent",
            fmt_rate(rates["shared"], "joint steps"),
            fmt_rate(rates["independent"], "joint steps"),
            ratio,
            f"≥ {TARGET:g}×",
            ratio >= TARGET,
            f"{repeats} chunks of {chunk} joint steps; ms per joint step: "
            f"{1000 / rates['shared']:.1f} shared, {1000 / rates['independent']:.0f} independent",
        )
    ]

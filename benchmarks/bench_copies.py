"""Traffic training on k copies of the simulation (``n_envs = k``, one libsumo per process) vs one.

The traffic preset's learners (one MLP SFDQN per light) train on k = 1, 2, 4 copies of the preset's env, in
interleaved chunks of joint steps after a warm-up chunk (past ``learning_starts``); the rate compared is
environment steps (transitions per learner) per second. With k copies a joint step gives every learner k
transitions. SB3's semantics for ``n_envs`` keep ``gradient_steps`` per joint step (1 in the preset: k times fewer
updates per transition); ``gradient_steps = k`` keeps the updates per transition of k = 1. Both are measured. The
copies step in their processes while the learners train in the main one.
"""

from __future__ import annotations

import os

import numpy as np

from benchmarks._common import Row, fmt_rate, paired_ratio
from benchmarks.bench_training import FixedWeights, chunked_interleaved
from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner


def _runner(k: int, gradient_steps: int, runners: list[MultiAgentRunner]):
    domain = load_domain("traffic")
    settings = domain.settings
    learner_kwargs = {"policy": settings.policy, **settings.learner_kwargs, "gradient_steps": gradient_steps}
    learner_kwargs["device"] = "cpu"
    env = domain.make_env(**domain.env_kwargs)
    runner = MultiAgentRunner(
        env, default_learner_factory(**learner_kwargs), seed=0, n_envs=k, env_fn=domain.make_env,
        env_kwargs=domain.env_kwargs,
    )  # fmt: skip
    runners.append(runner)
    callback = FixedWeights({name: np.array([0.5, 0.5]) for name in runner.learner_names}, 10**9)
    return lambda n: runner.learn(n, callback)


def run(quick: bool = False) -> list[Row]:
    """Environment steps per second of traffic training with k copies, against k = 1."""
    ks = (2,) if quick else (2, 4)
    repeats, chunk = (3, 100) if quick else (5, 200)
    cases = {(1, 1): "k=1", **{(k, g): f"k={k}, {g} updates" for k in ks for g in (1, k)}}
    runners: list[MultiAgentRunner] = []
    try:
        makers = {name: (lambda c=case: _runner(*c, runners)) for case, name in cases.items()}
        samples = chunked_interleaved(makers, chunk, repeats)
    finally:
        for runner in runners:
            runner.close()
            runner.env.close()
    rates = {case: chunk * case[0] / float(np.median(samples[name])) for case, name in cases.items()}
    rows = []
    for (k, g), name in list(cases.items())[1:]:
        speedup = paired_ratio(samples, "k=1", name)[0] * k  # env steps per second relative to k = 1
        rows.append(
            Row(
                "env copies",
                f"traffic training, {k} simulations vs 1, {g} gradient step(s) per joint step ({os.cpu_count()} cores)",
                fmt_rate(rates[(k, g)], "env steps"),
                fmt_rate(rates[(1, 1)], "env steps"),
                speedup,
                "≥ 1×" if k == 2 else "",
                speedup >= 1.0 if k == 2 else None,
                f"{repeats} chunks of {chunk} joint steps; "
                + ("as many updates per transition as k = 1" if g == k else "SB3's n_envs semantics: 1/k the updates")
                + f"; ≥ 0.7 × k = {0.7 * k:g} is the aim where there are k cores",
            )
        )
    return rows

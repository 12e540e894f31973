"""Admission in linear time: one round of pruning (GPI's score over Π and over every leave-one-out subset of Π).

A pool of Four-Room candidates is trained once without validation (``sb3-sfgpi train four-room --algo random`` with
``validation_weights=0``: two tabular policies per iteration); Π is its first 10, 20 and 40 policies. One round of
:class:`~sb3_sfgpi.admission.Admission`'s backward elimination scores Π and every leave-one-out subset on the
validation weights (the extrema and Dirichlet(1) draws of the run's seed):

* candidate: :class:`~sb3_sfgpi.validation.ValidationScorer`: Π's episodes once, recording the members GPI followed;
  a subset is rolled out again only at the weights where the member left out was decisive, over a view of Π
  (:meth:`~sb3_sfgpi.gpi.GPIPolicy.without`: no copies, no stacking);
* baseline: the previous commit's round, every subset copied (:meth:`~sb3_sfgpi.gpi.GPIPolicy.subset`) and rolled
  out at every weight (:func:`~sb3_sfgpi.evaluation.gpi_score`).

Both sides give the same scores to the last bit (checked here); interleaved, medians.
"""

from __future__ import annotations

import contextlib
import io
import json
import statistics
import tempfile
from pathlib import Path

from benchmarks._common import Row, fmt_time, interleaved_samples, paired_ratio
from sb3_sfgpi.admission import Admission
from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.evaluation import gpi_score
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.validation import ValidationScorer

SIZES = (10, 20, 40)
SEED = 0


def _pool(folder: Path, policies: int, steps: int) -> tuple[GPIPolicy, dict]:
    """The candidates of a Four-Room run of Dirichlet(1) weights without validation, and the run's settings."""
    out = folder / "pool"
    argv = ["train", "four-room", "--algo", "random", "--iterations", str(policies // 2 + 4)]
    argv += ["--steps-per-iteration", str(steps)]
    argv += ["--seed", str(SEED), "--no-progress", "--set", "n_test_weights=1", "--set", "validation_weights=0"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert main([*argv, "--out", str(out)]) == 0
    pool = GPIPolicy.load(out / "policy_set")
    if len(pool) < policies:
        raise RuntimeError(f"the pool holds {len(pool)} candidates, fewer than {policies}")
    return pool, json.loads((out / "run.json").read_text())


def run(quick: bool = False) -> list[Row]:
    """Seconds of one pruning round at |Π| = 10, 20, 40: candidate vs the previous commit's brute force."""
    n_weights, repeats, steps = (4, 1, 200) if quick else (10, 2, 300)
    with tempfile.TemporaryDirectory(prefix="sfgpi_admission_") as folder:
        pool, config = _pool(Path(folder), max(SIZES), steps)
    env = load_domain("four-room").build_env(config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)

    def rollout(policy, episodes, seed):
        return run_episodes(env, policy, episodes, gamma, seed=seed)

    weights = Admission(n_weights).weights(pool.reward_dim, SEED)
    rows, scores, seconds = [], {}, {}
    for size in SIZES:
        policy_set = pool.subset(range(size))
        scorer = ValidationScorer(weights, rollout, 1, SEED)

        def candidate(ps=policy_set, scorer=scorer, size=size):
            scored = scorer(ps)
            scores[size, "candidate"] = [scorer.without(ps, scored, m).score for m in range(len(ps))]
            return scored

        def baseline(ps=policy_set, size=size):
            others = [[j for j in range(len(ps)) if j != i] for i in range(len(ps))]
            gpi_score(ps, weights, rollout, 1, SEED, "validation")
            scores[size, "baseline"] = [
                gpi_score(ps.subset(rest), weights, rollout, 1, SEED, "validation") for rest in others
            ]

        samples = interleaved_samples({"candidate": candidate, "baseline": baseline}, repeats, warmup=0)
        assert scores[size, "candidate"] == scores[size, "baseline"], f"|Π|={size}: the scores differ"
        scored = candidate()
        decisive = scored.decisive_members()
        rolled = sum(len(scored.decisive(m)) for m in decisive)
        medians = {name: statistics.median(values) for name, values in samples.items()}
        seconds[size] = medians["candidate"]
        ratio = paired_ratio(samples, "baseline", "candidate")[0]
        note = (
            f"{len(weights)} validation weights; decisive members {len(decisive)}/{size}; weights rolled out "
            f"{len(weights)} + {rolled} vs {len(weights)} × {size + 1}; same scores; median of {repeats}"
        )
        rows.append(Row("admission", f"one pruning round, Four-Room |Π|={size}", fmt_time(medians["candidate"]),
                        fmt_time(medians["baseline"]), ratio, "", None, note))  # fmt: skip
    env.close()
    growth = seconds[SIZES[-1]] / seconds[SIZES[0]]
    linear = SIZES[-1] / SIZES[0]
    note = "a round's time at the largest |Π| / at the smallest"
    rows.append(Row("admission", f"growth |Π| {SIZES[0]} → {SIZES[-1]} (candidate)", f"{growth:.1f}×", "", None,
                    f"≤ {linear:.0f}× (linear)", growth <= linear, note))  # fmt: skip
    return rows

"""Tabular SFDQN steps per second, this tree against a former commit's code, in fresh interpreters (issue 48, item 1).

The workload is the main job's training loop (``sb3-sfgpi train four-room``): the preset's two tabular learners
(planning, optimism, Table 1 settings) driven by ``MultiAgentRunner`` for fixed weights, one iteration of
``STEPS`` joint steps (``QUICK_STEPS`` with ``--quick``), seed 0; no OLS, admission or evaluation. Learner
construction and imports are not timed.

Candidate: this source tree. Baseline: the source tree of :data:`BASELINE_COMMIT` (``git archive`` into a temporary
folder, or of ``$SB3_SFGPI_TABULAR_BASELINE``), the last commit before the fast tabular path. Each side runs in its own
interpreter with ``PYTHONPATH`` on its tree (its own ``sfgpi_envs`` too), alternately; medians, and the ratio of each
round's pair. Both sides must end with the same tables, bit for bit (the "same numbers" of the fast path): the note
says whether they did.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks._common import ROOT, Row, baseline_tree, fmt_rate

#: The last commit before the fast tabular path.
BASELINE_COMMIT = "96164d2"
STEPS = 20_000
QUICK_STEPS = 5_000
#: What each interpreter runs: ``{steps}`` joint steps, then one JSON line (agent steps per second, table digest).
WORKLOAD = """
import hashlib, json, time
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from sfgpi_envs.domains import four_room
from sb3_sfgpi.multiagent import MultiAgentRunner
try:
    from sb3_sfgpi.learners import default_learner_factory
except ImportError:  # a tree from before that module
    from sb3_sfgpi.multiagent import default_learner_factory

class Fixed(BaseCallback):
    def _on_step(self):
        return True

preset = four_room()
env = preset["make_env"](**preset["env_kwargs"])
runner = MultiAgentRunner(env, default_learner_factory(**preset["learner_kwargs"]), seed=0)
runner.start_iteration({{"agent_0": np.array([0.5, 0.3, 0.2]), "agent_1": np.array([0.2, 0.3, 0.5])}}, 0, {steps})
start = time.perf_counter()
runner.learn({steps}, Fixed())
seconds = time.perf_counter() - start
learners = runner.learners.values()
space = env.observation_space("agent_0")
# every row, in either tree's tables
every_obs = np.stack(np.unravel_index(np.arange(int(np.prod(space.nvec))), space.nvec), axis=1)
digest = hashlib.sha256(b"".join(l.successor_features(every_obs).tobytes() for l in learners))
steps = sum(l.num_timesteps for l in learners)
print(json.dumps({{"rate": steps / seconds, "digest": digest.hexdigest()}}))
"""


def _with_envs(tree: Path) -> Path:
    """An extracted ``tree`` with its own ``sfgpi_envs`` importable (the package is ``envs/``, mapped at install)."""
    (tree / "sfgpi_envs").symlink_to(tree / "envs", target_is_directory=True)
    return tree


def _measure(tree: Path, steps: int) -> dict[str, float | str]:
    """Agent steps per second of the workload in a fresh interpreter on ``tree``, and its tables' digest."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    code = WORKLOAD.format(steps=steps)
    result = subprocess.run([sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def run(quick: bool = False) -> list[Row]:
    """Tabular training steps per second, this tree against the baseline commit."""
    rounds, steps = (2, QUICK_STEPS) if quick else (3, STEPS)
    commit = os.environ.get("SB3_SFGPI_TABULAR_BASELINE", BASELINE_COMMIT)
    case = f"tabular SFDQN, Four-Room preset, 2 agents, {steps:,} joint steps"
    with tempfile.TemporaryDirectory(prefix="sfgpi_tabular_") as folder:
        if not baseline_tree(Path(folder), commit):
            return [Row("training", case, f"skipped: commit {commit} cannot be read")]
        trees = {"candidate": ROOT, "baseline": _with_envs(Path(folder))}
        samples: dict[str, list[dict]] = {name: [] for name in trees}
        for r in range(rounds):
            for name in list(trees)[r % 2 :] + list(trees)[: r % 2]:
                samples[name].append(_measure(trees[name], steps))
    rates = {name: [s["rate"] for s in values] for name, values in samples.items()}
    ratios = [c / b for c, b in zip(rates["candidate"], rates["baseline"], strict=True)]
    same = {s["digest"] for values in samples.values() for s in values}
    return [
        Row(
            "training",
            case,
            fmt_rate(statistics.median(rates["candidate"]), "agent steps"),
            fmt_rate(statistics.median(rates["baseline"]), "agent steps"),
            statistics.median(ratios),
            "",
            None,
            f"baseline: commit {commit}; tables {'identical' if len(same) == 1 else 'DIFFERENT'} on both sides; "
            f"{rounds} alternating runs each, fresh interpreters",
        )
    ]

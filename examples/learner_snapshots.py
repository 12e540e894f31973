"""Snapshots of learners trained for one weight, each scored afterwards: which point of training a rule would keep.

Trains every agent's learner for ``--w`` from scratch, as ``sb3-sfgpi train DOMAIN --algo fixed --w W --iterations 1
--steps-per-iteration STEPS`` does (the same seed gives the same learners), keeps a copy of every learner's network
every ``--every`` joint steps, and then scores each snapshot with every agent acting greedily with its own learner, on
two disjoint sets of episodes: the test episodes (``--test-seed``: ``sb3-sfgpi compare``'s by default) and selection
episodes (``--selection-seed``). A score is w·G, the learners' objective (w · the discounted return, mean over agents),
and the mean of each of the domain's episode metrics (``compare``'s; traffic: the mean waiting times, lower is
better). At the end it prints the snapshot each selection rule keeps and its test scores: the last one (what training
returns), the best by w·G on the selection episodes, and the lowest of each episode metric on them.

Run: ``python examples/learner_snapshots.py DOMAIN --w W [W ...] --steps STEPS --every EVERY [--seed S]
[--episodes N] [--env KEY=VALUE] [--learner KEY=VALUE] [--out FILE.json]``, e.g. ``python
examples/learner_snapshots.py traffic --w 1 0 --steps 16000 --every 2000 --env early_change=defer --seed 0``
(README, "Why GPI does not reach SUMO's actuated program").
"""

from __future__ import annotations

import argparse
import copy
import json
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_sfgpi.cli.compare import episode_metrics
from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import DomainPreset, load_domain
from sb3_sfgpi.cli.values import key_values
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.multiagent import MultiAgentRunner


class Snapshots(BaseCallback):
    """
    Runner-level callback: a copy of every learner's SF network every ``every`` joint steps; the one at the last step
    is taken again when training ends, of the learners as trained (a table's optimism removed, as ``train`` has it).

    :param every: joint steps between two snapshots
    """

    def __init__(self, every: int):
        super().__init__()
        self.every = every
        #: (joint steps, learner name -> state dict of its SF network)
        self.taken: list[tuple[int, dict[str, dict[str, th.Tensor]]]] = []

    def _on_step(self) -> bool:
        if self.model.num_timesteps % self.every == 0:
            self._take()
        return True

    def _on_training_end(self) -> None:
        if self.taken and self.taken[-1][0] == self.model.num_timesteps:
            self.taken.pop()
            self._take()

    def _take(self) -> None:
        runner = self.model
        states = {name: copy.deepcopy(learner.policy.sf_net.state_dict()) for name, learner in runner.learners.items()}
        self.taken.append((runner.num_timesteps, states))


def score(runner: MultiAgentRunner, w: np.ndarray, seed: int, episodes: int, metrics: list[list[str]]) -> dict:
    """w·G and the mean episode metrics of the learners' greedy joint policy over ``episodes`` from ``seed``."""
    result = run_episodes(runner.env, runner.learner_policy(), episodes, runner.gamma, seed=seed)
    means = {key: stats["mean"] for key, stats in episode_metrics(result, metrics).items()}
    return {"w·G": float(w @ result.mean_discounted_over()), **means}


def scored_snapshots(args: argparse.Namespace, preset: DomainPreset) -> list[dict[str, Any]]:
    """Train, then score every snapshot on the test and the selection episodes."""
    learner_kwargs = {"policy": preset.settings.policy, **preset.settings.learner_kwargs}
    learner_kwargs.update(key_values(args.learner, "--learner"))
    env = preset.build_env({**preset.env_kwargs, **key_values(args.env, "--env")})
    try:
        w = validate_weights(args.w, int(env.reward_space(env.possible_agents[0]).shape[0]), "--w")
        model = MASFOLS(
            env, learner_kwargs.pop("policy"), w, steps_per_iteration=args.steps, learner_kwargs=learner_kwargs,
            seed=args.seed,
        )  # fmt: skip
    except ValueError as error:
        env.close()
        raise UsageError(str(error)) from error
    snapshots = Snapshots(args.every)
    rows = []
    try:
        model.learn(max_iterations=1, callback=snapshots)
        for steps, states in snapshots.taken:
            for name, state in states.items():
                model.runner.learners[name].policy.sf_net.load_state_dict(state)
            rows.append({
                "steps": steps,
                "test": score(model.runner, w, args.test_seed, args.episodes, preset.episode_metrics),
                "selection": score(model.runner, w, args.selection_seed, args.episodes, preset.episode_metrics),
            })  # fmt: skip
            print(snapshot_line(rows[-1]), flush=True)
    finally:
        model.close()
    return rows


def scores_text(scores: dict[str, float]) -> str:
    """``name=value`` for each score, on one line."""
    return " ".join(f"{name}={value:.4f}" for name, value in scores.items())


def snapshot_line(row: dict[str, Any]) -> str:
    """One snapshot's scores on one line."""
    return f"steps {row['steps']}: test {scores_text(row['test'])} | selection {scores_text(row['selection'])}"


def kept(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The snapshot each selection rule keeps: the last, the best w·G and the lowest of each metric on selection."""
    rules = {"last": rows[-1], "best w·G": max(rows, key=lambda row: row["selection"]["w·G"])}
    for key in rows[-1]["selection"]:
        if key != "w·G":
            rules[f"lowest {key}"] = min(rows, key=lambda row: row["selection"][key])
    return rules


def main(argv: list[str] | None = None) -> None:
    """Parse the options, train and score, print the rules' choices; one line and exit 2 on bad input."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("domain", help="four-room, traffic, or another installed domain")
    parser.add_argument("--w", type=float, nargs="+", required=True, help="the learners' weights")
    parser.add_argument("--steps", type=int, required=True, help="joint env steps of training")
    parser.add_argument("--every", type=int, required=True, help="joint steps between two snapshots")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=5, help="episodes of each score")
    parser.add_argument("--test-seed", type=int, default=1000, help="reset seed of the first test episode")
    parser.add_argument("--selection-seed", type=int, default=2000, help="the same for the selection episodes")
    parser.add_argument("--env", metavar="KEY=VALUE", action="append", default=[], help="override an env argument")
    parser.add_argument("--learner", metavar="KEY=VALUE", action="append", default=[], help="override an SFDQN one")
    parser.add_argument("--out", help="write the snapshots' scores to this JSON file")
    args = parser.parse_args(argv)
    for option in ("steps", "every", "episodes"):
        if getattr(args, option) < 1:
            parser.error(f"--{option} must be at least 1, got {getattr(args, option)}")
    if args.every > args.steps:
        parser.error(f"--every ({args.every}) must not exceed --steps ({args.steps}): no snapshot would be taken")
    if abs(args.test_seed - args.selection_seed) < args.episodes:
        parser.error("--test-seed and --selection-seed must be --episodes apart: the two sets must not share episodes")
    th.set_num_threads(1)
    try:
        rows = scored_snapshots(args, load_domain(args.domain))
    except UsageError as error:
        parser.error(str(error))
    for rule, row in kept(rows).items():
        print(f"{rule}: steps {row['steps']}, test {scores_text(row['test'])}")
    if args.out:
        with open(args.out, "w") as file:
            json.dump(rows, file, indent=1)


if __name__ == "__main__":
    main()

"""Replay policy validation over a run that kept every candidate policy, without training again.

Validation leaves training as it is: whichever policies join Π, the weights trained, the learners and their
policies are the same (a left-out policy's value still goes to the schedule). A run trained with
``--set validation_weights=0`` keeps every candidate in its policy set, so validation's rules can be replayed over it:
the replay gives, to the last digit on the same machine, the curve of a run trained with those rules
(``tests/test_validation_replay.py`` checks it). Runs of levers that put Π in the training loop (transfer, GPI
behaviour, GPI values, replanning: written by older versions, which had them) are refused, and so are runs that
pooled their replay (``pool_replay``: every policy's SFs are planned again after each iteration, so those saved are
the last iteration's, not those validation would have scored). After every iteration, as
:class:`~sb3_sfgpi.admission.Admission` does it:

* the iteration's new policies, one by one, join Π unless GPI does worse with them on the validation weights;
* ``--admit-together``: those left out are then tried together;
* ``--recall`` (a rule the package does not have): the candidates so far that are not in Π (left out, or retired)
  are tried again, and the one with which GPI does best joins while GPI does strictly better;
* ``--prune``: the policy without which GPI does best is retired while GPI does strictly better without it.

It prints, after every iteration, |Π| and GPI's mean w·return over the run's test weights (as the run's
evaluation: its episodes and seeds), then the final members of Π. Scores are cached by set: a replay costs one
score per set tried.

Run: ``python examples/validation_replay.py RUN_DIR [--validation-weights N] [--[no-]admit-together] [--[no-]prune]
[--recall]`` (the rules of ``sb3-sfgpi train``'s ``--set validation_weights=N prune=... admit_together=...``, the
domain's by default), e.g. over a run of ``sb3-sfgpi train four-room --set validation_weights=0``.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from sb3_sfgpi.admission import Admission
from sb3_sfgpi.callbacks import VALUE_MODES
from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.common.rollouts import EpisodeReturns, JointPolicy, run_episodes
from sb3_sfgpi.evaluation import gpi_score
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import load_policy_set


class Candidates:
    """
    Every candidate policy of a run, and GPI's score over any subset of them (cached by subset).

    :param run_dir: a run that kept every candidate (see :func:`load`)
    :param config: its settings (``run.json``)
    :param env: the run's env
    :param validation: the validation weights and episodes to score with
    """

    def __init__(self, run_dir: RunDirectory, config: dict[str, Any], env: Any, validation: Admission):
        state = run_dir.read_checkpoint()
        self.record = load_policy_set(run_dir, state["n_policies"], iteration=state["iteration"], record=True)
        self.iterations = state["iteration"]
        self.env = env
        self.gamma = config["learner_kwargs"].get("gamma", 0.99)
        self.seed = config["seed"]
        self.test_episodes = config["eval_episodes"]
        self.test_weights = np.asarray(config["test_weights"], dtype=np.float64)
        if not len(self.record):
            raise ValueError(f"{run_dir} holds no policies")
        if self.test_weights.ndim != 2 or self.test_weights.shape[1] != self.record.reward_dim:
            shape, d = self.test_weights.shape, self.record.reward_dim
            raise ValueError(f"{run_dir}: test weights of shape {shape} for policies of {d} objectives")
        self.ccs_only = config.get("gpi_set") == "ccs"
        self.validation_episodes = validation.episodes
        self.validation_weights = validation.weights(self.record.reward_dim, self.seed)
        self._scores: dict[tuple[tuple[int, ...], str], float] = {}

    def of_iteration(self, iteration: int) -> list[int]:
        """The indices of the candidates made in ``iteration`` (numbered from 1)."""
        return [i for i, info in enumerate(self.record.infos) if info.iteration == iteration]

    def validation_score(self, members: list[int]) -> float:
        """GPI over ``members`` (in Π's order) on the validation weights, as validation scores it."""
        return self._score(members, self.validation_weights, self.validation_episodes, "validation")

    def test_score(self, members: list[int]) -> float:
        """GPI over ``members`` (or their CCS, as the run's) on the test weights, as the run's evaluation scores it."""
        return self._score(members, self.test_weights, self.test_episodes, "eval")

    def _score(self, members: list[int], weights: np.ndarray, episodes: int, purpose: str) -> float:
        key = (tuple(members), purpose)
        if key not in self._scores:
            policy_set = self.record.subset(members)
            if purpose == "eval" and self.ccs_only:
                policy_set = policy_set.ccs_policies()
            self._scores[key] = gpi_score(policy_set, weights, self._rollout, episodes, self.seed, purpose)
        return self._scores[key]

    def _rollout(self, policy: JointPolicy, episodes: int, seed: int) -> EpisodeReturns:
        return run_episodes(self.env, policy, episodes, self.gamma, seed=seed)


def admit(candidates: Candidates, members: list[int], new: list[int], together: bool) -> list[int]:
    """Π after the iteration's ``new`` policies were tried one by one (then, with ``together``, those left out)."""
    score = candidates.validation_score
    left_out = []
    for index in new:
        if not members or score(members + [index]) >= score(members):
            members = members + [index]
        else:
            left_out.append(index)
    if together and len(left_out) > 1 and score(members + left_out) >= score(members):
        members = members + left_out
    return members


def recall(candidates: Candidates, members: list[int], iteration: int) -> list[int]:
    """Π after adding, while GPI does strictly better, the candidate so far with which it does best."""
    so_far = [i for i, info in enumerate(candidates.record.infos) if info.iteration <= iteration]
    while rest := [i for i in so_far if i not in members]:
        scores = [candidates.validation_score(members + [i]) for i in rest]
        best = int(np.argmax(scores))
        if scores[best] <= candidates.validation_score(members):
            break
        members = members + [rest[best]]
    return members


def prune(candidates: Candidates, members: list[int]) -> list[int]:
    """Π after retiring, while GPI does strictly better without it, the policy without which it does best."""
    while len(members) > 1:
        scores = [candidates.validation_score(members[:i] + members[i + 1 :]) for i in range(len(members))]
        worst = int(np.argmax(scores))
        if scores[worst] <= candidates.validation_score(members):
            break
        members = members[:worst] + members[worst + 1 :]
    return members


def replay(candidates: Candidates, together: bool, recalling: bool, pruning: bool) -> list[list[int]]:
    """Π after every iteration under the rules given (indices into the run's candidates, in Π's order)."""
    members: list[int] = []
    history = []
    for iteration in range(1, candidates.iterations + 1):
        members = admit(candidates, members, candidates.of_iteration(iteration), together)
        if recalling:
            members = recall(candidates, members, iteration)
        if pruning:
            members = prune(candidates, members)
        history.append(members)
    return history


def load(args: argparse.Namespace) -> tuple[Candidates, bool, bool]:
    """
    The run's candidates and the rules to replay (the options given, else the domain's).

    :raises ValueError: not a run whose candidates are those of a validated run, or no validation weights
    :raises UsageError: a run of a domain that is not installed, or an env that refuses the run's settings
    """
    run_dir = RunDirectory(args.run_dir)
    required = ("domain", "algorithm", "seed", "test_weights", "env_kwargs", "learner_kwargs", "eval_episodes",
                "validation_weights", "prune", "value_mode", "pool_replay")  # fmt: skip
    config = run_dir.read_config(required=required)
    if config["algorithm"] == "fixed":
        raise ValueError(f"{args.run_dir} is a run of fixed weights: its agents act by their own policies")
    if config["validation_weights"] or config["prune"]:
        raise ValueError(f"{args.run_dir} was trained with validation: replay needs --set validation_weights=0")
    if config["value_mode"] not in VALUE_MODES:
        raise ValueError(f"{args.run_dir} was trained with value_mode={config['value_mode']}, which this version "
                         "does not have")  # fmt: skip
    if config["pool_replay"]:
        raise ValueError(f"{args.run_dir} pooled its replay: the SFs saved are its last iteration's, not those "
                         "validation would have scored")  # fmt: skip
    preset = load_domain(config["domain"])
    n_weights = preset.settings.validation_weights if args.validation_weights is None else args.validation_weights
    if n_weights < 1:
        raise ValueError(f"validation needs validation weights: --validation-weights N with N > 0, got {n_weights}")
    together = preset.settings.admit_together if args.admit_together is None else args.admit_together
    pruning = preset.settings.prune if args.prune is None else args.prune
    env = preset.build_env(config["env_kwargs"])
    try:
        return Candidates(run_dir, config, env, Admission(n_weights)), together, pruning
    except ValueError:
        env.close()
        raise


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a run of sb3-sfgpi train with --set validation_weights=0")
    parser.add_argument("--validation-weights", type=int, metavar="N", help="Dirichlet(1) weights (the domain's)")
    flag = argparse.BooleanOptionalAction
    parser.add_argument("--admit-together", action=flag, help="try left-out policies together (the domain's)")
    parser.add_argument("--prune", action=flag, help="retire policies without which GPI does better (the domain's)")
    parser.add_argument("--recall", action="store_true", help="try the candidates not in Π again every iteration")
    args = parser.parse_args(argv)
    try:
        candidates, together, pruning = load(args)
    except (ValueError, UsageError) as error:
        parser.error(str(error))
    try:
        history = replay(candidates, together, args.recall, pruning)
        for iteration, members in enumerate(history, start=1):
            score = candidates.test_score(members)
            print(f"iteration {iteration}: |Π|={len(members)} mean w·return (discounted)={score:.4f}")
    finally:
        candidates.env.close()
    final = [candidates.record.infos[i] for i in history[-1]]
    print(f"Π at the end ({len(final)} of {len(candidates.record)} candidates): " + ", ".join(
        f"{info.agent}'s of iteration {info.iteration}" for info in final
    ))  # fmt: skip


if __name__ == "__main__":
    main()

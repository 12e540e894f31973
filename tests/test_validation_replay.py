"""``examples/validation_replay.py``: validation replayed over a run that kept every candidate policy."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import pytest
from example_scripts import load_example

from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.presets import load_domain

TRAIN = ["train", "four-room", "--iterations", "4", "--steps-per-iteration", "400", "--set", "n_test_weights=4"]
#: the rules, as the replay takes them and as ``train`` does
RULES = ["--validation-weights", "6", "--prune", "--admit-together"]
TRAIN_RULES = ["--set", "validation_weights=6", "--set", "prune=true", "--set", "admit_together=true"]


@pytest.fixture(scope="module")
def example():
    return load_example("validation_replay")


# seeds whose validated runs use every rule the replay copies (found by replaying variants of the rules over them):
# on seed 7 pruning retires policies and a tie admits one; on seed 31 two policies left out join together
@pytest.fixture(scope="module", params=[7, 31])
def runs(request, tmp_path_factory):
    """The same seed trained twice: with the rules, and keeping every candidate."""
    root = tmp_path_factory.mktemp("replay")
    validated, kept = root / "validated", root / "kept"
    seed = ["--no-progress", "--seed", str(request.param)]
    keep_all = ["--set", "validation_weights=0"]  # no validation: no pruning, nothing admitted together either
    assert main([*TRAIN, *seed, *TRAIN_RULES, "--out", str(validated)]) == 0
    assert main([*TRAIN, *seed, *keep_all, "--out", str(kept)]) == 0
    config = json.loads((kept / "run.json").read_text())
    assert (config["validation_weights"], config["prune"], config["admit_together"]) == (0, False, False)
    return validated, kept


def replayed(example, capsys, run, *options):
    example.main([str(run), *options])
    return capsys.readouterr().out.splitlines()


def test_the_replay_gives_the_validated_run(example, runs, capsys):
    validated, kept = runs
    evaluations = json.loads((validated / "evaluation.json").read_text())
    expected = [
        f"iteration {row['iteration']}: |Π|={row['n_policies']} mean w·return (discounted)={row['mean_return']:.4f}"
        for row in evaluations
    ]
    manifest = json.loads((validated / "policy_set" / "manifest.json").read_text())["policies"]
    in_pi = [policy for policy in manifest if policy["retired"] is None]
    members = [f"{policy['agent']}'s of iteration {policy['iteration']}" for policy in in_pi]
    lines = replayed(example, capsys, kept, *RULES)
    assert lines[:-1] == expected and lines[-1].endswith("candidates): " + ", ".join(members))
    candidates = json.loads((kept / "evaluation.json").read_text())[-1]["n_policies"]
    assert evaluations[-1]["n_policies"] < candidates  # validation chose: the replay had something to reproduce
    if any(entry["retired"] is not None for entry in manifest):  # seed 7: a pruned run
        assert replayed(example, capsys, kept, *RULES, "--no-prune") != lines
    else:  # seed 31: two policies joined together
        assert replayed(example, capsys, kept, *RULES, "--no-admit-together") != lines


def test_the_replay_takes_the_domains_rules_by_default(example, runs):
    _, kept = runs
    options = argparse.Namespace(run_dir=str(kept), validation_weights=None, admit_together=None, prune=None)
    candidates, together, pruning = example.load(options)
    preset = load_domain("four-room")
    assert (together, pruning) == (preset.settings.admit_together, preset.settings.prune) == (True, True)
    assert len(candidates.validation_weights) == preset.settings.validation_weights + 3  # and the extrema
    candidates.env.close()


def test_a_run_that_pooled_its_replay_is_refused(example, tmp_path):
    settings = {"domain": "resource-gathering-v0", "algorithm": "ma-sfols", "seed": 0, "test_weights": [[1, 0, 0]]}
    settings.update(env_kwargs={}, learner_kwargs={}, eval_episodes=1, validation_weights=0, pool_replay=True)
    settings.update(format="sb3-sfgpi/run", version=1, prune=False, value_mode="joint")
    (tmp_path / "run.json").write_text(json.dumps(settings))
    options = argparse.Namespace(run_dir=str(tmp_path), validation_weights=None, admit_together=None, prune=None)
    with pytest.raises(ValueError, match="pooled its replay: the SFs saved are its last iteration's"):
        example.load(options)


class ScoredSets:
    """GPI's validation score given for each set of candidates: what the replay's rules read of the candidates."""

    def __init__(self, scores: dict[tuple[int, ...], float]):
        self.scores = scores

    def validation_score(self, members: list[int]) -> float:
        return self.scores[tuple(sorted(members))]


@pytest.mark.parametrize(
    ("with_both", "together", "one_by_one"),
    [(1.0, [0, 1, 2], [0]), (0.9, [0], [0])],  # a tie with Π joins ("no worse", as Admission); lower stays out
)
def test_the_replay_admits_left_out_policies_that_tie_together(example, with_both, together, one_by_one):
    scores = ScoredSets({(0,): 1.0, (0, 1): 0.8, (0, 2): 0.7, (0, 1, 2): with_both})  # 1 and 2 each lower GPI alone
    assert example.admit(scores, [0], [1, 2], together=True) == together
    assert example.admit(scores, [0], [1, 2], together=False) == one_by_one


def test_the_replay_admits_a_policy_that_ties_one_by_one(example):
    one_tie = ScoredSets({(0,): 1.0, (0, 1): 1.0, (0, 1, 2): 0.9})  # 1 ties and joins; 2 alone: nothing together
    assert example.admit(one_tie, [0], [1, 2], together=True) == [0, 1]


@pytest.mark.parametrize(
    ("which", "change", "extra", "message"),
    [
        ("validated", {}, [], "replay needs --set validation_weights=0"),
        ("kept", {}, ["--validation-weights", "0"], "validation needs validation weights"),
        ("kept", {"algorithm": "fixed"}, [], "is a run of fixed weights"),
        ("kept", {"value_mode": "gpi"}, [], "trained with value_mode=gpi, which this version does not have"),
        ("kept", {"version": 2}, [], "is of format version 2; this version of sb3-sfgpi reads version 1"),
        ("kept", {"env_kwargs": {"size": 3}}, [], "the four-room env refuses"),
        ("kept", {"test_weights": [[0.5, 0.5]]}, [], "test weights of shape (1, 2) for policies of 3 objectives"),
        ("nowhere", None, [], "is not a run directory"),
    ],
)
def test_the_replay_refuses_what_it_cannot_replay(example, runs, tmp_path, capsys, which, change, extra, message):
    validated, kept = runs
    run = {"validated": validated, "kept": kept}.get(which, tmp_path / which)
    if change:
        run = Path(shutil.copytree(run, tmp_path / "changed"))
        config = json.loads((run / "run.json").read_text())
        (run / "run.json").write_text(json.dumps({**config, **change}))
    with pytest.raises(SystemExit) as exit_info:
        example.main([str(run), *extra])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in error

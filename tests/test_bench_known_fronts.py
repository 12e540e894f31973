"""The known-fronts benchmark's side of morl-baselines: the peers' budgets, the row of a peer that is not installed,
and the Monte-Carlo EU by which a peer without a model (minecart's GPI-LS) is scored like our runs."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights

pytest.importorskip("mo_gymnasium")
if str(Path(__file__).resolve().parents[1]) not in sys.path:  # the benchmarks are not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import bench_known_fronts as bench  # noqa: E402
from benchmarks import minecart_reference  # noqa: E402

DOWN = 1  # deep-sea-treasure's action 1; down from the start is the first treasure, 0.7, in one step


def test_a_policy_that_always_goes_down_scores_the_first_treasure():
    """Every episode of always-down is one step to the first treasure: EU is exactly mean(w · (0.7, -1))."""
    problem = bench.PROBLEMS["deep-sea-treasure"]
    weights = random_weights(2, 10, rng=0)
    asked = []

    def act(observation: np.ndarray, w: np.ndarray) -> int:
        asked.append(tuple(w))
        return DOWN

    eu = bench.rollout_expected_utility(problem, act, weights, 0.99, seed=0)
    assert eu == pytest.approx(np.mean(weights @ [0.7, -1.0]), abs=1e-6)  # the env's rewards are float32
    assert asked == [tuple(w) for w in weights for _ in range(problem.eval_episodes)]  # each weight its episodes


def test_the_rollouts_reset_with_our_test_evaluations_seeds(monkeypatch):
    """Weight i's episodes start from derive_seed(seed, "eval", i), as TestEvaluation's do."""
    problem = bench.PROBLEMS["minecart"]
    seeds, run_episodes = [], bench.run_episodes

    def episodes(env, policy, n_episodes, gamma, seed):
        seeds.append(seed)
        return run_episodes(env, policy, n_episodes, gamma, seed=seed)

    monkeypatch.setattr(bench, "run_episodes", episodes)
    monkeypatch.setattr(bench, "_make_env", lambda p: bench.mo.make("deep-sea-treasure-v0"))
    bench.rollout_expected_utility(problem, lambda o, w: DOWN, random_weights(2, 3, rng=0), 0.99, seed=7)
    assert seeds == [derive_seed(7, "eval", i) for i in range(3)]


def test_the_peers_budgets():
    gpi_ls, minecart = bench.PEERS[False], bench.PROBLEMS["minecart"]
    assert gpi_ls.budget(minecart, quick=False, total=None) == (10_000, 15)  # GPI-PD's published 150,000 steps
    assert gpi_ls.budget(minecart, quick=False, total=60_000) == (10_000, 6)
    assert gpi_ls.budget(minecart, quick=True, total=None) == minecart.quick  # the smoke run takes ours
    mpmoq, fruit_tree = bench.PEERS[True], bench.PROBLEMS["fruit-tree"]
    assert mpmoq.budget(fruit_tree, quick=False, total=None) == (5_000, 25)


def test_a_problem_without_a_known_front_is_scored_by_eu_alone():
    """Lunar lander has no front: its rows give EU, not a ratio to an EU* that does not exist; minecart keeps EU/EU*."""
    lander, minecart = bench.PROBLEMS["lunar-lander"], bench.PROBLEMS["minecart"]
    assert "lunar-lander" in bench.DEEP and not lander.known_front and minecart.known_front
    weights = random_weights(4, 5, rng=0)
    assert bench._best(lander, bench._make_env(lander), None, weights, 0.98) is None
    short_legs = replace(minecart, front=lambda env, gamma: minecart_reference.searched_front(env, gamma, 6, 8))
    best = bench._best(short_legs, bench._make_env(minecart), None, random_weights(3, 5, rng=0), 0.98)
    assert best is not None and best > 0  # minecart's front: some ore home beats standing still
    outcomes = [bench.Outcome(-2.0, -2.0, 1.0, 100, 1, 1), bench.Outcome(-1.0, -1.0, 1.0, 100, 2, 1)]
    summary = bench.summary_row(bench.NAME, "lander", outcomes, None, "no known front: EU alone", [0, 1])
    assert summary.candidate == "EU -1.500 ± 0.707" and "per seed (0, 1): -2.000, -1.000" in summary.note
    assert bench.seed_row(bench.NAME, "mo-lunar-lander-v3 seed 0", outcomes[0], None).candidate == "EU -2.000"
    assert bench.seed_row(bench.NAME, "minecart-v0 seed 0", outcomes[0], -4.0).candidate == "EU/EU* 0.500"
    assert bench.summary_row(bench.NAME, "m", outcomes, -4.0, "EU*", [0, 1]).candidate == "EU/EU* 0.375 ± 0.177"


def test_a_seed_row_of_a_run_shows_gpis_score_after_every_iteration():
    """The deep runs swing between iterations: a seed's row shows the whole trace, scored as its end is."""
    outcome = bench.Outcome(4.0, 4.0, 1.0, 100, 2, 3, by_iteration=(2.0, -1.0, 4.0))
    note = bench.seed_row(bench.NAME, "deep-sea-treasure-v0 seed 0", outcome, 5.0).note
    assert note.endswith("EU/EU* by iteration (Monte Carlo): 0.40, -0.20, 0.80")
    assert bench.seed_row(bench.NAME, "mo-lunar-lander-v3 seed 0", outcome, None).note.endswith(
        "EU by iteration (Monte Carlo): 2.00, -1.00, 4.00"
    )
    assert (
        "by iteration" not in bench.seed_row(bench.NAME, "x seed 0", bench.Outcome(1.0, None, 1.0, 100, 1, 1), 2.0).note
    )


def test_deep_sea_treasure_with_mlp_successor_features_is_a_deep_problem_scored_exactly():
    """The tabular problem with the deep preset's learners: EU* by value iteration at the deep preset's γ."""
    problem = bench.PROBLEMS["deep-sea-treasure-mlp"]
    assert "deep-sea-treasure-mlp" in bench.DEEP and not problem.tabular and problem.model is not None
    policy, learner = bench._learner_of(problem)
    assert policy == "ConditionedMlpPolicy"
    env = bench._make_env(problem)
    weights = random_weights(2, 50, rng=0)
    best = bench._best(problem, env, bench._model(problem, env, learner["gamma"]), weights, learner["gamma"])
    assert best == pytest.approx(4.8558, abs=1e-4)  # the deep-fronts row's EU* at γ 0.98


def test_a_peer_that_is_not_installed_gets_one_row_saying_so():
    missing = bench.Peer("no_such_morl_module", "Nothing", "nothing", bench._train_gpi_ls, len)
    rows = bench._peer_rows(missing, bench.PROBLEMS["minecart"], [0], quick=True, peer_steps=None)
    assert [row.candidate for row in rows] == [bench.MORL_MISSING]


def test_a_tabular_peer_is_scored_exactly_and_repeats_with_its_seed(monkeypatch):
    """MPMOQLearning on deep-sea-treasure's smoke budget (a few seconds): a summary row and a seed row, the same EU
    from the same seed."""
    pytest.importorskip("morl_baselines")
    monkeypatch.setattr(bench, "N_TEST_WEIGHTS", 5)
    problem = bench.PROBLEMS["deep-sea-treasure"]
    first, again = (bench._peer_rows(bench.PEERS[True], problem, [0], quick=True, peer_steps=None) for _ in range(2))
    assert [row.case for row in first] == [
        "deep-sea-treasure-v0, morl-baselines MPMOQLearning (OLS, GPI, Dyna), 2 × 1,500 steps",
        "deep-sea-treasure-v0 morl-baselines MPMOQLearning seed 0",
    ]
    assert "3,000 env steps" in first[1].note
    assert first[1].baseline == again[1].baseline and first[1].baseline.startswith("EU ")


def test_our_runs_resume_from_their_run_directories_exactly_and_refuse_other_settings(monkeypatch, tmp_path):
    """``--runs``: a run cut after its first iteration and run again goes on to the same end as one run straight
    through; a finished one is only read; a directory of other settings is refused."""
    monkeypatch.setattr(bench, "N_TEST_WEIGHTS", 5)
    problem = bench.PROBLEMS["deep-sea-treasure"]
    policy, learner = bench._learner_of(problem)
    weights = random_weights(2, 5, rng=0)

    def train(budget: tuple[int, int], runs: Path, test_weights: np.ndarray = weights) -> bench.Outcome:
        monkeypatch.setitem(bench.PROBLEMS, "deep-sea-treasure", replace(problem, quick=budget))
        return bench._train_sfols("deep-sea-treasure", policy, learner, test_weights, None, 0, True, runs)

    straight = train((1_500, 2), tmp_path / "straight")
    assert train((1_500, 1), tmp_path / "cut").iterations == 1
    cut = train((1_500, 2), tmp_path / "cut")
    again = train((1_500, 2), tmp_path / "cut")
    for outcome in (cut, again):
        assert (outcome.by_iteration, outcome.env_steps, outcome.n_policies) == (
            straight.by_iteration, straight.env_steps, straight.n_policies,
        )  # fmt: skip
    assert again.wall_time == cut.wall_time  # read, not trained again
    with pytest.raises(ValueError, match="holds a run of other settings"):
        train((1_500, 2), tmp_path / "cut", random_weights(2, 5, rng=1))


def test_a_run_of_the_command_line_is_the_benchmarks_run(tmp_path):
    """``sb3-sfgpi train <env id> --seed S`` with the benchmark's budget, linked into ``--runs``, is read as its own run
    (the same settings, the learners' device included), not refused and not trained again."""
    from sb3_sfgpi.cli import main

    runs = tmp_path / "runs"
    steps, iterations = bench.PROBLEMS["deep-sea-treasure"].quick
    command = ["train", "deep-sea-treasure-v0", "--seed", "0", "--iterations", str(iterations)]
    command += ["--steps-per-iteration", str(steps), "--out", str(runs / "deep-sea-treasure-s0"), "--no-progress"]
    assert main(command) == 0
    policy, learner = bench._learner_of(bench.PROBLEMS["deep-sea-treasure"])
    weights = random_weights(2, bench.N_TEST_WEIGHTS, rng=0)
    history = json.loads((runs / "deep-sea-treasure-s0" / "evaluation.json").read_text())
    outcome = bench._train_sfols("deep-sea-treasure", policy, learner, weights, None, 0, True, runs)
    assert outcome.iterations == iterations and outcome.wall_time == history[-1]["wall_time"]

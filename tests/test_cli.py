"""The ``sb3-sfgpi`` command line: train, resume, evaluate, plot, and one-line errors for bad arguments."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest
from conftest import FEW_VALIDATION, tiny_four_room
from sfgpi_envs.domains import four_room

from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import DomainPreset
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.weights import random_weights, same_weight
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.run_settings import RunSettings

TRAIN = ["train", "four-room", "--iterations", "2", "--steps-per-iteration", "150", "--no-progress", "--seed", "1"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "fr"
    assert main([*TRAIN, *FEW_VALIDATION, "--out", str(out)]) == 0
    return out


def test_train_writes_a_run_directory(run_dir):
    config = json.loads((run_dir / "run.json").read_text())
    assert config["domain"] == "four-room" and config["algorithm"] == "ma-sfols"
    checkpoint = json.loads((run_dir / "checkpoint.json").read_text())
    assert checkpoint["iteration"] == 2 and checkpoint["timesteps"] == 300
    rows = (run_dir / "evaluation.csv").read_text().splitlines()
    assert rows[0].startswith("iteration,timesteps,n_policies,ccs_size,mean_return") and len(rows) == 3
    assert (run_dir / "policy_set" / "manifest.json").exists()
    assert any((run_dir / "tensorboard").iterdir()) and (run_dir / "logs" / "progress.csv").exists()
    preset = DomainPreset.from_dict("four-room", four_room())
    assert config["validation_weights"] == 4 and config["prune"] is preset.settings.prune  # --set over the preset's
    for key in ("gpi_set", "value_episodes", "eval_episodes", "ols_batch", "value_mode", "admit_together"):
        assert config[key] == getattr(preset.settings, key), key
    for removed in ("transfer", "gpi_behaviour", "replan"):
        assert removed not in config


def test_train_prints_a_header_first_and_no_progress_bars_off_a_terminal(tmp_path, capsys):
    out = tmp_path / "header"
    train = [arg for arg in TRAIN if arg != "--no-progress"]  # progress bars asked for, but not on a terminal
    assert main([*train, *FEW_VALIDATION, "--iterations", "1", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    header = captured.out.splitlines()[0]
    assert header.startswith("sb3-sfgpi train four-room: ma-sfols, seed 1, up to 1 x 150 steps, objectives: ")
    assert header.endswith(f"-> {out}")
    objectives = DomainPreset.from_dict("four-room", four_room()).objective_names({})
    assert objectives and ", ".join(objectives) in header
    assert "it/s" not in captured.err and "step/s" not in captured.err  # no tqdm bar: stderr is not a terminal


def test_resume_continues_to_more_iterations(run_dir, tmp_path):
    assert main([*TRAIN, "--out", str(run_dir)]) == 2  # exists: refused without --resume
    out = tmp_path / "random"
    args = [*TRAIN, *FEW_VALIDATION, "--algo", "random", "--out", str(out)]  # random weights never end before the cap
    assert main(args) == 0
    args[args.index("--iterations") + 1] = "3"
    assert main([*args, "--resume", "--set", "value_mode=shared"]) == 2  # would change the run
    assert main([*args, "--resume", "--set", "validation_weights=4", "--set", "eval_workers=0"]) == 0  # would not
    assert json.loads((out / "checkpoint.json").read_text())["iteration"] == 3
    assert len((out / "evaluation.csv").read_text().splitlines()) == 4


def test_value_mode_is_the_domains_unless_given(run_dir, tmp_path):
    assert json.loads((run_dir / "run.json").read_text())["value_mode"] == "joint"
    out = tmp_path / "shared-values"
    assert main([*TRAIN, *FEW_VALIDATION, "--iterations", "1", "--set", "value_mode=shared", "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["value_mode"] == "shared"


def test_refused_settings_leave_no_run_directory(tmp_path, capsys):
    out = tmp_path / "nested" / "refused"
    assert main([*TRAIN, "--learner", "bogus=1", "--out", str(out)]) == 2
    assert "learner argument 'bogus' is not taken from a run file" in capsys.readouterr().err and not out.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    assert main([*TRAIN, "--learner", "bogus=1", "--out", str(kept)]) == 2
    assert kept.is_dir()  # the user's own directory stays


def test_weights_match_within_their_rounding():
    # compare, plot and the examples match a run's weights to the ones asked for (run files round them)
    assert same_weight([0.4, 0.6], np.array([0.4004, 0.5996]))
    assert not same_weight([0.4, 0.6], [0.402, 0.598])


def test_evaluate_prints_per_agent_returns(run_dir, capsys):
    assert main(["evaluate", str(run_dir), "--w", "0.2", "0.3", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "agent_0: return [" in out and "agent_1: return [" in out


def test_evaluate_on_random_weights_prints_the_mean_of_their_w_returns(run_dir, capsys):
    assert main(["evaluate", str(run_dir), "--random-weights", "3", "--seed", "7"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("  3 Dirichlet(1) weights (seed 7): w·return (discounted, γ=0.95, mean over agents) ")
    values = []
    for w in random_weights(3, 3, rng=7):
        assert main(["evaluate", str(run_dir), "--w", *map(repr, w.tolist()), "--seed", "7"]) == 0
        out = capsys.readouterr().out
        values.append(np.mean([float(row.rsplit(" ", 1)[1]) for row in out.splitlines() if "w·return" in row]))
    assert line.split("mean over agents) ")[1].split(" ± ")[0] == f"{np.mean(values):.4f}"


def test_evaluate_members_runs_each_policy_of_the_gpi_set_alone(run_dir, capsys):
    """``--members``: GPI's mean w·return, then one line per policy of the set acting alone, each the return of that
    policy run by every agent on the same episodes."""
    w, seed = np.array([0.2, 0.3, 0.5]), 3
    argv = ["evaluate", str(run_dir), "--w", *map(str, w), "--episodes", "2", "--seed", str(seed), "--members"]
    assert main(argv) == 0
    out = capsys.readouterr().out.splitlines()
    per_agent = [float(row.rsplit(" ", 1)[1]) for row in out if ": return [" in row]
    gpi = [row for row in out if row.startswith("  GPI: ")]
    assert len(gpi) == 1 and float(gpi[0].rsplit(" ", 1)[1]) == pytest.approx(np.mean(per_agent), abs=1e-4)
    alone = [float(row.rsplit(" ", 1)[1]) for row in out if row.startswith("  alone: ")]
    config = json.loads((run_dir / "run.json").read_text())
    policy_set = GPIPolicy.load(run_dir / "policy_set").members()
    if config.get("gpi_set", "all") == "ccs":
        policy_set = policy_set.ccs_policies()
    assert len(alone) == len(policy_set) >= 2
    env = four_room()["make_env"](**config["env_kwargs"])
    for index, printed in enumerate(alone):
        result = run_episodes(env, policy_set.subset([index]).joint_policy(w), 2, 0.95, seed=seed)
        expected = np.mean([w @ result.mean_discounted(agent) for agent in result.discounted])
        assert printed == pytest.approx(expected, abs=1e-4)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["evaluate", "RUN", "--w", "0.5", "0.5"], "length 3"),
        (["evaluate", "RUN", "--w", "1", "-1", "0"], "non-negative"),
        (["evaluate", "RUN", "--w", "0", "0", "0"], "all zero"),
        (["evaluate", "NOT_A_RUN", "--w", "1", "0", "0"], "not a run directory"),
        (["evaluate", "RUN", "--w", "1", "0", "0", "--seed", "-1"], "--seed must be 0 or more"),
        (["evaluate", "RUN", "--random-weights", "0"], "--random-weights must be in [1, 1000000], got 0"),
        (["evaluate", "RUN", "--random-weights", "2", "--members"], "--members needs --w"),
        (["train", "no-such-domain"], "unknown domain"),
        (["train", "four-room", "--set", "bogus=1", "--out", "NOT_A_RUN"], "--set bogus: unknown setting"),
        (["train", "four-room", "--set", "prune", "--out", "NOT_A_RUN"], "--set expects KEY=VALUE"),
        (["train", "four-room", "--set", "value_mode=gpi", "--out", "NOT_A_RUN"], "--set value_mode must be one of"),
        (["train", "four-room", "--set", "ols_batch=spread", "--out", "NOT_A_RUN"], "--set ols_batch must be one of"),
        (["train", "four-room", "--set", "sharing=experience", "--out", "NOT_A_RUN"], "--set sharing must be one of"),
        (["train", "four-room", "--set", "prune=yes", "--out", "NOT_A_RUN"], "--set prune must be true or false"),
        (["train", "four-room", "--set", "n_envs=0", "--out", "NOT_A_RUN"], "--set n_envs must be an integer in [1, "),
        (["train", "four-room", "--set", "episode_weights=all", "--out", "NOT_A_RUN"], "--set episode_weights must be"),
        (
            ["train", "four-room", "--set", "episode_weights=support", "--out", "NOT_A_RUN"],
            "policy must be 'ConditionedMlpPolicy', got 'TabularPolicy'",
        ),
        (
            ["train", "four-room", "--set", "rebind_support=1", "--out", "NOT_A_RUN"],
            "--set rebind_support must be true",
        ),
        (
            ["train", "four-room", "--set", "rebind_support=true", "--out", "NOT_A_RUN"],
            "it needs policy='ConditionedMlpPolicy' and validation_weights > 0, got 'TabularPolicy'",
        ),
        (
            ["train", "four-room", "--set", "validation_weights=0", "--set", "prune=true", "--out", "NOT_A_RUN"],
            "--set prune=true needs validation weights",
        ),
        (
            ["train", "four-room", "--algo", "random", "--set", "ols_batch=top", "--out", "NOT_A_RUN"],
            "--set ols_batch is only for --algo ma-sfols",
        ),
        (["plot", "NOT_A_RUN", "-o", "x.png"], "not a run directory"),
    ],
)
def test_bad_arguments_give_one_line_and_exit_code_2(run_dir, tmp_path, cli_exit, argv, message):
    argv = [str(run_dir) if a == "RUN" else str(tmp_path / a) if a == "NOT_A_RUN" else a for a in argv]
    code, stderr = cli_exit(argv)
    assert code == 2
    assert message in stderr and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1


def test_the_console_command_refuses_in_one_line_with_exit_code_2(run_dir):
    """The same through a fresh interpreter, as a user's shell runs it (the cases above run in this process)."""
    result = subprocess.run(
        [sys.executable, "-m", "sb3_sfgpi.cli", "evaluate", str(run_dir), "--w", "1", "-1", "0"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "non-negative" in result.stderr


@pytest.mark.parametrize(
    "option", [["--transfer"], ["--gpi-behaviour"], ["--replan"], ["--torch-threads", "2"], ["--prune"]]
)
def test_removed_train_options_are_unknown(tmp_path, capsys, option):
    out = tmp_path / "removed"
    with pytest.raises(SystemExit) as exit_info:
        main([*TRAIN, *option, "--out", str(out)])
    assert exit_info.value.code == 2 and f"unrecognized arguments: {option[0]}" in capsys.readouterr().err
    assert not out.exists()


def test_plot_draws_a_png(run_dir, tmp_path):
    output = tmp_path / "fig.png"
    assert main(["plot", str(run_dir), "-o", str(output)]) == 0
    assert output.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sharing_is_the_domains_unless_given(run_dir, tmp_path):
    assert json.loads((run_dir / "run.json").read_text())["sharing"] == four_room()["sharing"] == "independent"
    assert {info.agent for info in GPIPolicy.load(run_dir / "policy_set").infos} <= {"agent_0", "agent_1"}
    out = tmp_path / "shared"
    assert main([*TRAIN, *FEW_VALIDATION, "--iterations", "1", "--set", "sharing=shared", "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["sharing"] == "shared"
    assert [info.agent for info in GPIPolicy.load(out / "policy_set").infos] == ["shared"]  # one learner for both


def test_compare_evaluates_a_fixed_run_of_one_shared_learner_by_its_policies(run_dir, tmp_path):
    fixed = tmp_path / "fixed-shared"
    train = [*TRAIN, "--algo", "fixed", "--w", "0.2", "0.3", "0.5", "--iterations", "1", "--set", "sharing=shared"]
    assert main([*train, "--out", str(fixed)]) == 0
    out = tmp_path / "compare.json"
    compare = ["compare", str(run_dir), "--fixed", str(fixed), "--episodes", "1", "--workers", "0", "--no-baselines"]
    assert main([*compare, "-o", str(out)]) == 0  # no agent learned a policy of its own: both act by the shared one
    (row,) = [row for row in json.loads(out.read_text())["rows"] if row["method"] == "fixed"]
    assert row["label"] == "scalarized w=[0.2,0.3,0.5]"


def test_a_preset_is_a_domain_around_run_settings():
    data = four_room()
    settings = DomainPreset.from_dict("four-room", data).settings
    assert isinstance(settings, RunSettings) and settings.policy == data["learner_kwargs"]["policy"] == "TabularPolicy"
    assert settings.learner_kwargs == {key: v for key, v in data["learner_kwargs"].items() if key != "policy"}
    assert (settings.ols_batch, settings.validation_weights) == ("same-after-extrema", 100)
    assert settings.steps_per_iteration == 50_000 != RunSettings.steps_per_iteration
    lean = {key: value for key, value in data.items() if key != "steps_per_iteration"}
    assert DomainPreset.from_dict("four-room", lean).settings.steps_per_iteration == RunSettings.steps_per_iteration


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"sharing": "experience"}, "sharing must be one of independent, shared, got 'experience'"),
        ({"transfer": True}, "unknown preset key 'transfer'"),
        ({"seed": 3}, "unknown preset key 'seed'"),  # each run's own
        ({"learner_kwargs": {"gamma": 0.9}}, "learner_kwargs must be a dict with the learners' 'policy'"),
        ({"steps_per_iteration": 0}, "steps_per_iteration must be a positive integer, got 0"),
        ({"value_episodes": True}, "value_episodes must be an integer in"),
        ({"n_test_weights": 0}, "n_test_weights must be an integer in"),
    ],
)
def test_a_preset_with_a_wrong_key_or_value_is_refused_in_one_line(change, message):
    with pytest.raises(UsageError, match=f"domain 'four-room': {message}"):
        DomainPreset.from_dict("four-room", {**four_room(), **change})


def test_a_preset_without_a_required_key_is_refused():
    for key in ("make_env", "learner_kwargs", "iterations"):
        data = {name: value for name, value in four_room().items() if name != key}
        with pytest.raises(UsageError, match=f"domain 'four-room': the preset lacks '{key}'"):
            DomainPreset.from_dict("four-room", data)


def test_plot_mean_over_seeds_forward_fills_runs_that_ended_early():
    from sb3_sfgpi.plots import align_runs

    values = align_runs([{1: 1.0, 2: 2.0}, {1: 3.0}])
    np.testing.assert_allclose(values, [[1.0, 2.0], [3.0, 3.0]])


@pytest.mark.parametrize("key", ["prune", "admit_together"])
def test_a_preset_with_a_validation_rule_that_is_not_a_bool_is_refused(key):
    assert DomainPreset.from_dict("four-room", four_room()).settings.validation_weights > 0
    with pytest.raises(UsageError, match=f"{key} must be true or false, got 'yes'"):
        DomainPreset.from_dict("four-room", {**four_room(), key: "yes"})


def test_compare_takes_fixed_runs_of_the_same_env_and_refuses_others(run_dir, tmp_path, capsys):
    preset = DomainPreset.from_dict("four-room", four_room())
    assert preset.same_env({"observation_mode": "own"}, {"observation_mode": "own", "max_steps": 200})  # default
    assert preset.same_env({"goal_reward": [1.0, 1.0, 1.0]}, {})  # the default tuple, as run.json writes it
    assert not preset.same_env({"observation_mode": "own"}, {"observation_mode": "full"})
    fixed = tmp_path / "fixed"
    fixed_train = [*TRAIN, "--algo", "fixed", "--w", "0.2", "0.3", "0.5", "--iterations", "1"]
    assert main([*fixed_train, "--env", "max_steps=200", "--out", str(fixed)]) == 0
    compare = ["compare", str(run_dir), "--fixed", str(fixed), "--episodes", "1", "--workers", "0"]
    assert main([*compare, "-o", str(tmp_path / "compare.json")]) == 0
    rows = json.loads((tmp_path / "compare.json").read_text())["rows"]
    assert any(row["label"].startswith("scalarized") for row in rows)
    other = tmp_path / "other"
    assert main([*fixed_train, "--env", "max_steps=100", "--out", str(other)]) == 0
    capsys.readouterr()
    assert main(["compare", str(run_dir), "--fixed", str(other), "--episodes", "1", "--workers", "0"]) == 2
    assert "was trained on another env configuration" in capsys.readouterr().err


def test_an_ols_end_on_one_dominating_value_says_to_check_the_learners_steps(tmp_path, capsys):
    """Learners of 5 steps learn nothing: the extrema's values leave one CCS point and OLS ends with budget left. The
    result line must not call that set a CCS of the problem (minecart's first three policies end a run this way)."""
    tiny = ["--steps-per-iteration", "5", "--env", "max_steps=30", "--set", "n_test_weights=2"]
    argv = ["train", "four-room", "--iterations", "10", *tiny, "--set", "validation_weights=0", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "run")]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert ": 2 iterations, " in last and "CCS=1," in last  # ended by OLS after the extrema (two agents, d = 3)
    assert "the set is a CCS" not in last and "the learners need more steps: --steps-per-iteration)" in last


def test_an_ols_end_on_several_values_or_one_objective_says_the_set_is_a_ccs():
    from sb3_sfgpi.cli.train import _ols_end

    assert _ols_end(ccs_size=4, reward_dim=3) == _ols_end(ccs_size=1, reward_dim=1) == " (OLS ended: the set is a CCS)"


def test_the_logs_of_every_iteration_and_of_the_run_are_closed(tmp_path):
    """TensorBoard's writers (a thread and an open file each) of every iteration's learners end with the iteration,
    the run's own (logs/) with the run: a process that trains run after run does not gather them."""
    before = set(threading.enumerate())
    argv = [*tiny_four_room(), "--iterations", "3", *FEW_VALIDATION, "--no-progress", "--out", str(tmp_path / "run")]
    assert main(argv) == 0
    assert len(list((tmp_path / "run" / "tensorboard").iterdir())) == 6  # two learners in each of 3 iterations
    started = [t.name for t in threading.enumerate() if t not in before]
    assert [name for name in started if name != "tqdm_monitor"] == []  # tqdm's one monitor of the process stays

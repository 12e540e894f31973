"""Regressions of issue 45, "a run directory from elsewhere cannot touch the machine": what evaluate, compare and
--resume take from run.json is on an allow-list. Each failed on the code before the fix."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from conftest import tiny_four_room
from shared_runs import edited

from sb3_sfgpi.cli import main
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.trust import check_learner_kwargs

#: A traffic run of seconds: 20 simulated seconds, 8 steps, one test weight, no workers.
TINY_TRAFFIC = [
    "train", "traffic", "--env", "num_seconds=20", "--iterations", "1", "--steps-per-iteration", "8",
    "--set", "n_test_weights=1", "--set", "eval_workers=0", "--set", "validation_weights=0",
    "--learner", "learning_starts=0",
    "--learner", "batch_size=4", "--no-progress",
]  # fmt: skip
TINY_FOUR_ROOM = [*tiny_four_room(), "--set", "validation_weights=0", "--no-progress"]


@pytest.fixture(scope="module")
def traffic_run(tmp_path_factory) -> Path:
    pytest.importorskip("libsumo")
    out = tmp_path_factory.mktemp("trust") / "traffic"
    assert main([*TINY_TRAFFIC, "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def four_room_run(tmp_path_factory) -> Path:
    """A four-room run trained with ``--env render_mode=null`` (an argument a run file may not set)."""
    out = tmp_path_factory.mktemp("trust") / "four-room"
    assert main([*TINY_FOUR_ROOM, "--env", "render_mode=null", "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("sumo_args", ["--summary-output", "VICTIM"]),
        ("sumo_args", ["--tripinfo-output=VICTIM"]),
        ("additional_files", ["ADDITIONAL"]),
        ("actuated_file", "ADDITIONAL"),
        ("gui", True),
        ("render_mode", "human"),
    ],
)
def test_a_run_file_cannot_make_sumo_write_files_or_run_programs(traffic_run, tmp_path, capsys, key, value):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    additional = tmp_path / "outputs.add.xml"
    additional.write_text(f'<additional><edgeData id="x" file="{victim}" period="5"/></additional>')
    value = json.loads(json.dumps(value).replace("VICTIM", str(victim)).replace("ADDITIONAL", str(additional)))
    copy = edited(traffic_run, tmp_path, "env_kwargs", **{key: value})
    for argv in (
        ["evaluate", str(copy), "--w", "0.5", "0.5"],
        ["compare", str(copy), "--episodes", "1", "--workers", "0"],
        ["train", "traffic", "--out", str(copy), "--resume", "--iterations", "2", "--no-progress"],
    ):
        assert main(argv) == 2
        error = capsys.readouterr().err
        assert f"env argument {key!r} is not taken from a run file" in error and len(error.strip().splitlines()) == 1
    assert victim.read_text() == "precious"
    assert json.loads((copy / "run.json").read_text())["env_kwargs"][key] == value  # the resume wrote nothing


def test_the_allowed_env_arguments_of_a_run_file_still_evaluate(traffic_run, tmp_path, capsys):
    copy = edited(traffic_run, tmp_path, "env_kwargs", num_seconds=10, seed=3, early_change="ignore")
    assert main(["evaluate", str(copy), "--w", "0.5", "0.5"]) == 0
    copy = edited(traffic_run, tmp_path, "env_kwargs", num_seconds=-1)
    assert main(["evaluate", str(copy), "--w", "0.5", "0.5"]) == 2  # values: checked by the env
    assert "num_seconds" in capsys.readouterr().err


def test_an_option_given_again_on_the_command_line_vouches_for_the_run_file(four_room_run, tmp_path, capsys):
    copy = edited(four_room_run, tmp_path, "env_kwargs")
    resume = ["train", "four-room", "--iterations", "2", "--no-progress", "--out", str(copy), "--resume"]
    assert main(["evaluate", str(copy), "--w", "1", "0", "0"]) == 2
    assert main(resume) == 2
    assert "env argument 'render_mode' is not taken from a run file" in capsys.readouterr().err
    assert main([*resume, "--env", "render_mode=null"]) == 0


@pytest.mark.parametrize(
    ("learner", "message"),
    [
        ({"tensorboard_log": "/elsewhere"}, "learner argument 'tensorboard_log' is not taken from a run file"),
        ({"replay_buffer_class": "x"}, "'replay_buffer_class' must be one of MOReplayBuffer"),
        ({"policy_kwargs": {"activation_fn": "Tanh"}}, "policy argument 'activation_fn' is not taken"),
        ({"policy_kwargs": {"net_arch": [10**9]}}, "'net_arch' must be a list of at most 16 widths"),
        ({"policy_kwargs": [1]}, "'policy_kwargs' must be an object"),
        ({"policy_kwargs": {"n_heads": 0}}, "'n_heads' must be an integer in [1, 16], got 0"),
        ({"policy_kwargs": {"n_heads": True}}, "'n_heads' must be an integer in [1, 16], got True"),
        ({"policy_kwargs": {"member_average": 1}}, "'member_average' must be a number in [0, 1), got 1"),
        ({"policy_kwargs": {"member_average": "0.1"}}, "'member_average' must be a number in [0, 1), got '0.1'"),
    ],
)
def test_a_run_file_sets_only_allowed_learner_arguments(four_room_run, tmp_path, capsys, learner, message):
    copy = edited(four_room_run, tmp_path, "learner_kwargs", **learner)
    for argv in (
        ["evaluate", str(copy), "--w", "1", "0", "0"],
        ["plot", str(copy), "-o", str(tmp_path / "fig.png")],
        ["train", "four-room", "--out", str(copy), "--resume", "--iterations", "2", "--no-progress"],
    ):
        assert main(argv) == 2
        assert message in capsys.readouterr().err
    with pytest.raises(ValueError, match=re.escape(message)):
        MASFOLS.load(copy, env=None)


def test_train_refuses_up_front_a_learner_argument_its_resume_would_refuse(tmp_path, capsys):
    out = tmp_path / "run"
    assert main([*TINY_FOUR_ROOM, "--learner", "tensorboard_log=elsewhere", "--out", str(out)]) == 2
    assert "--learner: learner argument 'tensorboard_log' is not taken from a run file" in capsys.readouterr().err
    assert not out.exists()


def test_a_conditioned_networks_head_count_and_member_average_are_taken_from_a_run_file():
    check_learner_kwargs({"policy_kwargs": {"net_arch": [8], "n_heads": 2, "member_average": 1e-3}}, "run.json")

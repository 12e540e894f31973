"""``examples/learner_snapshots.py``: snapshots of fixed-weight learners, scored after training."""

from __future__ import annotations

import json

import pytest
from example_scripts import load_example

from sb3_sfgpi.cli import main

W = ["0.2", "0.3", "0.5"]


@pytest.fixture(scope="module")
def example():
    return load_example("learner_snapshots")


def test_the_last_snapshot_is_the_trained_learners(example, tmp_path, capsys):
    """The snapshots are of the learners `train --algo fixed` makes: the last one scores as that run's evaluation."""
    run = tmp_path / "fixed"
    fixed = ["train", "four-room", "--algo", "fixed", "--w", *W, "--iterations", "1", "--no-progress"]
    assert main([*fixed, "--steps-per-iteration", "3000", "--seed", "3", "--out", str(run)]) == 0
    trained = json.loads((run / "evaluation.json").read_text())[-1]["mean_return"]
    capsys.readouterr()
    out = tmp_path / "snapshots.json"
    example.main(["four-room", "--w", *W, "--steps", "3000", "--every", "1000", "--seed", "3", "--out", str(out)])
    rows = json.loads(out.read_text())
    assert [row["steps"] for row in rows] == [1000, 2000, 3000]
    assert rows[-1]["test"]["w·G"] == pytest.approx(trained, abs=1e-12)
    scores = [row["test"]["w·G"] for row in rows]
    assert len(set(scores)) == 3  # each snapshot is scored with its own network, not the final one
    lines = capsys.readouterr().out.splitlines()
    best = max(rows, key=lambda row: row["selection"]["w·G"])
    assert lines[-2] == f"last: steps 3000, test w·G={trained:.4f}"
    assert lines[-1] == f"best w·G: steps {best['steps']}, test w·G={best['test']['w·G']:.4f}"


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--w", "1", "0", "--steps", "10", "--every", "5"], "--w must have length 3"),
        (["--w", *W, "--steps", "10", "--every", "20"], "--every (20) must not exceed --steps (10)"),
        (["--w", *W, "--steps", "10", "--every", "5", "--selection-seed", "1002"], "must be --episodes apart"),
        (["--w", *W, "--steps", "10", "--every", "5", "--env", "nope=1"], "the four-room env refuses"),
        (["--w", *W, "--steps", "10", "--every", "5", "--learner", "nope=1"], "bad learner options"),
        (["--w", *W, "--steps", "0", "--every", "5"], "--steps must be at least 1"),
    ],
)
def test_bad_options_get_one_line_and_exit_2(example, capsys, options, message):
    with pytest.raises(SystemExit) as stop:
        example.main(["four-room", *options])
    assert stop.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in error

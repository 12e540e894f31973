"""The run directory: its layout, the order and atomicity of an iteration's files, and what a resume refuses."""

from __future__ import annotations

import csv
import json
import os
import stat

import pytest

import sb3_sfgpi.run_directory as run_directory_module
from sb3_sfgpi.common.serialization import atomic_write_bytes, atomic_write_json
from sb3_sfgpi.run_directory import SUMMARY_FIELDS, RunDirectory


def row(iteration: int, **extra) -> dict:
    """A history row: the summary fields and the details that only evaluation.json keeps."""
    summary = {
        "iteration": iteration,
        "timesteps": 100 * (iteration + 1),
        "n_policies": iteration + 2,
        "ccs_size": iteration + 1,
        "mean_return": 1.5 * iteration + 0.25,
        "mean_return_undiscounted": 2.0 * iteration,
        "expected_utility": 0.5 + iteration,
        "hypervolume": None,
        "wall_time": 1.0 + iteration,
        "eval_time": 0.125,
    }
    return {**summary, "weights_trained": {"agent_0": [1.0, 0.0]}, "test": [{"weights": [0.5, 0.5]}], **extra}


def checkpoint(n: int, **overrides) -> dict:
    """A well-formed checkpoint after ``n`` iterations, with ``overrides``."""
    state = {
        "iteration": n,
        "timesteps": 100 * n,
        "n_policies": n + 1,
        "schedule": {"kind": "ols", "ols": {"reward_dim": 2}},
        "next_weights": {"agent_0": [0.5, 0.5]},
        "policy_set": None,  # no set staged
    }
    return {**state, **overrides}


def record_writes(monkeypatch, fail_on: str | None = None) -> list[str]:
    """
    Wrap run_directory's atomic writers (the real ones still write) to record the file names in order.

    With ``fail_on``, the real write of that file fails when it flushes to disk (``os.fsync`` raises), after the
    payload went into the temporary file: the atomic writer must then leave the old file as it was.
    """
    written: list[str] = []

    def failing_fsync(fd):
        raise OSError(28, "No space left on device")

    def wrap(real):
        def recording(path, payload):
            written.append(os.path.basename(path))
            if os.path.basename(path) == fail_on:
                with monkeypatch.context() as patch:
                    patch.setattr(os, "fsync", failing_fsync)
                    return real(path, payload)
            return real(path, payload)

        return recording

    monkeypatch.setattr(run_directory_module, "atomic_write_json", wrap(atomic_write_json))
    monkeypatch.setattr(run_directory_module, "atomic_write_bytes", wrap(atomic_write_bytes))
    return written


# --- layout -----------------------------------------------------------------------------------------------------
def test_layout(tmp_path):
    run_dir = RunDirectory(tmp_path / "run")
    assert run_dir.path == tmp_path / "run" and str(run_dir) == str(tmp_path / "run")
    assert run_dir.policy_set_dir == tmp_path / "run" / "policy_set"
    assert run_dir.logs_dir == tmp_path / "run" / "logs"
    assert run_dir.tensorboard_dir == tmp_path / "run" / "tensorboard"
    assert run_dir.compare_file == tmp_path / "run" / "compare.json"
    assert not (run_dir.is_run() or run_dir.has_checkpoint() or run_dir.has_evaluations())
    assert not run_dir.path.exists()  # nothing is created before something is written

    run_dir.write_config({"seed": 1})
    written = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run_dir.is_run() and written == {"format": "sb3-sfgpi/run", "version": 1, "seed": 1}
    assert run_dir.read_config() == {"seed": 1}
    run_dir.write_iteration([row(1)], checkpoint(1))
    assert run_dir.has_checkpoint() and run_dir.has_evaluations()
    names = {p.name for p in run_dir.path.iterdir()}
    assert names == {"run.json", "evaluation.json", "evaluation.csv", "checkpoint.json"}  # no temporary files left


def test_write_iteration_writes_the_evaluations_then_the_checkpoint_last(tmp_path, monkeypatch):
    written = record_writes(monkeypatch)
    run_dir = RunDirectory(tmp_path)
    history = [row(1), row(2)]
    run_dir.write_iteration(history, checkpoint(2))
    assert written[-1] == "checkpoint.json" and written.count("checkpoint.json") == 1
    assert set(written) == {"evaluation.json", "evaluation.csv", "checkpoint.json"}

    assert json.loads((tmp_path / "evaluation.json").read_text()) == history  # the details included
    assert run_dir.read_checkpoint() == checkpoint(2)
    with open(tmp_path / "evaluation.csv", newline="") as handle:
        reader = csv.reader(handle)
        assert tuple(next(reader)) == SUMMARY_FIELDS
        assert len(list(reader)) == 2
    summary = run_dir.read_summary()
    assert [r["iteration"] for r in summary] == ["1", "2"]
    assert float(summary[1]["mean_return"]) == history[1]["mean_return"]
    assert summary[0]["hypervolume"] == ""  # None is an empty cell
    assert "weights_trained" not in summary[0]


def test_a_failed_checkpoint_write_leaves_the_previous_checkpoint_intact(tmp_path, monkeypatch):
    run_dir = RunDirectory(tmp_path)
    run_dir.write_iteration([row(1)], checkpoint(1))
    before = (tmp_path / "checkpoint.json").read_bytes()

    written = record_writes(monkeypatch, fail_on="checkpoint.json")
    with pytest.raises(OSError, match="No space left"):
        run_dir.write_iteration([row(1), row(2)], checkpoint(2))
    assert written[-1] == "checkpoint.json"
    assert (tmp_path / "checkpoint.json").read_bytes() == before
    state = run_dir.read_checkpoint()
    assert state == checkpoint(1)
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []  # the temporary file is removed
    # The evaluation files went ahead; a resume trusts the checkpoint's count and ignores the extra row.
    assert len(run_dir.read_history()) == 2
    assert run_dir.read_history(state["iteration"]) == [row(1)]


def test_runs_that_numbered_iterations_from_0_are_read_numbered_from_1(tmp_path):
    run_dir = RunDirectory(tmp_path)
    run_dir.write_iteration([row(0), row(1)], checkpoint(2))  # as written before 2026-11-23
    assert [r["iteration"] for r in run_dir.read_history()] == [1, 2]
    assert [r["iteration"] for r in run_dir.read_summary()] == ["1", "2"]
    assert run_dir.read_history()[1]["mean_return"] == row(1)["mean_return"]
    run_dir.write_iteration([row(0), row(2)], checkpoint(2))  # a gap is not a legacy run: refused
    with pytest.raises(ValueError, match="row 2 is not the summary of iteration 2"):
        run_dir.read_history()


# --- checkpoint and run description -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "content, message",
    [
        pytest.param("[]", "not a JSON object", id="list"),
        pytest.param("null", "not a JSON object", id="null"),
        pytest.param('{"iteration": 1', "not valid JSON", id="truncated"),
        pytest.param(checkpoint(1, schedule=None), "'schedule'", id="schedule-null"),
        pytest.param({k: v for k, v in checkpoint(1).items() if k != "schedule"}, "'schedule'", id="no-schedule"),
        pytest.param(checkpoint(1, schedule={"kind": "ols"}), "'schedule'", id="schedule-without-ols"),
        pytest.param(checkpoint(1, iteration="one"), "'iteration'", id="iteration-string"),
        pytest.param(checkpoint(1, iteration=True), "'iteration'", id="iteration-bool"),
        pytest.param(checkpoint(1, iteration=1.0), "'iteration'", id="iteration-float"),
        pytest.param(checkpoint(1, timesteps=-5), "'timesteps'", id="negative-timesteps"),
        pytest.param({k: v for k, v in checkpoint(1).items() if k != "n_policies"}, "'n_policies'", id="no-n"),
        pytest.param(checkpoint(1, next_weights=[[0.5, 0.5]]), "'next_weights'", id="next-weights-list"),
    ],
)
def test_read_checkpoint_refuses_a_malformed_checkpoint(tmp_path, content, message):
    text = content if isinstance(content, str) else json.dumps(content)
    (tmp_path / "checkpoint.json").write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        RunDirectory(tmp_path).read_checkpoint()
    assert "checkpoint" in str(error.value)


def test_read_checkpoint_accepts_a_finished_run_and_refuses_a_missing_file(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        RunDirectory(tmp_path).read_checkpoint()
    (tmp_path / "checkpoint.json").write_text(json.dumps(checkpoint(3, next_weights=None)))
    assert RunDirectory(tmp_path).read_checkpoint()["next_weights"] is None


def test_read_config_refuses_what_is_not_a_run(tmp_path):
    with pytest.raises(ValueError, match="not a run directory"):
        RunDirectory(tmp_path).read_config()
    (tmp_path / "run.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="not a JSON object"):
        RunDirectory(tmp_path).read_config()
    (tmp_path / "run.json").write_text('{"seed": ')
    with pytest.raises(ValueError, match="not valid JSON"):
        RunDirectory(tmp_path).read_config()


# --- history ----------------------------------------------------------------------------------------------------
def test_read_history_returns_the_first_rows_the_checkpoint_counts(tmp_path):
    run_dir = RunDirectory(tmp_path)
    history = [row(1), row(2), row(3)]
    run_dir.write_iteration(history, checkpoint(3))
    assert run_dir.read_history() == history
    assert run_dir.read_history(2) == history[:2]
    assert run_dir.read_history(0) == []
    assert run_dir.read_history(3) == history
    with pytest.raises(ValueError, match="does not hold the checkpoint's rows"):
        run_dir.read_history(4)


def test_read_history_refuses_an_evaluation_that_is_not_a_list(tmp_path):
    (tmp_path / "evaluation.json").write_text('{"iteration": 0}')
    with pytest.raises(ValueError, match="evaluation"):
        RunDirectory(tmp_path).read_history()


def test_read_summary_needs_an_evaluation(tmp_path):
    with pytest.raises(ValueError, match="no evaluation.csv"):
        RunDirectory(tmp_path).read_summary()


# --- temporary directories --------------------------------------------------------------------------------------
def test_temporary_directory_is_removed_by_remove_temporary():
    run_dir = RunDirectory.temporary()
    try:
        assert run_dir.path.is_dir() and run_dir.path.name.startswith("sfgpi_run_")
        run_dir.write_iteration([row(1)], checkpoint(1))
        assert run_dir.has_checkpoint()
    finally:
        run_dir.remove_temporary()
    assert not run_dir.path.exists()
    run_dir.remove_temporary()  # twice is harmless


def test_remove_temporary_deletes_nothing_of_a_normal_directory(tmp_path):
    run_dir = RunDirectory(tmp_path / "run")
    run_dir.write_config({"seed": 0})
    run_dir.write_iteration([row(1)], checkpoint(1))
    run_dir.remove_temporary()
    assert run_dir.is_run() and run_dir.has_checkpoint() and run_dir.has_evaluations()
    assert RunDirectory(tmp_path / "run").read_checkpoint() == checkpoint(1)


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_files_written_atomically_get_the_mode_the_umask_gives(tmp_path, umask, mode):
    previous = os.umask(umask)
    try:
        atomic_write_json(tmp_path / "run.json", {"a": 1})
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "run.json").stat().st_mode) == mode
    assert json.loads((tmp_path / "run.json").read_text()) == {"a": 1}


def test_software_records_each_training_process_from_the_checkpoints_iteration_and_refuses_another_file(tmp_path):
    run = RunDirectory(tmp_path)
    run.record_software({"torch": "1"})
    run.write_iteration([row(1), row(2)], checkpoint(2))
    run.record_software({"torch": "2"})
    records = json.loads((tmp_path / "software.json").read_text())
    assert records == [{"from_iteration": 0, "torch": "1"}, {"from_iteration": 2, "torch": "2"}]
    (tmp_path / "software.json").write_text('{"torch": "1"}')
    with pytest.raises(ValueError, match="software record .* is not a JSON list"):
        run.record_software({"torch": "3"})

"""The run directory: its layout, the order and atomicity of an iteration's files, and what a resume refuses."""

from __future__ import annotations

import csv
import json
import os
import stat

import numpy as np
import pytest

import sb3_sfgpi.run_directory as run_directory_module
from sb3_sfgpi.common.serialization import atomic_write_bytes, atomic_write_json
from sb3_sfgpi.gpi import GPIPolicy
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
    assert not (run_dir.is_run() or run_dir.has_checkpoint() or run_dir.has_evaluations() or run_dir.has_policy_set())
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


# --- policy set -------------------------------------------------------------------------------------------------
@pytest.fixture
def policy_set(make_random_tabular) -> GPIPolicy:
    rng = np.random.default_rng(0)
    policies = GPIPolicy()
    for seed in range(4):
        w = rng.dirichlet(np.ones(3))
        policies.add(make_random_tabular(seed), weights=w, value=rng.normal(size=3), agent=f"agent_{seed % 2}")
    return policies


def commit(run_dir: RunDirectory, policy_set, iteration: int = 1) -> None:
    """Π staged by an iteration and committed by its checkpoint."""
    run_dir.stage_policy_set(policy_set, iteration)
    run_dir.write_iteration([row(i) for i in range(1, iteration + 1)], checkpoint(iteration))


def test_load_policy_set_returns_the_first_n_policies(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    with pytest.raises(ValueError, match="no policy set"):
        run_dir.load_policy_set()
    commit(run_dir, policy_set)
    assert run_dir.has_policy_set()
    obs = np.array([[0, 0, 0], [1, 2, 1], [2, 3, 0]])
    everything = run_dir.load_policy_set()
    assert len(everything) == 4
    np.testing.assert_allclose(everything.successor_features(obs), policy_set.successor_features(obs))
    for n in (0, 1, 3):
        loaded = run_dir.load_policy_set(n)
        assert len(loaded) == n
        for mine, theirs in zip(loaded.infos, policy_set.infos[:n], strict=True):
            np.testing.assert_allclose(mine.weights, theirs.weights)
            np.testing.assert_allclose(mine.value, theirs.value)
            assert mine.agent == theirs.agent
        if n:
            np.testing.assert_allclose(loaded.successor_features(obs), policy_set.successor_features(obs)[:n])


def test_load_policy_set_restores_pi_as_it_was_at_a_checkpoint(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    policy_set.retire(0, 2)  # retired after iteration 2
    policy_set.retire(2, 3)  # retired after iteration 3: a save made after the checkpoint of iteration 2
    commit(run_dir, policy_set)
    assert [i.agent for i in run_dir.load_policy_set().infos] == [policy_set.infos[i].agent for i in (1, 3)]
    at_2 = run_dir.load_policy_set(3, iteration=2, record=True)  # the checkpoint of iteration 2 counted 3
    assert [info.retired for info in at_2.infos] == [2, None, None]
    members = run_dir.load_policy_set(3, iteration=2)
    np.testing.assert_allclose(members.successor_features(np.array([[1, 2, 1]])),
                               policy_set.subset([1, 2]).successor_features(np.array([[1, 2, 1]])))  # fmt: skip


def test_load_policy_set_refuses_more_policies_than_saved(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set)
    with pytest.raises(ValueError, match="holds 4 policies, the checkpoint 5"):
        run_dir.load_policy_set(5)


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


# --- Π committed by its checkpoint ------------------------------------------------------------------------------
def features(policy_set) -> np.ndarray:
    return policy_set.successor_features(np.array([[0, 0, 0], [1, 2, 1], [2, 3, 0]]))


def test_a_set_staged_without_its_checkpoint_is_never_read_and_its_files_go(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set.subset([0, 1]))
    committed_files = files_of(run_dir.policy_set_dir)
    run_dir.stage_policy_set(policy_set, 2)  # iteration 2 staged Π; its writer was killed before the checkpoint
    assert files_of(run_dir.policy_set_dir) >= committed_files  # not one committed file written over
    for loaded in (run_dir.load_policy_set(), GPIPolicy.load(run_dir.policy_set_dir)):
        np.testing.assert_array_equal(features(loaded), features(policy_set.subset([0, 1])))
    run_dir.commit_policy_set()  # what a resume does first: the checkpoint did not name it, so it goes
    assert files_of(run_dir.policy_set_dir) == committed_files


def test_a_set_its_checkpoint_named_is_read_and_committed_after_a_kill(tmp_path, policy_set, monkeypatch):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set.subset([0, 1]))
    with monkeypatch.context() as patch:  # killed between the checkpoint and the commit
        patch.setattr(RunDirectory, "commit_policy_set", lambda self: None)
        commit(run_dir, policy_set, 2)
    assert (run_dir.policy_set_dir / "manifest.next.json").is_file()
    np.testing.assert_array_equal(features(run_dir.load_policy_set()), features(policy_set))  # the checkpoint's
    np.testing.assert_array_equal(features(GPIPolicy.load(run_dir.policy_set_dir)), features(policy_set.subset([0, 1])))
    run_dir.commit_policy_set()
    assert sorted(files_of(run_dir.policy_set_dir)) == ["manifest.json", *(f"policy_00{i}.0002.pt" for i in range(4))]
    np.testing.assert_array_equal(features(GPIPolicy.load(run_dir.policy_set_dir)), features(policy_set))


def test_a_checkpoint_naming_a_set_that_is_not_there_is_refused(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set)
    state = json.loads((tmp_path / "checkpoint.json").read_text())
    (tmp_path / "checkpoint.json").write_text(json.dumps({**state, "policy_set": "0" * 64}))
    with pytest.raises(ValueError, match="does not hold the policy set that checkpoint.json names"):
        run_dir.load_policy_set()
    (tmp_path / "checkpoint.json").write_text(json.dumps({**state, "policy_set": "not a digest"}))
    with pytest.raises(ValueError, match="'policy_set' must be null or a SHA-256 digest"):
        run_dir.read_checkpoint()


def files_of(directory) -> set[str]:
    return {path.name for path in directory.iterdir()}

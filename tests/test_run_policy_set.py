"""Π in a run directory: staged by an iteration, committed by its checkpoint, read as of a checkpoint."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_run_directory import checkpoint, row

from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import (
    commit_policy_set,
    load_policy_set,
    policy_set_manifest,
    stage_policy_set,
    staged_digest,
)


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
    stage_policy_set(run_dir, policy_set, iteration)
    write_checkpoint(run_dir, iteration)
    commit_policy_set(run_dir)


def write_checkpoint(run_dir: RunDirectory, iteration: int) -> None:
    """The checkpoint of ``iteration``, naming the staged Π, as the OLS callback writes it."""
    run_dir.write_iteration(
        [row(i) for i in range(1, iteration + 1)], checkpoint(iteration, policy_set=staged_digest(run_dir))
    )


def test_load_policy_set_returns_the_first_n_policies(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    with pytest.raises(ValueError, match="no policy set"):
        load_policy_set(run_dir)
    commit(run_dir, policy_set)
    assert policy_set_manifest(run_dir) is not None
    obs = np.array([[0, 0, 0], [1, 2, 1], [2, 3, 0]])
    everything = load_policy_set(run_dir)
    assert len(everything) == 4
    np.testing.assert_allclose(everything.successor_features(obs), policy_set.successor_features(obs))
    for n in (0, 1, 3):
        loaded = load_policy_set(run_dir, n)
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
    assert [i.agent for i in load_policy_set(run_dir).infos] == [policy_set.infos[i].agent for i in (1, 3)]
    at_2 = load_policy_set(run_dir, 3, iteration=2, record=True)  # the checkpoint of iteration 2 counted 3
    assert [info.retired for info in at_2.infos] == [2, None, None]
    members = load_policy_set(run_dir, 3, iteration=2)
    np.testing.assert_allclose(members.successor_features(np.array([[1, 2, 1]])),
                               policy_set.subset([1, 2]).successor_features(np.array([[1, 2, 1]])))  # fmt: skip


def test_load_policy_set_refuses_more_policies_than_saved(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set)
    with pytest.raises(ValueError, match="holds 4 policies, the checkpoint 5"):
        load_policy_set(run_dir, 5)


# --- Π committed by its checkpoint ------------------------------------------------------------------------------
def features(policy_set) -> np.ndarray:
    return policy_set.successor_features(np.array([[0, 0, 0], [1, 2, 1], [2, 3, 0]]))


def test_a_set_staged_without_its_checkpoint_is_never_read_and_its_files_go(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set.subset([0, 1]))
    committed_files = files_of(run_dir.policy_set_dir)
    stage_policy_set(run_dir, policy_set, 2)  # iteration 2 staged Π; its writer was killed before the checkpoint
    assert files_of(run_dir.policy_set_dir) >= committed_files  # not one committed file written over
    for loaded in (load_policy_set(run_dir), GPIPolicy.load(run_dir.policy_set_dir)):
        np.testing.assert_array_equal(features(loaded), features(policy_set.subset([0, 1])))
    commit_policy_set(run_dir)  # what a resume does first: the checkpoint did not name it, so it goes
    assert files_of(run_dir.policy_set_dir) == committed_files


def test_a_set_its_checkpoint_named_is_read_and_committed_after_a_kill(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set.subset([0, 1]))
    stage_policy_set(run_dir, policy_set, 2)
    write_checkpoint(run_dir, 2)  # killed between the checkpoint and the commit
    assert (run_dir.policy_set_dir / "manifest.next.json").is_file()
    np.testing.assert_array_equal(features(load_policy_set(run_dir)), features(policy_set))  # the checkpoint's
    np.testing.assert_array_equal(features(GPIPolicy.load(run_dir.policy_set_dir)), features(policy_set.subset([0, 1])))
    commit_policy_set(run_dir)
    assert sorted(files_of(run_dir.policy_set_dir)) == ["manifest.json", *(f"policy_00{i}.0002.pt" for i in range(4))]
    np.testing.assert_array_equal(features(GPIPolicy.load(run_dir.policy_set_dir)), features(policy_set))


def test_a_checkpoint_naming_a_set_that_is_not_there_is_refused(tmp_path, policy_set):
    run_dir = RunDirectory(tmp_path)
    commit(run_dir, policy_set)
    state = json.loads((tmp_path / "checkpoint.json").read_text())
    (tmp_path / "checkpoint.json").write_text(json.dumps({**state, "policy_set": "0" * 64}))
    with pytest.raises(ValueError, match="does not hold the policy set that checkpoint.json names"):
        load_policy_set(run_dir)
    (tmp_path / "checkpoint.json").write_text(json.dumps({**state, "policy_set": "not a digest"}))
    with pytest.raises(ValueError, match="'policy_set' must be null or a SHA-256 digest"):
        run_dir.read_checkpoint()


def files_of(directory) -> set[str]:
    return {path.name for path in directory.iterdir()}

"""RunSettings: one description of a run's settings, written to run.json and read back the same; the loop's cap."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from parallel_chain import make_chain_runner

from sb3_sfgpi.callbacks import OLSCallback, learn_iterations
from sb3_sfgpi.evaluation import EvaluationConfig
from sb3_sfgpi.run_settings import EPISODE_WEIGHTS, OLS_BATCHES, SHARINGS, VALUE_MODES, RunSettings
from sb3_sfgpi.schedules import OLSSchedule

counts = st.integers(min_value=0, max_value=10**6)
weights = st.lists(st.floats(min_value=0, max_value=1), min_size=2, max_size=4)
RUN_SETTINGS = st.builds(
    RunSettings,
    policy=st.sampled_from(["TabularPolicy", "MlpPolicy", "ConditionedMlpPolicy"]),
    weights=st.one_of(st.sampled_from(["ols", "random"]), weights),
    ols_batch=st.sampled_from(OLS_BATCHES),
    steps_per_iteration=counts,
    learner_kwargs=st.dictionaries(st.sampled_from(["gamma", "learning_rate", "batch_size"]), st.floats(0, 1)),
    test_weights=st.lists(weights, min_size=1, max_size=3),
    seed=counts,
    value_mode=st.sampled_from(VALUE_MODES),
    value_episodes=counts,
    eval_episodes=counts,
    gpi_set=st.sampled_from(["all", "ccs"]),
    validation_weights=counts,
    prune=st.booleans(),
    admit_together=st.booleans(),
    sharing=st.sampled_from(SHARINGS),
    n_envs=counts,
    pool_replay=st.booleans(),
    episode_weights=st.sampled_from(EPISODE_WEIGHTS),
    rebind_support=st.booleans(),
)


@settings(max_examples=50, deadline=None)
@given(RUN_SETTINGS)
def test_settings_written_to_run_json_read_back_the_same(run_settings):
    stored = json.loads(json.dumps({"format": "sb3-sfgpi/run", "domain": "x", **run_settings.to_json()}))
    assert RunSettings.stored(stored, "run.json") == run_settings
    assert list(run_settings.to_json()) == list(RunSettings.names())


def test_a_run_json_without_a_setting_names_it():
    stored = RunSettings().to_json()
    del stored["prune"]
    with pytest.raises(ValueError, match=r"run.json lacks the settings \['prune'\]: not a run of MASFOLS"):
        RunSettings.stored(stored, "run.json")


@pytest.mark.parametrize("added", [{"episode_weights": "support"}, {"rebind_support": True}])
def test_a_run_json_from_before_a_setting_was_added_has_its_default(added):
    stored = RunSettings(**added).to_json()
    for name in added:
        del stored[name]  # a run written before the setting: it had the default
    assert RunSettings.stored(stored, "run.json") == RunSettings()


def test_a_run_json_of_a_removed_setting_goes_on_only_at_the_value_kept():
    """A run written with ``snapshots`` (removed) at 0 is this version's run; at 3 it is refused, not run without."""
    stored = {**RunSettings().to_json(), "snapshots": 0}
    assert RunSettings.stored(stored, "run.json") == RunSettings()
    with pytest.raises(ValueError, match=r"run.json is of a run with \{'snapshots': 3\}, which this version no longer"):
        RunSettings.stored({**stored, "snapshots": 3}, "run.json")


@pytest.mark.parametrize("cap", [0, -1])
def test_the_loop_refuses_a_cap_below_one_iteration(cap):
    ols = OLSCallback(OLSSchedule(), 10, EvaluationConfig([[0.5, 0.5]]))
    with pytest.raises(ValueError, match="max_iterations must be positive or None"):
        learn_iterations(make_chain_runner(), ols, max_iterations=cap)
    assert not ols.started  # refused before anything ran

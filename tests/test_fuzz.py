"""Fuzzing of what a user or a damaged disk hands the package: run files, policy-set manifests, CLI arguments.

Every input either works or is refused with one line (``ValueError`` in the API, exit code 2 on the CLI): never a
traceback, never another exception type. ``FUZZ_EXAMPLES=300`` tries 300 fresh random examples per surface; the
default run tries the same 40 every time, so that a red test is a reproducible one.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import train_tiny_run
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from sb3_sfgpi.cli import main
from sb3_sfgpi.gpi import MANIFEST, CorruptPolicySetError, GPIPolicy

FUZZ = settings(
    max_examples=int(os.environ.get("FUZZ_EXAMPLES", "40")),
    derandomize="FUZZ_EXAMPLES" not in os.environ,  # the default run tries the same examples every time
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=8), children, max_size=3),
    max_leaves=6,
)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return train_tiny_run(tmp_path_factory.mktemp("fuzz") / "run")


def damaged_copy(run_dir: Path, tmp_path: Path, file: str, key: str | None, value) -> Path:
    """A copy of the run whose ``file`` has ``key`` set to ``value`` (the whole file when ``key`` is None)."""
    copy = tmp_path / "copy"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run_dir, copy)
    path = copy / file
    data = json.loads(path.read_text())
    if key is None:
        data = value
    elif isinstance(data, list):
        data[0][key] = value
    else:
        data[key] = value
    path.write_text(json.dumps(data))
    return copy


RUN_KEYS = ["domain", "env_kwargs", "learner_kwargs", "test_weights", "gpi_set", "seed", "version", None]
CHECKPOINT_KEYS = ["iteration", "timesteps", "n_policies", "schedule", "next_weights", "policy_set", None]


@FUZZ
@given(
    file_and_key=st.sampled_from(
        [("run.json", key) for key in RUN_KEYS]
        + [("checkpoint.json", key) for key in CHECKPOINT_KEYS]
        + [("evaluation.json", key) for key in ("iteration", "mean_return", None)]
    ),
    value=JSON,
)
@example(file_and_key=("checkpoint.json", "next_weights"), value={"": {}})  # found by CI's run
@example(file_and_key=("run.json", "env_kwargs"), value={"": None})
@example(file_and_key=("checkpoint.json", "policy_set"), value="0" * 64)  # a set that is not there
def test_damaged_run_files_give_one_line_errors(run_dir, tmp_path, capsys, file_and_key, value):
    file, key = file_and_key
    copy = damaged_copy(run_dir, tmp_path, file, key, value)
    for argv in (
        ["evaluate", str(copy), "--w", "0.2", "0.3", "0.5"],
        ["train", "four-room", "--out", str(copy), "--resume", "--iterations", "1", "--no-progress"],
        ["plot", str(copy), "-o", str(tmp_path / "fig.png")],
    ):
        assert main(argv) in (0, 2)
        error = capsys.readouterr().err
        assert "Traceback" not in error and len(error.strip().splitlines()) <= 1


@pytest.mark.parametrize("file", ["run.json", "checkpoint.json", "evaluation.json"])
def test_a_json_nested_too_deep_gives_one_line(run_dir, tmp_path, capsys, file):
    copy = damaged_copy(run_dir, tmp_path, file, None, None)
    (copy / file).write_text("[" * 100_000 + "]" * 100_000)
    assert main(["evaluate", str(copy), "--w", "0.2", "0.3", "0.5"]) == (0 if file == "evaluation.json" else 2)
    assert main(["train", "four-room", "--out", str(copy), "--resume", "--no-progress"]) == 2
    error = capsys.readouterr().err
    assert "is not valid JSON" in error and "Traceback" not in error


@FUZZ
@given(
    key=st.sampled_from(["reward_dim", "observation_space", "action_space", "network", "policies", "version"]),
    value=JSON,
)
def test_damaged_manifests_load_or_raise_corrupt_policy_set_error(run_dir, tmp_path, key, value):
    copy = damaged_copy(run_dir, tmp_path, f"policy_set/{MANIFEST}", key, value)
    try:
        policy_set = GPIPolicy.load(copy / "policy_set")
    except CorruptPolicySetError:
        return
    if len(policy_set):  # an empty list of policies is an empty set
        assert np.isfinite(policy_set.successor_features(np.zeros(14, dtype=np.int64))).all()


@FUZZ
@given(
    w=st.lists(st.floats() | st.integers(-3, 3), min_size=0, max_size=4),
    episodes=st.integers(-2, 2),
    seed=st.integers(-(2**33), 2**33),
    gpi_set=st.sampled_from(["all", "ccs"]),
)
def test_evaluate_arguments_work_or_give_one_line(run_dir, cli_exit, w, episodes, seed, gpi_set):
    argv = ["evaluate", str(run_dir), "--w", *map(str, w), "--episodes", str(episodes), "--seed", str(seed)]
    code, error = cli_exit([*argv, "--gpi-set", gpi_set])  # argparse exits on a malformed command line
    assert code in (0, 2) and "Traceback" not in error
    assert code == 0 or error.strip()


OPTION_VALUE = st.sampled_from(["0", "1", "-1", "0.5", "abc", "", "1e400", "nan", "true", "[1]"])
TRAIN_OPTION = st.one_of(
    st.tuples(st.sampled_from(["--iterations", "--steps-per-iteration", "--seed"]), OPTION_VALUE),
    st.tuples(st.sampled_from(["--workers", "--algo", "--w", "--policy"]), OPTION_VALUE),
    st.tuples(
        st.just("--set"),
        st.builds(
            "{}={}".format,
            st.sampled_from(["n_test_weights", "validation_weights", "prune", "ols_batch", "sharing", "nosuch", ""]),
            OPTION_VALUE,
        ),
    ),
    st.tuples(
        st.sampled_from(["--env", "--learner"]),
        st.builds(
            "{}={}".format,
            st.sampled_from(["gamma", "batch_size", "learning_rate", "observation_mode", "size", "nosuch", ""]),
            OPTION_VALUE,
        ),
    ),
)


@FUZZ
@given(options=st.lists(TRAIN_OPTION, max_size=4))
def test_train_arguments_work_or_give_one_line(tmp_path, cli_exit, options):
    argv = ["train", "four-room", "--iterations", "1", "--steps-per-iteration", "60", "--set", "n_test_weights=1"]
    argv += ["--set", "validation_weights=0"]  # what is fuzzed is the arguments, not validation (an option may set it)
    argv += [part for option in options for part in option]  # later options override the small defaults
    out = tmp_path / "run"
    shutil.rmtree(out, ignore_errors=True)
    code, error = cli_exit([*argv, "--no-progress", "--out", str(out)])  # argparse exits on a malformed line
    assert code in (0, 2) and "Traceback" not in error
    assert code == 0 or error.strip()

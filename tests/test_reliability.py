"""Regressions of issue 12 (no silent wrong answers on bad input): each of these failed on the code before the fix."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from conftest import FIG1_TABULAR_KWARGS
from momdp import Fig1MOMDP

from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.sfdqn import SFDQN


def test_huge_weights_are_normalised_without_overflow():
    np.testing.assert_array_equal(validate_weights([1e308, 1e308, 0.0], 3), [0.5, 0.5, 0.0])
    np.testing.assert_allclose(validate_weights([5e-324, 0.0], 2), [1.0, 0.0])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"gamma": 2.0}, "gamma must be a number in"),
        ({"gamma": -0.1}, "gamma must be a number in"),
        ({"gamma": float("nan")}, "gamma must be a number in"),
        ({"batch_size": 0}, "batch_size must be a positive integer"),
        ({"batch_size": 2.5}, "batch_size must be a positive integer"),
    ],
)
def test_out_of_range_learner_options_are_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        SFDQN("TabularPolicy", Fig1MOMDP(), **{**FIG1_TABULAR_KWARGS, **overrides})


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--iterations", "0"], "--iterations must be positive, got 0"),
        (["--steps-per-iteration", "0"], "--steps-per-iteration must be positive, got 0"),
        (["--learner", "gamma=2"], "gamma must be a number in [0, 1], got 2"),
        (["--learner", "batch_size=0"], "batch_size must be a positive integer, got 0"),
    ],
)
def test_train_refuses_zero_budgets_and_bad_learner_options(tmp_path, argv, message):
    command = [sys.executable, "-m", "sb3_sfgpi.cli", "train", "four-room", "--out", str(tmp_path / "run"), *argv]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_numpy_scalars_are_accepted_as_options():
    model = SFDQN("TabularPolicy", Fig1MOMDP(), gamma=np.float32(0.9), batch_size=np.int64(4), learning_starts=0)
    assert model.gamma == pytest.approx(0.9) and model.batch_size == 4

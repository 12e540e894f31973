"""SFDQN save/load round trips (tabular and MLP) and the logger's scalarised and per-objective returns."""

from __future__ import annotations

import csv
import io
import zipfile

import numpy as np
import pytest
import torch as th
from momdp import Fig1MOMDP, all_observations
from stable_baselines3.common.logger import configure

from sb3_sfgpi.sfdqn import SFDQN


@pytest.mark.parametrize("policy", ["TabularPolicy", "MlpPolicy"])
def test_save_load_round_trip(tmp_path, policy):
    one_hot = policy == "MlpPolicy"
    model = SFDQN(
        policy, Fig1MOMDP(one_hot=one_hot), weights=[0.8, 0.2], learning_rate=0.3 if one_hot is False else 1e-3,
        gamma=1.0, learning_starts=0, batch_size=8, train_freq=1, seed=0,
    )  # fmt: skip
    model.learn(120)
    if not one_hot:  # a table learns little in 120 steps: make ψ non-trivial
        table = model.policy.sf_net.table
        table.set_dense(th.randn((table.n_rows, table.width)).numpy())
    model.save(tmp_path / "model.zip")

    for env in (None, Fig1MOMDP(one_hot=one_hot)):
        loaded = SFDQN.load(tmp_path / "model.zip", env=env)
        assert loaded.reward_dim == 2
        np.testing.assert_array_equal(loaded.weights, model.weights)
        np.testing.assert_array_equal(loaded.policy.weights.cpu().numpy(), model.policy.weights.cpu().numpy())
        observations = all_observations(one_hot)
        np.testing.assert_array_equal(loaded.successor_features(observations), model.successor_features(observations))
        for w in (None, [1.0, 0.0], [0.0, 1.0], [0.3, 0.7]):
            np.testing.assert_array_equal(
                loaded.predict(observations, deterministic=True, w=w)[0],
                model.predict(observations, deterministic=True, w=w)[0],
            )
    # Training can go on after loading.
    loaded.learn(8)


def test_a_tabular_model_keeps_its_learning_rate_and_loads_one_saved_with_sgd(tmp_path):
    """The table's optimizer (:class:`StepSize`) saves its rate in SGD's layout: zips saved when a torch SGD held the
    rate load, and a damaged state is refused in one line."""
    model = SFDQN("TabularPolicy", Fig1MOMDP(), weights=[0.8, 0.2], learning_rate=0.3, learning_starts=0, seed=0)
    model.save(tmp_path / "model.zip")
    assert SFDQN.load(tmp_path / "model.zip").policy.optimizer.param_groups[0]["lr"] == pytest.approx(0.3)
    sgd = th.optim.SGD([th.empty(0, requires_grad=True)], lr=0.25)  # what held the rate before
    for state, rate in ((sgd.state_dict(), 0.25), ({"state": {}, "param_groups": [{"params": [0]}]}, None)):
        with zipfile.ZipFile(tmp_path / "model.zip") as source, zipfile.ZipFile(tmp_path / "old.zip", "w") as old:
            for item in source.infolist():
                if item.filename == "policy.optimizer.pth":
                    buffer = io.BytesIO()
                    th.save(state, buffer)
                    old.writestr(item, buffer.getvalue())
                else:
                    old.writestr(item, source.read(item))
        if rate is None:
            with pytest.raises(ValueError, match="one parameter group with an 'lr'"):
                SFDQN.load(tmp_path / "old.zip")
        else:
            assert SFDQN.load(tmp_path / "old.zip").policy.optimizer.param_groups[0]["lr"] == rate


def test_logger_records_the_scalarised_and_per_objective_returns(tmp_path, make_tabular_sfdqn):
    w = np.array([0.25, 0.75])
    model = make_tabular_sfdqn(w, stats_window_size=5)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)  # 50 episodes of 4 steps, one log line per episode

    with open(tmp_path / "progress.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) >= 40
    for row in rows:
        per_objective = np.array([float(row["rollout/ep_rew_mean_0"]), float(row["rollout/ep_rew_mean_1"])])
        assert float(row["rollout/ep_rew_mean"]) == pytest.approx(w @ per_objective, rel=1e-5)
    # The last line is w · (mean vector return of the last 5 episodes).
    mean_return = np.mean([info["r_vec"] for info in model.ep_info_buffer], axis=0)
    assert len(model.ep_info_buffer) == 5
    np.testing.assert_allclose(
        [float(rows[-1]["rollout/ep_rew_mean_0"]), float(rows[-1]["rollout/ep_rew_mean_1"])], mean_return, rtol=1e-5
    )
    assert float(rows[-1]["rollout/ep_rew_mean"]) == pytest.approx(w @ mean_return, rel=1e-5)
    # Vector returns vary between episodes (exploration), so the per-objective columns are not trivially equal.
    assert len({row["rollout/ep_rew_mean_0"] for row in rows}) > 1

"""The deep-peer benchmark compares what it says: both sides make the same number of gradient updates per env step."""

from __future__ import annotations

import inspect
import sys
from pathlib import Path

import pytest

from sb3_sfgpi.sfdqn.conditioned import ConditionedPolicy

pytest.importorskip("mo_gymnasium")
if str(Path(__file__).resolve().parents[1]) not in sys.path:  # the benchmarks are not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import bench_deep_peer as bench  # noqa: E402

WARM = 150  # past both sides' learning_starts (100)


def test_our_side_makes_the_presets_updates_per_step_over_the_support(monkeypatch):
    updates = []
    td_update = ConditionedPolicy.td_update

    def counted(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        updates.append(len(self.support))
        return td_update(self, *args, **kwargs)

    monkeypatch.setattr(bench, "WARMUP", WARM)
    advance = bench._ours()
    monkeypatch.setattr(ConditionedPolicy, "td_update", counted)
    advance(20)
    assert updates == [len(bench.SUPPORT)] * 20 * bench.MLP_LEARNER["gradient_steps"]


def test_the_peer_makes_as_many_once_past_its_warm_up(monkeypatch):
    """GPI-LS updates once per step until ``dynamics_rollout_starts``, which the untimed warm-up passes; past it (here
    set to 0), ``gradient_updates`` minibatches per step."""
    gpi_pd = pytest.importorskip("morl_baselines.multi_policy.gpi_pd.gpi_pd")
    assert bench.WARMUP > inspect.signature(gpi_pd.GPIPD).parameters["dynamics_rollout_starts"].default
    batches = []
    sample = gpi_pd.GPIPD._sample_batch_experiences

    def counted(self):  # noqa: ANN001, ANN202
        batches.append(self.global_step)
        return sample(self)

    monkeypatch.setattr(bench, "WARMUP", WARM)
    monkeypatch.setitem(bench.GPI_LS_SETTINGS, "dynamics_rollout_starts", 0)
    monkeypatch.setattr(gpi_pd.GPIPD, "_sample_batch_experiences", counted)
    advance = bench._gpi_ls(gpi_pd.GPIPD, 3)
    batches.clear()
    advance(20)
    assert batches == [step for step in range(WARM + 1, WARM + 21) for _ in range(3)]

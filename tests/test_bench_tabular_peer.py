"""The tabular-peer benchmark compares what it says: both sides make the same number of TD updates per env step."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy

pytest.importorskip("mo_gymnasium")
if str(Path(__file__).resolve().parents[1]) not in sys.path:  # the benchmarks are not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import bench_tabular_peer as bench  # noqa: E402


@pytest.mark.parametrize("updates", list(bench.PAIRS))
def test_our_side_updates_a_batch_of_that_many_transitions_per_step(updates, monkeypatch):
    batches = []
    sample = TabularPolicy.minibatch_rows

    def counted(buffer: MOReplayBuffer, batch_size: int):  # noqa: ANN202
        batches.append(batch_size)
        return sample(buffer, batch_size)

    monkeypatch.setattr(TabularPolicy, "minibatch_rows", staticmethod(counted))
    bench._sfdqn(bench.PAIRS[updates][0])(50)
    assert batches == [updates] * 50  # one batch per step from the first (learning_starts 0, train_freq 1)


@pytest.mark.parametrize("updates", list(bench.PAIRS))
def test_the_peer_updates_that_many_times_per_step(updates, monkeypatch):
    """Per step MOQLearning updates its step's transition (``update``) and, with Dyna, ``dyna_updates`` transitions
    drawn from its model (``random_transition``)."""
    moq = pytest.importorskip("morl_baselines.single_policy.ser.mo_q_learning")
    from morl_baselines.common.model_based.tabular_model import TabularModel

    calls = {"update": 0, "random_transition": 0}
    for cls, name in ((moq.MOQLearning, "update"), (TabularModel, "random_transition")):
        method = getattr(cls, name)

        def counted(self, *args, _method=method, _name=name, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            calls[_name] += 1
            return _method(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, counted)
    bench._moq_learning(moq.MOQLearning, bench.PAIRS[updates][1])(20)
    assert calls == {"update": 20, "random_transition": 20 * (updates - 1)}


def test_without_morl_baselines_one_row_says_so(monkeypatch):
    monkeypatch.setitem(sys.modules, "morl_baselines", None)  # import fails as where it is not installed
    monkeypatch.setitem(sys.modules, "morl_baselines.single_policy.ser.mo_q_learning", None)
    assert [row.candidate for row in bench.run(quick=True)] == [bench.MORL_MISSING]

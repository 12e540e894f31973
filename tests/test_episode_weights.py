"""Episodes that act for weights drawn from the support (``episode_weights="support"``, GPI-LS's behaviour): what is
drawn, when, what joins Π, exact resume, and what is refused."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from momdp import Fig1MOMDP
from stable_baselines3.common.callbacks import BaseCallback
from test_conditioned import _masfols

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.episode_weights import EpisodeWeights


class WeightsSeen(BaseCallback):
    """After every joint step: the iteration, the episodes the learner finished so far, and its weights."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[int, int, tuple[float, ...]]] = []

    def _on_step(self) -> bool:
        (learner,) = self.model.learners.values()
        self.seen.append((self.model.iteration, learner._episode_num, tuple(learner.weights.tolist())))
        return True


@pytest.fixture(scope="module")
def support_episodes() -> tuple[MASFOLS, WeightsSeen]:
    model, seen = _masfols(episode_weights="support"), WeightsSeen()
    model.learn(max_iterations=3, callback=seen)
    return model, seen


def test_each_episode_acts_for_a_weight_of_the_support_and_members_keep_their_own(support_episodes):
    model, seen = support_episodes
    trained = [tuple(row["weights_trained"]["agent_0"]) for row in model.history]
    for iteration in range(3):
        rows = [(episodes, w) for it, episodes, w in seen.seen if it == iteration]
        support = np.array(trained[: iteration + 1])
        assert all(np.isclose(support, w, atol=1e-9).all(axis=1).any() for _, w in rows)  # weights OLS visited
        switches = [(a, b) for a, b in itertools.pairwise(rows) if a[1] != b[1]]
        assert all(a[0] != b[0] for a, b in switches), switches  # weights change only where an episode ended
    assert len({w for it, _, w in seen.seen if it == 2}) > 1  # the last iteration drew more than its own weight
    (learner,) = model.runner.learners.values()
    np.testing.assert_allclose(learner.weights, trained[-1])  # its own weight back
    for net, info in zip(model.callback.record.networks, model.callback.record.infos, strict=True):
        np.testing.assert_allclose(net.member_weights.cpu().numpy(), info.weights, atol=1e-7)


def test_a_resumed_run_draws_the_same_weights(support_episodes, tmp_path):
    model, _ = support_episodes
    _masfols(tmp_path / "run", episode_weights="support").learn(max_iterations=1)
    resumed = MASFOLS.load(tmp_path / "run", Fig1MOMDP(one_hot=True))
    assert resumed.settings.episode_weights == "support"
    resumed.learn(max_iterations=3)
    assert [row["mean_return"] for row in resumed.history] == [row["mean_return"] for row in model.history]


def test_drawing_weights_is_refused_for_learners_not_conditioned_on_them_and_unknown_kinds():
    with pytest.raises(ValueError, match="policy must be 'ConditionedMlpPolicy', got 'TabularPolicy'"):
        MASFOLS(Fig1MOMDP(), policy="TabularPolicy", episode_weights="support")
    with pytest.raises(ValueError, match=r"episode_weights must be one of \('own', 'support'\), got 'other'"):
        EpisodeWeights("other")

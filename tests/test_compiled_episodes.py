"""GPI's episodes over tables in one compiled call (``MultiAgentRunner.gpi_episodes``) against the same episodes
stepped in lockstep: validation's scores, returns, members followed and decisions, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_mlp_network
from gymnasium.spaces import Discrete
from hypothesis import given, settings
from hypothesis import strategies as st
from sfgpi_envs.four_room import FourRoomParallelEnv
from test_four_room_batched import SETTINGS

from sb3_sfgpi import GPIPolicy
from sb3_sfgpi.common.parallel_wrappers import SwapTerminationsTruncations
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.tabular import gpi_episodes
from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.validation import Scored, ValidationScorer

TABULAR = dict(policy="TabularPolicy", learning_starts=0, train_freq=1, batch_size=4)


def random_tables(
    env: FourRoomParallelEnv, seed: int, n_members: int, nvec: list[int] | None = None, n_actions: int = 4
) -> GPIPolicy:
    """Random tables of the env's observations (``nvec``: of another space) and ``n_actions`` actions, their default
    row random too, and a copy of the first member last (GPI follows both wherever it follows one)."""
    space = env.observation_space("agent_0")
    rng = np.random.default_rng(seed)
    policy_set = GPIPolicy()
    for k in range(n_members):
        net = TabularSFNetwork(space if nvec is None else type(space)(nvec), Discrete(n_actions), 3)
        rows = np.unique(rng.integers(0, net.table.n_rows, min(net.table.n_rows, 3_000)))
        rows = np.union1d(rows, np.arange(0, net.table.n_rows, max(net.table.n_rows // 169, 1)))  # flags all 0
        values = rng.normal(size=(len(rows), net.table.width)).astype(np.float32)
        net.table.set_rows(rows, values, rng.normal(size=net.table.width).astype(np.float32))
        policy_set.add(net, weights=rng.dirichlet(np.ones(3)), agent=f"agent_{k % 2}")
    policy_set.add(policy_set.networks[0], weights=[1 / 3] * 3, agent="agent_0")
    return policy_set


def scorers(env: FourRoomParallelEnv, n_weights: int, episodes: int) -> tuple[ValidationScorer, ValidationScorer, list]:
    """Validation stepped in lockstep, and in compiled calls (the runs of every call that ran compiled listed)."""
    runner = MultiAgentRunner(env, default_learner_factory(**TABULAR), seed=0, gamma=0.95)
    compiled = []

    def gpi_episodes_spied(*args, **kwargs):
        ran = runner.gpi_episodes(*args, **kwargs)
        compiled.append(ran is not None)
        return ran

    weights = np.random.default_rng(n_weights).dirichlet(np.ones(3), n_weights)
    stepped = ValidationScorer(weights, runner.rollout, episodes, 7, lockstep=runner.lockstep)
    in_one_call = ValidationScorer(
        weights, runner.rollout, episodes, 7, lockstep=runner.lockstep, gpi_episodes=gpi_episodes_spied
    )
    return stepped, in_one_call, compiled


def same(one: Scored, other: Scored) -> None:
    assert one.score == other.score and one.followed == other.followed
    for mine, theirs in zip(one.returns, other.returns, strict=True):
        assert mine.discounted.keys() == theirs.discounted.keys()
        for agent in mine.discounted:
            assert mine.discounted[agent].tobytes() == theirs.discounted[agent].tobytes()
            assert mine.undiscounted[agent].tobytes() == theirs.undiscounted[agent].tobytes()
    for mine, theirs in zip(one.decisions, other.decisions, strict=True):
        for a, b in zip(mine, theirs, strict=True):
            assert (a is None and b is None) or np.array_equal(a, b)


@settings(max_examples=25, deadline=None)
@given(
    kwargs=SETTINGS,
    n_members=st.integers(1, 4),
    n_weights=st.integers(2, 5),
    episodes=st.integers(1, 2),
    seed=st.integers(0, 2**16),
)
def test_compiled_episodes_score_what_the_lockstep_scores(kwargs, n_members, n_weights, episodes, seed):
    """The whole set, every member left out, and a larger set replayed from a smaller one's decisions: the same
    scores, returns, members followed and decisions, every run compiled."""
    env = FourRoomParallelEnv(**kwargs)
    policy_set = random_tables(env, seed, n_members)
    stepped, in_one_call, compiled = scorers(env, n_weights, episodes)
    whole = stepped(policy_set)
    same(whole, in_one_call(policy_set))
    left_out = zip(stepped.without_each(policy_set, whole), in_one_call.without_each(policy_set, whole), strict=True)
    for mine, theirs in left_out:
        same(mine, theirs)
    smaller = policy_set.subset([0])
    same(stepped.replayed(policy_set, stepped(smaller)), in_one_call.replayed(policy_set, in_one_call(smaller)))
    assert compiled and all(compiled) and stepped.rollouts == in_one_call.rollouts


def test_episodes_longer_than_the_first_room_go_on_where_they_were(monkeypatch):
    """Episodes of 200 steps overflow the trace's first room: the call goes on from the episode that found none, with
    the same runs as the lockstep's."""
    calls = []
    compiled = gpi_episodes._compiled

    def counted():
        kernel = compiled()
        return lambda *args: calls.append(kernel(*args)) or calls[-1]

    monkeypatch.setattr(gpi_episodes, "_compiled", counted)
    env = FourRoomParallelEnv(max_steps=200, starts=[(0, 9), (9, 12)])
    policy_set = random_tables(env, 3, 2)
    stepped, in_one_call, _ = scorers(env, 4, 2)
    same(stepped(policy_set), in_one_call(policy_set))
    assert [status for status, _, _ in calls][-1] == gpi_episodes.ENDED
    assert gpi_episodes.NO_ROOM in [status for status, _, _ in calls]


@pytest.mark.parametrize(("mode", "nvec", "n_actions"), [("xy", [4, 4], 4), ("own", [13, 13], 4), ("xy", None, 6)])
def test_what_the_tables_and_the_env_do_not_share_is_refused_as_in_the_lockstep(mode, nvec, n_actions):
    """Tables of a smaller grid than the env's, of observations without the env's object flags, or of more actions
    than the env has: validation refuses the first observation or action with the lockstep's error."""
    env = FourRoomParallelEnv(observation_mode=mode)
    policy_set = random_tables(env, 0, 2, nvec=nvec, n_actions=n_actions)
    errors = []
    for scorer in scorers(env, 3, 1)[:2]:
        with pytest.raises(ValueError) as error:
            scorer(policy_set)
        errors.append(str(error.value))
    assert errors[0] == errors[1] and ("observation" in errors[0] or "actions are" in errors[0])


def test_no_compiled_episodes_without_tables_or_the_envs_own_packed_step():
    """An MLP set, and an env behind a wrapper (what it changes the packed step would not), run no compiled call."""
    env = FourRoomParallelEnv()
    runner = MultiAgentRunner(env, default_learner_factory(**TABULAR), seed=0, gamma=0.95)
    args = (np.full((2, 3), 1 / 3), np.full(2, -1), [0, 1])
    assert runner.gpi_episodes(random_tables(env, 0, 1), *args) is not None
    mlp = GPIPolicy()
    mlp.add(random_mlp_network(0, 2, 4, 3), [1, 0, 0])
    assert runner.gpi_episodes(mlp, *args) is None
    wrapped = MultiAgentRunner(SwapTerminationsTruncations(env), default_learner_factory(**TABULAR), seed=0, gamma=0.9)
    assert wrapped.gpi_episodes(random_tables(env, 0, 1), *args) is None


def test_the_env_is_left_as_the_lockstep_leaves_it():
    """After the compiled episodes the shared env is where the lockstep leaves it: the same episode and the same
    action spaces' generators."""
    ends = []
    for compiled in (True, False):
        env = FourRoomParallelEnv()
        runner = MultiAgentRunner(env, default_learner_factory(**TABULAR), seed=0, gamma=0.95)
        policy_set = random_tables(env, 1, 2)
        scorer = ValidationScorer(
            np.full((3, 3), 1 / 3), runner.rollout, 2, 5, lockstep=runner.lockstep,
            gpi_episodes=runner.gpi_episodes if compiled else None,
        )  # fmt: skip
        scorer(policy_set)
        ends.append((env.packed_dynamics().state, [env.action_space(a).np_random.random() for a in env.agents]))
    assert np.array_equal(ends[0][0], ends[1][0]) and ends[0][1] == ends[1][1]

"""Admission in linear time: leave-one-out scores roll out again only where the member left out was decisive.

They must be the scores of full rollouts of every leave-one-out subset, to the last bit, and pruning must decide as
it does with full rollouts (issue 48, item 2).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import N_ACTIONS, N_STATES, REWARD_DIM
from parallel_chain import ParallelChainEnv
from sfgpi_envs.four_room import FourRoomParallelEnv

from sb3_sfgpi.admission import Admission
from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.validation import Scored, ValidationScorer


def chain_set(tables: list[np.ndarray]) -> GPIPolicy:
    """A set of the chain's ψ tables, shape ``(N_STATES, N_ACTIONS, REWARD_DIM)`` each."""
    policy_set = GPIPolicy()
    for table in tables:
        net = TabularSFNetwork(spaces.Discrete(N_STATES), spaces.Discrete(N_ACTIONS), REWARD_DIM)
        net.table.set_dense(table.reshape(N_STATES, -1))
        policy_set.add(net, weights=[0.5, 0.5])
    return policy_set


def chain_scorer(episodes: int = 1) -> ValidationScorer:
    env = ParallelChainEnv(3, staggered=True)  # agents in different states at every decision
    weights = Admission(4).weights(REWARD_DIM, seed=0)
    return ValidationScorer(weights, lambda policy, n, seed: run_episodes(env, policy, n, 0.9, seed=seed), episodes, 0)


def same_returns(a: Scored, b: Scored) -> bool:
    """The same score and discounted returns, to the last bit."""
    returns = all(
        x.discounted.keys() == y.discounted.keys()
        and all(np.array_equal(x.discounted[k], y.discounted[k]) for k in x.discounted)
        for x, y in zip(a.returns, b.returns, strict=True)
    )
    return a.score == b.score and returns


def same(a: Scored, b: Scored) -> bool:
    """The same score, returns, followed members and decisions, to the last bit."""
    decisions = all(
        all(np.array_equal(p, q) for p, q in zip(x, y, strict=True))  # observations, masks, actions
        for x, y in zip(a.decisions, b.decisions, strict=True)
    )
    return same_returns(a, b) and a.followed == b.followed and decisions


#: small integers: many exact ties between policies and between actions
TABLES = st.lists(
    st.lists(st.integers(0, 2), min_size=N_STATES * N_ACTIONS * REWARD_DIM, max_size=N_STATES * N_ACTIONS * REWARD_DIM),
    min_size=2,
    max_size=5,
).map(lambda rows: [np.array(row, dtype=np.float32).reshape(N_STATES, N_ACTIONS, REWARD_DIM) for row in rows])


@settings(max_examples=40, deadline=None)
@given(TABLES)
def test_leave_one_out_scores_are_those_of_full_rollouts(tables):
    policy_set, scorer = chain_set(tables), chain_scorer()
    scored = scorer(policy_set)
    for member in range(len(policy_set)):
        full = scorer(policy_set.subset(j for j in range(len(policy_set)) if j != member))
        assert same(scorer.without(policy_set, scored, member), full)
        if member not in scored.decisive_members():  # never decisive: GPI without it acts the same everywhere
            assert same_returns(full, scored)


@settings(max_examples=40, deadline=None)
@given(TABLES, st.integers(1, 3))
def test_scores_replayed_from_another_sets_decisions_are_those_of_full_rollouts(tables, added):
    scorer = chain_scorer()
    again = chain_set(tables + tables[:added])  # the same tables again: ties that change nothing
    new = chain_set(tables + [t[::-1].copy() for t in tables[:added]])  # other ones: they may change actions
    for policy_set in (again, new):
        for prefix in range(1, len(policy_set)):
            scored = scorer(policy_set.subset(range(prefix)))
            assert same(scorer.replayed(policy_set, scored), scorer(policy_set))
            assert same(scorer.replayed(policy_set.subset(range(prefix)), scored), scored)


@settings(max_examples=40, deadline=None)
@given(TABLES, st.lists(st.integers(0, N_STATES - 1), min_size=1, max_size=6), st.floats(0.0, 1.0))
def test_a_view_without_a_member_acts_as_the_subset(tables, states, w0):
    policy_set, w = chain_set(tables), np.array([w0, 1.0 - w0]) if 0 < w0 < 1 else np.array([0.5, 0.5])
    obs = np.array(states)
    actions, followed = policy_set.predict_followed(obs, w)
    np.testing.assert_array_equal(actions, policy_set.predict(obs, w)[0])
    q = np.stack([policy_set.subset([i]).q_values(obs, w) for i in range(len(policy_set))])  # (P, batch, A)
    for b, members in enumerate(followed):  # exactly those that attain GPI's value of the action taken
        chosen = q[:, b, actions[b]]
        assert members == set(np.flatnonzero(chosen == chosen.max()).tolist())
    for member in range(len(policy_set)):
        rest = policy_set.subset(j for j in range(len(policy_set)) if j != member)
        np.testing.assert_array_equal(policy_set.without(member).q_values(obs, w), rest.q_values(obs, w))
        np.testing.assert_array_equal(policy_set.without(member).predict(obs, w)[0], rest.predict(obs, w)[0])
        if all(members != {member} for members in followed):
            np.testing.assert_array_equal(rest.predict(obs, w)[0], actions)


@pytest.mark.parametrize(
    "device",
    [
        "cpu",
        pytest.param(
            "cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")]
        ),
    ],
)
def test_a_view_of_mlp_networks_without_a_member_gives_the_subsets_values(make_random_mlp, device):
    """On the GPU too: a stacked product's per-policy values must not depend on how many policies are stacked."""
    policy_set = GPIPolicy(device=device)
    for seed in range(5):
        policy_set.add(make_random_mlp(seed), weights=[1.0, 1.0, 1.0])
    obs = np.random.default_rng(0).random((32, 4)).astype(np.float32)
    w = np.array([0.2, 0.3, 0.5])
    for member in range(len(policy_set)):
        rest = policy_set.subset(j for j in range(len(policy_set)) if j != member)
        np.testing.assert_array_equal(policy_set.without(member).q_values(obs, w), rest.q_values(obs, w))


def test_decisions_are_traced_only_where_every_agent_acts_over_the_whole_set():
    policy_set = GPIPolicy()
    policy_set.add(
        TabularSFNetwork(spaces.Discrete(N_STATES), spaces.Discrete(N_ACTIONS), REWARD_DIM), [1, 0], agent="agent_0"
    )
    with pytest.raises(ValueError, match="whole set"):
        policy_set.joint_policy([0.5, 0.5], ["agent_0"], trace=[])
    with pytest.raises(IndexError):
        policy_set.without(1)


# --- Four-Room, learners trained briefly ----------------------------------------------------------------------------
class BruteForce(ValidationScorer):
    """Every leave-one-out subset rolled out at every weight (the rule before issue 48)."""

    def without(self, policy_set: GPIPolicy, scored: Scored, member: int) -> Scored:
        return self(policy_set.subset(j for j in range(len(policy_set)) if j != member))


class Counting(ValidationScorer):
    """Counts, for each set scored in full, the leave-one-out sets rolled out again from its episodes."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.rounds: list[tuple[Scored, int, int]] = []  # (the set's episodes, sets rolled out, weights rolled out)

    def without(self, policy_set: GPIPolicy, scored: Scored, member: int) -> Scored:
        if not self.rounds or self.rounds[-1][0] is not scored:
            self.rounds.append((scored, 0, 0))
        before = self.rollouts
        result = super().without(policy_set, scored, member)
        _, sets, weights = self.rounds[-1]
        self.rounds[-1] = (scored, sets + (self.rollouts > before), weights + self.rollouts - before)
        return result


@pytest.fixture(scope="module")
def four_room(tmp_path_factory):
    """Every candidate of a short Four-Room run (no validation), the env, and its rollout."""
    out = tmp_path_factory.mktemp("four-room") / "run"
    train = ["train", "four-room", "--iterations", "4", "--steps-per-iteration", "300", "--no-progress"]
    assert (
        main([*train, "--seed", "3", "--set", "n_test_weights=2", "--set", "validation_weights=0", "--out", str(out)])
        == 0
    )
    config = json.loads((out / "run.json").read_text())
    env = load_domain("four-room").build_env(config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)
    yield GPIPolicy.load(out / "policy_set"), lambda policy, n, seed: run_episodes(env, policy, n, gamma, seed=seed)
    env.close()


def pruned(record: GPIPolicy, scorer: ValidationScorer) -> tuple[list[tuple], list[int | None], float]:
    admission = Admission(6, prune=True)
    admission.start(scorer)
    policy_set = admission.admit(record, [], iteration=99)
    return (
        [(i.agent, i.iteration) for i in policy_set.infos],
        [i.retired for i in record.infos],
        admission._current(policy_set),
    )


def test_pruning_four_room_decides_as_full_rollouts_with_fewer(four_room):
    record, rollout = four_room
    weights = Admission(6).weights(record.reward_dim, seed=3)
    counting, brute = Counting(weights, rollout, 1, 3), BruteForce(weights, rollout, 1, 3)
    fast, slow = pruned(record.subset(range(len(record))), counting), pruned(record.subset(range(len(record))), brute)
    assert fast == slow  # the same members retired, in the same rounds, the same final score
    assert len(fast[0]) < len(record)  # something was retired: the comparison covers a retirement
    for scored, sets, rolled in counting.rounds:  # per round, only the decisive members' sets and weights
        decisive = scored.decisive_members()
        assert sets <= len(decisive)  # with the set's own episodes: at most |decisive| + 1 sets rolled out per round
        assert rolled == sum(len(scored.decisive(m)) for m in decisive)
    assert counting.rollouts < brute.rollouts


def test_every_leave_one_out_score_on_four_room_is_that_of_full_rollouts(four_room):
    record, rollout = four_room
    scorer = ValidationScorer(Admission(6).weights(record.reward_dim, seed=3), rollout, 1, 3)
    scored = scorer(record)
    for member in range(len(record)):
        assert same(
            scorer.without(record, scored, member), scorer(record.subset(j for j in range(len(record)) if j != member))
        )


def test_every_members_leave_one_out_episodes_stepped_together_are_those_of_one_member_at_a_time(four_room):
    """Pruning rolls the decisive weights of every member out in one lockstep, each row acting by GPI without its
    member: the same scores, returns, members followed and decisions as one member at a time without a lockstep."""
    record, rollout = four_room
    weights = Admission(6).weights(record.reward_dim, seed=3)
    runner = MultiAgentRunner(FourRoomParallelEnv(observation_mode="own"), gamma=0.95)
    together, alone = (
        ValidationScorer(weights, rollout, 1, 3, lockstep=runner.lockstep),
        ValidationScorer(weights, rollout, 1, 3),
    )
    scored = together(record)
    assert same(scored, alone(record))
    each = together.without_each(record, scored)
    assert len(each) == len(record) and sum(len(scored.decisive(m)) > 0 for m in range(len(record))) >= 2
    for member, without in enumerate(each):
        assert same(without, alone.without(record, scored, member))

"""Weight-conditioned successor features (``ConditionedMlpPolicy``): exact SFs for every support weight, GPI over the
support, Π members bound to their weights, safe files, exploration counted across calls of ``learn``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from momdp import Fig1MOMDP, observation, optimal_policy, optimal_value, policy_of, policy_value, successor_features

from sb3_sfgpi import MASFOLS, GPIPolicy
from sb3_sfgpi.common.weights import SAME_WEIGHT
from sb3_sfgpi.ols import unique_points
from sb3_sfgpi.policy_files import CorruptPolicySetError
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork
from sb3_sfgpi.sfdqn.training_state import restore_training_state, training_state

#: Weights whose optimal policy has no tie in any state (its SFs are unique): one per CCS point of different actions
SUPPORT = np.array([[0.8, 0.2], [0.3, 0.7]])
GAMMA = 0.9


@pytest.fixture(scope="module")
def trained() -> SFDQN:
    """One conditioned SFDQN (two heads, the default) trained for (0.8, 0.2) with the support above, on uniformly
    random transitions."""
    model = SFDQN(
        "ConditionedMlpPolicy",
        Fig1MOMDP(one_hot=True),
        weights=SUPPORT[0],
        learning_rate=1e-3,
        gamma=GAMMA,
        batch_size=64,
        train_freq=1,
        learning_starts=200,
        target_update_interval=100,
        exploration_initial_eps=1.0,
        exploration_final_eps=1.0,  # uniform behaviour: every pair is in the buffer
        buffer_size=5_000,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.set_weight_support(SUPPORT)
    model.learn(1_500)  # exact to 0.04 by 1,500 steps with one head or two (0.001 and 0.000 on 2026-11-29)
    return model


def _psi(model: SFDQN, state: int, w: np.ndarray) -> np.ndarray:
    device = model.policy.device
    obs = th.as_tensor(observation(state, one_hot=True), device=device).reshape(1, -1)
    with th.no_grad():
        return model.policy.sf_net(obs, th.as_tensor(w, dtype=th.float32, device=device))[0].cpu().numpy()


@pytest.mark.parametrize("w", SUPPORT.tolist())
def test_learns_the_optimal_successor_features_of_every_support_weight(trained, w):
    exact = successor_features(optimal_policy(w, GAMMA), GAMMA)
    for state in range(4):
        np.testing.assert_allclose(_psi(trained, state, np.array(w)), exact[state], atol=0.1)


@pytest.mark.parametrize("w", [*SUPPORT.tolist(), [0.5, 0.5], [0.9, 0.1], [0.1, 0.9]])
def test_gpi_over_the_support_acts_optimally(trained, w):
    assert _optimal_with_gpi(trained, w)


def _optimal_with_gpi(model: SFDQN, w: list[float]) -> bool:
    policy = policy_of(lambda s: model.predict(observation(s, one_hot=True), deterministic=True, w=w)[0])
    return np.dot(w, policy_value(policy, GAMMA)) >= optimal_value(w, GAMMA) - 1e-6


def test_members_of_the_set_are_bound_to_their_weights_and_saved_safely(trained, tmp_path):
    policy_set = GPIPolicy()
    for w in SUPPORT:
        policy_set.add(trained, weights=w)
    obs = np.eye(5, dtype=np.float32)[:4]
    for i, w in enumerate(SUPPORT):
        member = policy_set.networks[i]
        assert isinstance(member, ConditionedSFNetwork)
        np.testing.assert_allclose(member.member_weights.cpu().numpy(), w)
        expected = np.stack([_psi(trained, s, w) for s in range(4)])
        with th.no_grad():
            psi = member(th.as_tensor(obs, device=member.member_weights.device)).cpu().numpy()
        np.testing.assert_allclose(psi, expected, rtol=1e-5, atol=1e-4)  # batched: other roundings
    policy_set.save(tmp_path / "set")
    loaded = GPIPolicy.load(tmp_path / "set")
    assert loaded.networks[0].n_heads == trained.policy.sf_net.n_heads == 2  # every head saved and loaded
    for w in [[0.3, 0.7], [1.0, 0.0]]:
        np.testing.assert_array_equal(loaded.q_values(obs, w), policy_set.q_values(obs, w))
    state = th.load(tmp_path / "set" / "policy_001.pt", weights_only=True)
    state["member_weights"] = th.tensor([0.5, 0.5])  # the file says another policy than the manifest
    th.save(state, tmp_path / "set" / "policy_001.pt")
    with pytest.raises(CorruptPolicySetError, match="bound to the weights"):
        GPIPolicy.load(tmp_path / "set")
    manifest = json.loads((tmp_path / "set" / "manifest.json").read_text())
    assert manifest["network"]["n_heads"] == trained.policy.sf_net.n_heads
    for n_heads in (0, 17, "2", 1.0):
        manifest["network"]["n_heads"] = n_heads
        (tmp_path / "set" / "manifest.json").write_text(json.dumps(manifest))
        with pytest.raises(ValueError, match="n_heads must be an integer"):
            GPIPolicy.load(tmp_path / "set")


def test_the_target_bootstraps_from_the_lowest_head_and_every_head_learns_it():
    model = SFDQN(
        "ConditionedMlpPolicy", Fig1MOMDP(one_hot=True), weights=SUPPORT[0], gamma=GAMMA, batch_size=8,
        learning_starts=0, learning_rate=1e-3, policy_kwargs=dict(net_arch=[16, 16], n_heads=3), seed=0,
    )  # fmt: skip
    model.learn(20)
    policy = model.policy
    assert len(policy.sf_net.sf_net) == 3
    np.random.seed(5)  # the replay samples with numpy's global generator
    batch = model.replay_buffer.sample(8)
    np.random.seed(5)
    rows = th.arange(8, device=policy.device)
    with th.no_grad():
        w = policy.weights.expand(8, -1)
        next_actions = (policy.sf_net(batch.next_observations, w) @ policy.weights).argmax(dim=1)
        heads = policy.sf_net_target.heads(batch.next_observations, w)[:, rows, next_actions]  # (3, 8, d)
        lowest = (heads @ policy.weights).argmin(dim=0)
        target = batch.rewards + (1 - batch.dones) * GAMMA * heads[lowest, rows]
        current = policy.sf_net.heads(batch.observations, w)[:, rows, batch.actions.flatten()]
        expected = sum(th.nn.functional.smooth_l1_loss(current[h], target).item() for h in range(3))
    assert policy.td_update(model.replay_buffer, 8, GAMMA, 10.0) == pytest.approx(expected, rel=1e-5)
    assert not th.equal(heads[0], heads[1])  # the heads differ: the lowest one is a choice
    with pytest.raises(ValueError, match="at least one head"):
        SFDQN("ConditionedMlpPolicy", Fig1MOMDP(one_hot=True), policy_kwargs=dict(n_heads=0))


def test_exploration_steps_count_across_calls_of_learn():
    model = SFDQN(
        "ConditionedMlpPolicy", Fig1MOMDP(one_hot=True), exploration_steps=100, exploration_final_eps=0.1,
        learning_starts=1_000, policy_kwargs=dict(net_arch=[8]), seed=0,
    )  # fmt: skip
    model.learn(40)
    assert model.exploration_rate == pytest.approx(1.0 - 0.9 * 40 / 100)
    model.learn(40, reset_num_timesteps=False)
    assert model.exploration_rate == pytest.approx(1.0 - 0.9 * 80 / 100)
    model.learn(40, reset_num_timesteps=False)
    assert model.exploration_rate == pytest.approx(0.1)
    with pytest.raises(ValueError, match="exploration_steps"):
        SFDQN("MlpPolicy", Fig1MOMDP(one_hot=True), exploration_steps=0)


def test_support_is_for_conditioned_policies_and_survives_save_and_load(trained, tmp_path):
    with pytest.raises(ValueError, match="ConditionedMlpPolicy"):
        SFDQN("MlpPolicy", Fig1MOMDP(one_hot=True)).set_weight_support(SUPPORT)
    with pytest.raises(ValueError, match="non-negative"):
        trained.set_weight_support([[1.0, -1.0]])
    trained.save(tmp_path / "model.zip")
    loaded = SFDQN.load(tmp_path / "model.zip")
    np.testing.assert_array_equal(loaded.weight_support, SUPPORT)
    np.testing.assert_array_equal(loaded.policy.support.cpu().numpy(), SUPPORT.astype(np.float32))
    obs = observation(0, one_hot=True)
    for w in ([0.3, 0.7], [0.5, 0.5]):
        assert loaded.predict(obs, deterministic=True, w=w)[0] == trained.predict(obs, deterministic=True, w=w)[0]


def _masfols(run_dir=None, **kwargs) -> MASFOLS:
    learner_kwargs = dict(
        gamma=GAMMA, learning_rate=1e-3, learning_starts=100, train_freq=1, batch_size=32, buffer_size=5_000,
        target_update_interval=100, exploration_steps=600, policy_kwargs=dict(net_arch=[32, 32]),
    )  # fmt: skip
    return MASFOLS(
        Fig1MOMDP(one_hot=True), policy="ConditionedMlpPolicy", steps_per_iteration=300, learner_kwargs=learner_kwargs,
        run_dir=run_dir, seed=0, **kwargs,
    )  # fmt: skip


@pytest.fixture(scope="module")
def three_iterations() -> MASFOLS:
    model = _masfols()
    model.learn(max_iterations=3)
    return model


def test_one_learner_goes_on_over_the_iterations_for_the_support(three_iterations):
    (learner,) = three_iterations.runner.learners.values()
    assert learner.num_timesteps == 900 and learner.replay_buffer.buffer_size == 5_000  # not cut to one iteration
    trained = [np.array(row["weights_trained"]["agent_0"]) for row in three_iterations.history]
    np.testing.assert_allclose(learner.weight_support, unique_points(np.array(trained), SAME_WEIGHT))
    record = three_iterations.callback.record
    for net, info in zip(record.networks, record.infos, strict=True):
        assert isinstance(net, ConditionedSFNetwork)
        np.testing.assert_allclose(net.member_weights.cpu().numpy(), info.weights, atol=1e-7)


def test_a_resumed_run_goes_on_exactly_and_members_keep_the_network_they_joined_with(three_iterations, tmp_path):
    """A run resumed after its first iteration ends as the one never stopped; its first member of Π is still the
    learner's network as it was when the member joined, while the learner went on learning."""
    first = _masfols(tmp_path / "run").learn(max_iterations=1).callback.record.networks[0]
    joined = {key: value.clone() for key, value in first.state_dict().items()}
    resumed = MASFOLS.load(tmp_path / "run", Fig1MOMDP(one_hot=True))
    resumed.learn(max_iterations=3)
    kept = resumed.callback.record.networks[0].state_dict()
    assert all(th.equal(value.cpu(), kept[key].cpu()) for key, value in joined.items())
    latest = next(iter(resumed.runner.learners.values())).policy.sf_net.state_dict()
    assert not all(th.equal(value.cpu(), latest[key].cpu()) for key, value in joined.items() if key != "member_weights")
    assert [row["mean_return"] for row in resumed.history] == [row["mean_return"] for row in three_iterations.history]
    (learner,) = resumed.runner.learners.values()
    (reference,) = three_iterations.runner.learners.values()
    for key, value in reference.policy.state_dict().items():
        assert th.equal(value.cpu(), learner.policy.state_dict()[key].cpu()), key
    assert [path.name for path in (tmp_path / "run" / "learners").iterdir()] == ["iteration_003.pt"]


def test_a_saved_learner_state_that_does_not_fit_is_refused(three_iterations):
    (learner,) = three_iterations.runner.learners.values()
    state = training_state(learner)
    state["replay"]["rewards"] = th.zeros(10, 1, 3)  # three objectives for a learner of two
    with pytest.raises(ValueError, match="'rewards' does not fit"):
        restore_training_state(learner, state)
    state = training_state(learner)
    state["replay"]["observations"][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        restore_training_state(learner, state)
    state = training_state(learner)
    key = next(iter(state["policy"]))
    state["policy"][key] = state["policy"][key].to(th.float64).fill_(1e39)  # finite in float64, inf in float32
    with pytest.raises(ValueError, match="non-finite values"):
        restore_training_state(learner, state)
    state = training_state(learner)
    del state["optimizer"]
    with pytest.raises(ValueError, match="does not fit"):
        restore_training_state(learner, state)


def test_a_one_head_file_from_before_two_became_the_default_is_refused_in_one_line_and_loads_when_told(tmp_path):
    model = SFDQN("ConditionedMlpPolicy", Fig1MOMDP(one_hot=True), policy_kwargs=dict(net_arch=[8], n_heads=1))
    model.policy_kwargs = {"net_arch": [8]}  # as saved before n_heads=2 became the default
    model.save(tmp_path / "one_head.zip")
    with pytest.raises(ValueError, match="do not fit the policy") as refused:
        SFDQN.load(tmp_path / "one_head.zip")
    assert len(str(refused.value).splitlines()) == 1
    loaded = SFDQN.load(tmp_path / "one_head.zip", custom_objects={"policy_kwargs": {"net_arch": [8], "n_heads": 1}})
    assert loaded.policy.sf_net.n_heads == 1
    for mine, theirs in zip(loaded.policy.parameters(), model.policy.parameters(), strict=True):
        assert th.equal(mine, theirs)


def test_a_candidate_offered_for_another_weight_joins_bound_to_it(trained):
    """A conditioned learner's network offered to Π for another weight of its support joins bound to that weight:
    its SFs are the network's for it, not for the learner's own weights."""
    from sb3_sfgpi.admission import Admission, Candidate

    record = GPIPolicy()
    other = SUPPORT[1]
    pi = Admission(validation_weights=0, prune=False, together=False).admit(
        record, [Candidate(trained, np.zeros(2), "agent_0", other)], iteration=1
    )
    for policy_set in (record, pi):
        assert policy_set.infos[0].weights.tolist() == other.tolist()
        for state in range(3):
            obs = observation(state, one_hot=True).reshape(1, -1)
            np.testing.assert_allclose(  # stacked over the set's members: a rounding of its own
                policy_set.successor_features(obs)[0, 0], _psi(trained, state, other), rtol=1e-6, atol=1e-6
            )
    assert not all(np.allclose(_psi(trained, s, other), _psi(trained, s, SUPPORT[0]), atol=1e-3) for s in range(3))


def test_rebinding_offers_the_latest_network_at_every_earlier_weight_and_validation_decides(monkeypatch, capsys):
    """With ``rebind_support`` every iteration offers Π, after its own policy, the learner's latest network bound to
    each earlier weight of OLS's support; the offers that validation admits join bound to those weights, and each one
    it leaves out is named with the weights it was offered for."""
    from sb3_sfgpi import admission

    offered = []
    admit = admission.Admission.admit

    def spied(self, record, candidates, iteration):
        offered.append([(c.learner, None if c.weights is None else c.weights.tolist()) for c in candidates])
        return admit(self, record, candidates, iteration)

    monkeypatch.setattr(admission.Admission, "admit", spied)
    model = _masfols(validation_weights=8, rebind_support=True, verbose=1)
    model.learn(max_iterations=3)
    (learner,) = model.runner.learners.values()
    trained = [row["weights_trained"]["agent_0"] for row in model.history]
    for k, candidates in enumerate(offered):
        earlier = [w for w in model.callback.schedule.ols.weights[: k + 1] if not np.allclose(w, trained[k])]
        assert [w for _, w in candidates[1:]] == [np.asarray(w).tolist() for w in earlier]
        assert candidates[0][1] is None and all(c is learner for c, _ in candidates)
    rebound = [i for i in model.callback.record.infos if not np.allclose(i.weights, trained[i.iteration - 1])]
    assert rebound  # here iteration 3's network joined for (1, 0)
    assert all(any(np.allclose(info.weights, w) for w in model.callback.schedule.ols.weights) for info in rebound)
    kept_out = sum(len(candidates) - 1 for candidates in offered) - len(rebound)
    assert kept_out > 0 and capsys.readouterr().out.count("agent_0's policy for w = [") == kept_out


def test_rebinding_needs_conditioned_learners_and_validation_weights():
    with pytest.raises(ValueError, match="rebind_support"):
        _masfols(rebind_support=True)
    with pytest.raises(ValueError, match="rebind_support"):
        MASFOLS(Fig1MOMDP(one_hot=True), policy="TabularPolicy", validation_weights=4, rebind_support=True)


def test_members_copy_the_running_average_of_the_network_where_one_is_kept(tmp_path):
    def model(average: float) -> SFDQN:
        return SFDQN(
            "ConditionedMlpPolicy", Fig1MOMDP(one_hot=True), weights=SUPPORT[0], batch_size=8, learning_starts=0,
            learning_rate=1e-2, policy_kwargs=dict(net_arch=[16], member_average=average), seed=0,
        )  # fmt: skip

    plain, averaged = model(0.0), model(0.25)
    assert plain.policy.sf_net_average is None and plain.policy.member_net is plain.policy.sf_net
    policy = averaged.policy
    averaged.learn(10)
    before = [p.clone() for p in policy.sf_net_average.parameters()]
    np.random.seed(1)
    policy.td_update(averaged.replay_buffer, 8, GAMMA, 10.0)
    for old, new, online in zip(before, policy.sf_net_average.parameters(), policy.sf_net.parameters(), strict=True):
        th.testing.assert_close(new, old + 0.25 * (online - old))  # a quarter of the way to the network stepped
        assert not th.equal(new, online)
    policy_set = GPIPolicy()
    policy_set.add(averaged, weights=SUPPORT[1])
    obs = th.as_tensor(np.eye(5, dtype=np.float32)[:4], device=policy.device)
    w = th.as_tensor(SUPPORT[1], dtype=th.float32, device=policy.device)
    with th.no_grad():
        th.testing.assert_close(policy_set.networks[0](obs), policy.sf_net_average(obs, w))
    averaged.save(tmp_path / "model.zip")
    loaded = SFDQN.load(tmp_path / "model.zip")
    for mine, theirs in zip(loaded.policy.sf_net_average.parameters(), policy.sf_net_average.parameters(), strict=True):
        th.testing.assert_close(mine, theirs.cpu())
    for refused in (1.0, -0.1, "0.1", True):
        with pytest.raises(ValueError, match="member_average"):
            model(refused)

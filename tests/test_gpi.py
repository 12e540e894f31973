"""GPIPolicy: the GPI theorem with exact successor features, batched = naive GPI, save/load, corrupt directories."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch as th
from conftest import BAD_WEIGHTS, random_tabular_network
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import (
    ALL_POLICIES,
    N_STATES,
    all_observations,
    all_policy_values,
    convex_coverage_values,
    exact_tabular_network,
    optimal_value,
    policy_value,
    rollout_return,
)

from sb3_sfgpi.gpi import MANIFEST, CorruptPolicySetError, GPIPolicy
from sb3_sfgpi.policy_files import build_network, declared_bytes, memory_budget

weights_2d = st.floats(0.0, 1.0).map(lambda t: np.array([1.0 - t, t]))


def exact_policy_set(policies) -> GPIPolicy:
    """A GPI set of tabular networks holding the exact ψ^π of the given deterministic Fig. 1 policies."""
    policy_set = GPIPolicy()
    for i, actions in enumerate(policies):
        value = policy_value(actions)
        policy_set.add(exact_tabular_network(actions), weights=[0.5, 0.5], value=value, agent="a", iteration=i)
    return policy_set


def gpi_policy(policy_set: GPIPolicy, w) -> tuple[int, ...]:
    """The deterministic policy (one action per state s0..s3) of GPI for w, read in one batched call."""
    return tuple(int(a) for a in policy_set.predict(np.arange(4), w)[0])


# --------------------------------------------------------------------------------------------------------------
# The GPI theorem on the Fig. 1 MOMDP, with exact values
# --------------------------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    indices=st.lists(st.integers(0, len(ALL_POLICIES) - 1), min_size=1, max_size=5, unique=True),
    w=weights_2d,
)
def test_gpi_is_at_least_as_good_as_every_policy_of_the_set(indices, w):
    policies = [ALL_POLICIES[i] for i in indices]
    policy_set = exact_policy_set(policies)
    gpi = gpi_policy(policy_set, w)
    for start in range(4):  # the theorem holds in every state, not only s0
        best_of_set = max(w @ policy_value(p, start=start) for p in policies)
        assert w @ policy_value(gpi, start=start) >= best_of_set - 1e-9
    # Rolled out in the env (one observation at a time), GPI earns the same exact value.
    returns = rollout_return(lambda obs: policy_set.predict(obs, w)[0])
    np.testing.assert_allclose(returns, policy_value(gpi))


def test_gpi_can_be_strictly_better_than_every_policy_of_the_set():
    # For objective 0, π1 acts optimally everywhere but in s0 and π2 only in s0: GPI combines them.
    pi1, pi2 = (0, 0, 1, 1), (1, 2, 2, 2)
    policy_set = exact_policy_set([pi1, pi2])
    w = np.array([1.0, 0.0])
    assert max(w @ policy_value(pi1), w @ policy_value(pi2)) < 29.0
    assert w @ policy_value(gpi_policy(policy_set, w)) == 29.0


def test_gpi_over_the_ccs_is_optimal_for_every_weight():
    ccs_values = convex_coverage_values()
    np.testing.assert_array_equal(ccs_values, [[23.0, 30.0], [29.0, 24.0]])
    values = all_policy_values()
    ccs_policies = [ALL_POLICIES[int(np.flatnonzero((values == v).all(axis=1))[0])] for v in ccs_values]
    policy_set = exact_policy_set(ccs_policies)
    for t in [*np.linspace(0.0, 1.0, 41), *np.random.default_rng(0).uniform(size=40)]:
        w = np.array([1.0 - t, t])
        assert w @ policy_value(gpi_policy(policy_set, w)) == pytest.approx(optimal_value(w), abs=1e-9)
        # The GPI action value in s0 is the optimal value too.
        assert policy_set.q_values(0, w).max() == pytest.approx(optimal_value(w), abs=1e-4)


def test_gpi_over_a_single_policy_is_that_policy_greedy(make_tabular_sfdqn):
    model = make_tabular_sfdqn([0.7, 0.3])
    table = model.policy.sf_net.table
    table.set_dense(th.randn((table.n_rows, table.width)).numpy())
    policy_set = GPIPolicy([model])
    assert len(policy_set) == 1
    np.testing.assert_array_equal(policy_set.infos[0].weights, [0.7, 0.3])
    observations = all_observations()
    for w in ([0.7, 0.3], [1.0, 0.0], [0.2, 0.8]):
        np.testing.assert_array_equal(
            policy_set.predict(observations, w)[0], model.predict(observations, deterministic=True, w=w)[0]
        )
    # The set holds a copy: training the model further does not change it.
    before = policy_set.successor_features(observations)
    table.set_dense(table.dense() + 100.0)
    np.testing.assert_array_equal(policy_set.successor_features(observations), before)


# --------------------------------------------------------------------------------------------------------------
# Batched GPI = a naive Python loop over the networks
# --------------------------------------------------------------------------------------------------------------


def naive_gpi(networks, observations, w):
    """GPI the slow way: each network on its own, then max over policies and argmax over actions."""
    psis, q_values = [], []
    for net in networks:
        obs_tensor, _ = net.obs_to_tensor(observations)
        with th.no_grad():
            psi = net(obs_tensor).numpy().astype(np.float64)
        psis.append(psi)
        q_values.append(psi @ np.asarray(w, dtype=np.float64))
    q = np.max(q_values, axis=0)
    return np.stack(psis), q, q.argmax(axis=1)


@pytest.mark.parametrize("kind", ["mlp", "tabular"])
@pytest.mark.parametrize("n_policies", [1, 2, 5])
def test_batched_gpi_equals_a_naive_loop(kind, n_policies, make_random_mlp, make_random_tabular):
    make = make_random_mlp if kind == "mlp" else make_random_tabular
    networks = [make(seed) for seed in range(n_policies)]
    policy_set = GPIPolicy()
    for net in networks:
        policy_set.add(net, weights=[1.0, 1.0, 1.0])
    space = networks[0].observation_space
    space.seed(0)
    rng = np.random.default_rng(1)
    for batch_size in (1, 7, 64):
        observations = np.stack([space.sample() for _ in range(batch_size)])
        for w in [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.2, 0.3, 0.5], *rng.dirichlet(np.ones(3), size=3)]:
            psi, q, actions = naive_gpi(networks, observations, w)
            np.testing.assert_allclose(policy_set.successor_features(observations), psi, rtol=1e-5, atol=1e-6)
            gpi_q = policy_set.q_values(observations, w)
            np.testing.assert_allclose(gpi_q, q, rtol=1e-5, atol=1e-6)
            gpi_actions = policy_set.predict(observations, w)[0]
            assert gpi_actions.shape == (batch_size,)
            # The chosen action attains the naive maximum (exact ties aside, the actions are the same).
            np.testing.assert_allclose(q[np.arange(batch_size), gpi_actions], q.max(axis=1), rtol=1e-5, atol=1e-6)
            if kind == "tabular":
                np.testing.assert_array_equal(gpi_actions, actions)
        # One observation, not a batch: a single action, as SB3's predict.
        single, _ = policy_set.predict(observations[0], [0.2, 0.3, 0.5])
        assert np.ndim(single) == 0 and single == naive_gpi(networks, observations[:1], [0.2, 0.3, 0.5])[2][0]


def test_a_set_refuses_networks_of_another_kind(make_random_mlp, make_random_tabular):
    policy_set = GPIPolicy()
    policy_set.add(make_random_mlp(0), weights=[1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="architecture"):
        policy_set.add(make_random_mlp(1, net_arch=(8,)), weights=[1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="architecture"):
        policy_set.add(make_random_tabular(1), weights=[1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="weights"):
        policy_set.add(make_random_mlp(2))
    assert len(policy_set) == 1


# --------------------------------------------------------------------------------------------------------------
# predict validates w; an empty set refuses to act
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("weights, message", BAD_WEIGHTS)
def test_predict_refuses_bad_weights(weights, message):
    policy_set = exact_policy_set([(0, 0, 0, 0), (1, 1, 1, 1)])
    with pytest.raises(ValueError, match=message):
        policy_set.predict(np.arange(4), weights)
    with pytest.raises(ValueError, match=message):
        policy_set.q_values(0, weights)


def test_an_empty_set_refuses_to_act():
    policy_set = GPIPolicy()
    assert len(policy_set) == 0
    with pytest.raises(ValueError, match="empty"):
        policy_set.predict(0, [0.5, 0.5])
    with pytest.raises(ValueError, match="empty"):
        policy_set.q_values(np.arange(4), [0.5, 0.5])


# --------------------------------------------------------------------------------------------------------------
# Save / load
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["mlp", "tabular"])
def test_save_load_round_trip(tmp_path, kind, make_random_mlp, make_random_tabular):
    make = make_random_mlp if kind == "mlp" else make_random_tabular
    policy_set = GPIPolicy()
    metadata = [
        dict(weights=[0.2, 0.3, 0.5], value=[1.5, -2.0, 3.25], agent="agent_0", iteration=0),
        dict(weights=[1.0, 0.0, 0.0], value=None, agent=None, iteration=None),
        dict(weights=[0.0, 0.5, 0.5], value=[0.0, 1e-7, 12.0], agent="agent_1", iteration=3),
    ]
    for seed, meta in enumerate(metadata):
        policy_set.add(make(seed), **meta)
    policy_set.save(tmp_path / "set")
    assert (tmp_path / "set" / MANIFEST).is_file()

    loaded = GPIPolicy.load(tmp_path / "set")
    assert len(loaded) == 3 and loaded.reward_dim == 3
    assert loaded.observation_space == policy_set.observation_space
    assert loaded.action_space == policy_set.action_space
    for original, restored in zip(policy_set.infos, loaded.infos, strict=True):
        np.testing.assert_array_equal(restored.weights, original.weights)
        if original.value is None:
            assert restored.value is None
        else:
            np.testing.assert_array_equal(restored.value, original.value)
        assert restored.agent == original.agent and restored.iteration == original.iteration
    space = policy_set.observation_space
    space.seed(3)
    observations = np.stack([space.sample() for _ in range(32)])
    np.testing.assert_array_equal(loaded.successor_features(observations), policy_set.successor_features(observations))
    for w in ([1, 0, 0], [0.1, 0.6, 0.3], [0, 0, 1]):
        np.testing.assert_array_equal(loaded.q_values(observations, w), policy_set.q_values(observations, w))
        np.testing.assert_array_equal(loaded.predict(observations, w)[0], policy_set.predict(observations, w)[0])

    # The loaded set can grow and be saved again.
    loaded.add(make(7), weights=[0.3, 0.3, 0.4])
    loaded.save(tmp_path / "set")
    assert len(GPIPolicy.load(tmp_path / "set")) == 4


def test_tables_are_stored_and_stacked_by_their_learned_rows(tmp_path, make_random_tabular):
    """Mostly-zero tables (large observation spaces) cost their non-zero rows on disk and in the GPI stack."""
    policy_set = GPIPolicy()
    for seed, learned in enumerate(([0, 5, 17], [5, 20], [])):  # MultiDiscrete([3, 4, 2]): 24 rows
        net = make_random_tabular(seed)
        keep = np.zeros(24, dtype=bool)
        keep[learned] = True
        table = net.table.dense()
        table[~keep] = 0.0
        net.table.set_dense(table)
        policy_set.add(net, weights=[1.0, 1.0, 1.0])
    policy_set.save(tmp_path / "set")
    stored = th.load(tmp_path / "set" / "policy_000.pt", weights_only=True)
    assert set(stored) == {"table.rows", "table.values", "table.shape"}
    assert stored["table.rows"].tolist() == [0, 5, 17] and stored["table.values"].shape == (3, 9)
    assert th.load(tmp_path / "set" / "policy_002.pt", weights_only=True)["table.rows"].numel() == 0
    loaded = GPIPolicy.load(tmp_path / "set")
    for original, restored in zip(policy_set.networks, loaded.networks, strict=True):
        np.testing.assert_array_equal(restored.table.dense(), original.table.dense())
    assert loaded._stack().tables_numpy.shape == (4 + 1, 3 * 9)  # rows 0, 5, 17, 20 and one default row for the others
    every_state = np.array([[i, j, k] for i in range(3) for j in range(4) for k in range(2)])
    obs_tensor, _ = loaded._obs_to_tensor(every_state)
    each = loaded._psi_each(obs_tensor).numpy()
    np.testing.assert_array_equal(loaded.successor_features(every_state), each)
    for w in ([1.0, 0.0, 0.0], [0.2, 0.3, 0.5]):
        q = np.max(each @ (np.array(w, dtype=np.float32) / np.sum(w)), axis=0)
        np.testing.assert_allclose(loaded.q_values(every_state, w), q, rtol=1e-6, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_a_tabular_sets_stack_follows_its_changes_as_stacking_all_again_would(data):
    """Adding a table extends the set's stack, popping one and taking a subset keep their columns (admission does
    this for every policy it tries): ψ of every state is what a stack of the same tables built afresh gives."""
    every_state = np.array([[i, j, k] for i in range(3) for j in range(4) for k in range(2)])  # MultiDiscrete 3, 4, 2
    policy_set = GPIPolicy()
    for step in range(data.draw(st.integers(1, 8))):
        operation = data.draw(st.sampled_from(["add", "add", "pop", "subset"]))
        if operation == "add" or not len(policy_set):
            net = random_tabular_network(step)
            stored = data.draw(st.lists(st.integers(0, 23), unique=True, max_size=6))
            table = net.table.dense()
            net.table.set_rows(np.array(stored, dtype=np.int64), table[stored], table[23] * 0.5)
            policy_set.add(net, weights=[1.0, 1.0, 1.0])
        elif operation == "pop":
            policy_set.pop()
        else:
            policy_set = policy_set.subset(data.draw(st.permutations(range(len(policy_set)))))
        if len(policy_set):
            kept = policy_set.successor_features(every_state)  # from the stack the set keeps up to date
            policy_set.networks_changed()
            np.testing.assert_array_equal(kept, policy_set.successor_features(every_state))  # stacked afresh


def test_a_set_of_untrained_tables_acts(tmp_path, make_random_tabular):
    policy_set = GPIPolicy()
    for seed in range(2):
        net = make_random_tabular(seed)
        net.table.fill(0.0)
        policy_set.add(net, weights=[1.0, 0.0, 0.0])
    policy_set.save(tmp_path / "set")
    loaded = GPIPolicy.load(tmp_path / "set")
    observations = np.array([[0, 0, 0], [2, 3, 1]])
    np.testing.assert_array_equal(loaded.q_values(observations, [0.2, 0.3, 0.5]), np.zeros((2, 3)))
    np.testing.assert_array_equal(loaded.predict(observations, [0.2, 0.3, 0.5])[0], [0, 0])  # ties: the first


# --------------------------------------------------------------------------------------------------------------
# Corrupt, half-written or foreign directories
# --------------------------------------------------------------------------------------------------------------


@pytest.fixture
def saved_set(tmp_path) -> Path:
    directory = tmp_path / "set"
    exact_policy_set([(1, 0, 1, 1), (0, 0, 0, 1), (2, 2, 2, 2)]).save(directory)
    assert len(GPIPolicy.load(directory)) == 3  # the intact directory loads
    return directory


def remove_manifest(directory: Path) -> None:
    (directory / MANIFEST).unlink()


def truncate_manifest(directory: Path) -> None:
    text = (directory / MANIFEST).read_text()
    (directory / MANIFEST).write_text(text[: len(text) // 2])


def remove_policy_file(directory: Path) -> None:
    (directory / "policy_001.pt").unlink()


def truncate_policy_file(directory: Path) -> None:
    data = (directory / "policy_001.pt").read_bytes()
    (directory / "policy_001.pt").write_bytes(data[: len(data) // 2])


def wrong_shapes(directory: Path) -> None:
    state = th.load(directory / "policy_001.pt", weights_only=True)
    th.save({**state, "table.shape": th.tensor([N_STATES + 1, 6])}, directory / "policy_001.pt")


def sparse_table(directory: Path, **changes) -> None:
    """Rewrite policy 1 with its table stored by rows, with some of the stored tensors replaced."""
    state = th.load(directory / "policy_001.pt", weights_only=True)
    th.save({**state, **changes}, directory / "policy_001.pt")


def sparse_rows_outside_the_table(directory: Path) -> None:
    sparse_table(directory, **{"table.rows": th.tensor([0, N_STATES]), "table.values": th.ones(2, 6)})


def sparse_table_of_another_shape(directory: Path) -> None:
    sparse_table(directory, **{"table.shape": th.tensor([N_STATES + 1, 6])})


def sparse_values_not_matching_rows(directory: Path) -> None:
    sparse_table(directory, **{"table.rows": th.tensor([0, 1]), "table.values": th.ones(3, 6)})


def sparse_table_without_rows(directory: Path) -> None:
    state = th.load(directory / "policy_001.pt", weights_only=True)
    del state["table.rows"]
    th.save(state, directory / "policy_001.pt")


def sparse_rows_repeated(directory: Path) -> None:
    sparse_table(directory, **{"table.rows": th.tensor([1, 1]), "table.values": th.ones(2, 6)})


def non_finite_values(directory: Path, value: float) -> None:
    sparse_table(directory, **{"table.rows": th.tensor([0, 1]), "table.values": th.full((2, 6), value)})


def nan_values(directory: Path) -> None:
    non_finite_values(directory, float("nan"))


def infinite_values(directory: Path) -> None:
    non_finite_values(directory, float("inf"))


def non_finite_value_vector(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["policies"][1]["value"] = [float("nan"), 0.0]
    (directory / MANIFEST).write_text(json.dumps(manifest))


def file_listed_twice(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["policies"] = [manifest["policies"][0]] * 40
    (directory / MANIFEST).write_text(json.dumps(manifest))


def link_leaving_the_directory(directory: Path) -> None:
    shutil.copy(directory / "policy_001.pt", directory.parent / "outside.pt")
    (directory / "policy_001.pt").unlink()
    (directory / "policy_001.pt").symlink_to(directory.parent / "outside.pt")


def more_policies_than_memory(directory: Path) -> None:
    """Big tables (a Discrete(40,000,000) observation: 960 MB each), as many as half of this machine's memory takes."""
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["observation_space"] = {"type": "Discrete", "n": 40_000_000, "start": 0}
    n = memory_budget() // declared_bytes({"kind": "tabular"}, spaces.Discrete(40_000_000), spaces.Discrete(3), 2) + 1
    entry = manifest["policies"][0]
    manifest["policies"] = [{**entry, "file": f"policy_{i:06d}.pt"} for i in range(n)]  # none of them is read
    (directory / MANIFEST).write_text(json.dumps(manifest))


def not_tensors(directory: Path) -> None:
    th.save({"table.values": [1.0, 2.0]}, directory / "policy_001.pt")


def foreign_manifest(directory: Path) -> None:
    (directory / MANIFEST).write_text(json.dumps({"format": "someone-else/checkpoint", "version": 1, "policies": []}))


def future_version(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    (directory / MANIFEST).write_text(json.dumps({**manifest, "version": 99}))


def escaping_file_name(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    shutil.copy(directory / "policy_000.pt", directory.parent / "outside.pt")
    manifest["policies"][0]["file"] = "../outside.pt"
    (directory / MANIFEST).write_text(json.dumps(manifest))


def retired_not_an_iteration(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["policies"][1]["retired"] = True
    (directory / MANIFEST).write_text(json.dumps(manifest))


def beyond_float32(directory: Path) -> None:
    """Values stored as float64 that are finite there and infinite in the float32 the table holds."""
    state = th.load(directory / "policy_001.pt", weights_only=True)
    values = state["table.values"].to(th.float64)
    values[0, 0] = 1e39
    th.save({**state, "table.values": values}, directory / "policy_001.pt")


def huge_action_space(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["action_space"]["n"] = 10**30
    (directory / MANIFEST).write_text(json.dumps(manifest))


def iteration_not_an_integer(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["policies"][1]["iteration"] = "1"
    (directory / MANIFEST).write_text(json.dumps(manifest))


def decompression_bomb(directory: Path) -> None:
    """A small file whose deflated record unpacks to 8 MB: refused from the archive's directory, before unpacking."""
    with zipfile.ZipFile(directory / "policy_001.pt", "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("archive/data.pkl", bytes(8 * 2**20))


def missing_key(directory: Path) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    del manifest["observation_space"]
    (directory / MANIFEST).write_text(json.dumps(manifest))


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (remove_manifest, "manifest .* does not exist"),
        (truncate_manifest, "not valid JSON"),
        (remove_policy_file, "policy_001.pt.* is missing"),
        (truncate_policy_file, "policy_001.pt is unreadable"),
        (wrong_shapes, "the stored table has shape"),
        (not_tensors, "state dict of tensors"),
        (sparse_rows_repeated, "stored table rows repeat"),
        (nan_values, r"non-finite values \(NaN or inf\) in 'table.values'"),
        (infinite_values, r"non-finite values \(NaN or inf\) in 'table.values'"),
        (non_finite_value_vector, "the value of 'policy_001.pt' must be a list of finite numbers"),
        (file_listed_twice, "lists a policy file more than once"),
        (link_leaving_the_directory, "policy_001.pt is a link that leaves the directory"),
        (more_policies_than_memory, r"policies of 960.0 MB each .* more than half of this machine's memory"),
        (sparse_rows_outside_the_table, "rows outside 0..4"),
        (sparse_table_of_another_shape, r"stored table has shape \(6, 6\), the network's is \(5, 6\)"),
        (sparse_values_not_matching_rows, r"rows \(2,\) and values \(3, 6\) do not match"),
        (sparse_table_without_rows, "table.rows"),
        (foreign_manifest, "not an sb3-sfgpi policy-set manifest"),
        (future_version, "unsupported policy-set version 99"),
        (escaping_file_name, r"\.\./outside\.pt.* is missing"),
        (missing_key, "observation_space"),
        (retired_not_an_iteration, "'retired' of 'policy_001.pt' must be null or an iteration, got True"),
        (decompression_bomb, r"policy_001.pt unpacks to 8.4 MB, more than its network can hold"),
        (beyond_float32, r"non-finite values \(NaN or inf\) in 'table.values'"),
        (huge_action_space, r"n must hold integers in \[1, 2147483647\]"),
        (iteration_not_an_integer, "'iteration' of 'policy_001.pt' must be null or a non-negative integer, got '1'"),
    ],
)
def test_corrupt_directories_fail_clearly(saved_set, corrupt, message):
    corrupt(saved_set)
    with pytest.raises(CorruptPolicySetError, match=message) as error:
        GPIPolicy.load(saved_set)
    assert isinstance(error.value, ValueError)


def test_loading_a_missing_directory_fails_clearly(tmp_path):
    with pytest.raises(CorruptPolicySetError, match="does not exist"):
        GPIPolicy.load(tmp_path / "nowhere")


class CodeRunningPayload:
    """Unpickling this object opens (creates) the marker file: it stands for any code a pickle can run."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_pickle_that_runs_code_is_not_executed(saved_set, tmp_path):
    # Control: the payload does run code when unpickled the unsafe way.
    control_marker, control_file = tmp_path / "control-marker", tmp_path / "control.pt"
    th.save({"table.values": CodeRunningPayload(control_marker)}, control_file)
    th.load(control_file, weights_only=False)["table.values"].close()  # the payload returns the opened file
    assert control_marker.exists()

    marker = tmp_path / "marker"
    th.save({"table.values": CodeRunningPayload(marker)}, saved_set / "policy_001.pt")
    with pytest.raises(CorruptPolicySetError, match="policy_001.pt is unreadable or unsafe"):
        GPIPolicy.load(saved_set)
    assert not marker.exists()


def test_an_interrupted_save_keeps_the_previous_set_loadable(saved_set, monkeypatch):
    before = GPIPolicy.load(saved_set)
    grown = GPIPolicy.load(saved_set)
    grown.add(exact_tabular_network((0, 1, 2, 0)), weights=[0.5, 0.5])
    real_save = th.save

    def crash_half_way(obj, f, *args, **kwargs):
        """Write half of the file, then fail (a full disk, a kill signal)."""
        buffer = io.BytesIO()
        real_save(obj, buffer, *args, **kwargs)
        data = buffer.getvalue()
        if isinstance(f, (str, Path)):
            Path(f).write_bytes(data[: len(data) // 2])
        else:
            f.write(data[: len(data) // 2])
        raise OSError("simulated crash while saving")

    monkeypatch.setattr(th, "save", crash_half_way)
    with pytest.raises(OSError, match="simulated crash"):
        grown.save(saved_set)
    monkeypatch.undo()
    # The previous manifest is still there, and every file it lists is intact.
    after = GPIPolicy.load(saved_set)
    assert len(after) == len(before) == 3
    np.testing.assert_array_equal(
        after.successor_features(np.arange(N_STATES)), before.successor_features(np.arange(N_STATES))
    )


@pytest.mark.parametrize(
    ("spec", "observation_space"),
    [
        ({"kind": "tabular"}, spaces.MultiDiscrete([13, 13, 2, 2])),
        ({"kind": "mlp", "net_arch": [64, 32], "activation_fn": "ReLU"}, spaces.Box(-1, 1, shape=(7,))),
    ],
)
def test_the_memory_a_manifest_declares_is_what_its_networks_take(spec, observation_space):
    net = build_network(spec, observation_space, spaces.Discrete(4), 3)
    if spec["kind"] == "tabular":  # the most a table takes: every row stored
        net.table.set_dense(np.ones((net.table.n_rows, net.table.width)))
        taken = net.table.stored_values().nbytes
    else:
        taken = sum(parameter.numel() * parameter.element_size() for parameter in net.parameters())
    assert declared_bytes(spec, observation_space, spaces.Discrete(4), 3) == taken


def test_retired_policies_are_saved_and_left_out_of_a_plain_load(saved_set):
    record = GPIPolicy.load(saved_set)
    assert all(info.retired is None for info in record.infos)  # files written before retirement existed read alike
    record.retire(1, 3)
    assert [info.retired for info in record.infos][:2] == [None, 3]
    members = record.members()
    assert len(members) == len(record) - 1
    obs = np.arange(3)
    kept = [i for i in range(len(record)) if i != 1]
    np.testing.assert_allclose(members.successor_features(obs), record.subset(kept).successor_features(obs))
    record.save(saved_set)
    assert len(GPIPolicy.load(saved_set)) == len(members)
    everything = GPIPolicy.load(saved_set, retired=True)
    assert [info.retired for info in everything.infos] == [info.retired for info in record.infos]
    everything.retire(1, None)
    assert len(everything.members()) == len(record)


def test_as_of_is_the_record_after_an_iteration(saved_set):
    record = GPIPolicy.load(saved_set)
    for i, (iteration, retired) in enumerate([(1, 2), (1, None), (2, 3)]):
        record.infos[i] = replace(record.infos[i], iteration=iteration, retired=retired)
    assert [(i.iteration, i.retired) for i in record.as_of(1).infos] == [(1, None), (1, None)]
    assert [(i.iteration, i.retired) for i in record.as_of(2).infos] == [(1, 2), (1, None), (2, None)]
    assert [(i.iteration, i.retired) for i in record.as_of(3).infos] == [(1, 2), (1, None), (2, 3)]
    assert len(record.as_of(2).members()) == 2

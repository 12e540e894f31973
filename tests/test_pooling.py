"""Pooled replay: the pool's counts, its files, planning on it (exact on small models), resume and refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from conftest import StopAfter
from gymnasium import spaces
from momdp import N_ACTIONS, N_STATES, REWARD_DIM, REWARDS, TERMINAL, Fig1MOMDP, optimal_value, successor_features
from parallel_chain import CHAIN_LEARNER, ParallelChainEnv

from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.policy_files import file_state
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import load_policy_set
from sb3_sfgpi.sfdqn import TabularSFNetwork
from sb3_sfgpi.tabular.planning import Experience
from sb3_sfgpi.tabular.pooling import PooledReplay

mo = pytest.importorskip("mo_gymnasium")


def random_transitions(rng: np.random.Generator, n: int, n_rows: int = 6, n_actions: int = 2):
    """``n`` random transitions (rows, actions, next rows, dones, integer rewards of 2 objectives)."""
    return (
        rng.integers(0, n_rows, n),
        rng.integers(0, n_actions, n),
        rng.integers(0, n_rows, n),
        (rng.random(n) < 0.3).astype(np.float64),
        rng.integers(-2, 3, (n, 2)).astype(np.float32),
    )


def test_pooled_counts_equal_the_transitions_fed_in_any_split():
    rng = np.random.default_rng(0)
    transitions = random_transitions(rng, 300)
    whole = Experience.from_transitions(*transitions, n_rows=6, n_actions=2)
    pooled = PooledReplay(gamma=0.9)
    for part in np.split(np.arange(300), [40, 41, 200]):  # four iterations' worth, one of a single transition
        pooled.add(Experience.from_transitions(*(array[part] for array in transitions), n_rows=6, n_actions=2))
    assert pooled.experience is not None and len(pooled.experience) == 300
    for key in ("keys", "counts", "dones", "rewards"):  # integer rewards: the sums are exact in any order
        np.testing.assert_array_equal(getattr(pooled.experience, key), getattr(whole, key))
    # by hand: how often (s=0, a=1) was followed by s'=3
    rows, actions, next_rows = transitions[:3]
    key = (0 * 2 + 1) * 12 + 3 * 2
    assert pooled.experience.counts[list(pooled.experience.keys).index(key)] == np.sum(
        (rows == 0) & (actions == 1) & (next_rows == 3)
    )


def test_experience_arrays_round_trip_and_malformed_ones_are_refused():
    experience = Experience.from_transitions(*random_transitions(np.random.default_rng(1), 50), n_rows=6, n_actions=2)
    back = Experience.from_arrays(experience.arrays(), 6, 2, 2)
    for key, array in experience.arrays().items():
        np.testing.assert_array_equal(back.arrays()[key], array)
    good = experience.arrays()
    bad = {
        "keys not sorted": {**good, "keys": good["keys"][::-1]},
        "a key of another table": {**good, "keys": good["keys"] + 10_000},
        "a key that is no outcome": {**good, "keys": good["keys"] + 1},
        "a zero count": {**good, "counts": np.zeros_like(good["counts"])},
        "more terminations than counts": {**good, "dones": good["counts"] + 1.0},
        "a NaN reward": {**good, "rewards": np.full_like(good["rewards"], np.nan)},
        "rewards of 3 objectives": {**good, "rewards": np.zeros((len(good["keys"]), 3))},
        "float counts": {**good, "counts": good["counts"].astype(np.float64)},
        "a count short": {**good, "counts": good["counts"][1:]},
    }
    for problem, arrays in bad.items():
        with pytest.raises(ValueError, match="experience"):
            Experience.from_arrays(arrays, 6, 2, 2)
            pytest.fail(problem)
    with pytest.raises(ValueError, match="lacks"):
        Experience.from_arrays({"keys": good["keys"]}, 6, 2, 2)


def fig1_experience() -> Experience:
    """Every pair of the Fig. 1 MOMDP tried (twice): its empirical model is the exact one."""
    states, actions = np.repeat(np.arange(TERMINAL), N_ACTIONS * 2), np.tile(np.arange(N_ACTIONS), TERMINAL * 2)
    dones = (states == TERMINAL - 1).astype(np.float64)
    return Experience.from_transitions(
        states, actions, states + 1, dones, REWARDS[states, actions], n_rows=N_STATES, n_actions=N_ACTIONS
    )


@pytest.mark.parametrize("w", [[1.0, 0.0], [0.0, 1.0], [0.3, 0.7], [0.8, 0.2]])
@pytest.mark.parametrize("gamma", [1.0, 0.9])
def test_planning_on_an_exact_pool_gives_the_sfs_of_an_optimal_policy(w, gamma):
    # A table starting from the SFs of the worst policy: afterwards it holds ψ of its own greedy policy, exactly,
    # and that policy is optimal for w (brute force over all 81 policies).
    net = TabularSFNetwork(spaces.Discrete(N_STATES), spaces.Discrete(N_ACTIONS), REWARD_DIM)
    net.table.set_dense(successor_features((2, 2, 2, 2), gamma).reshape(N_STATES, -1))
    pooled = PooledReplay(gamma)
    pooled.add(fig1_experience())
    pooled.plan([(net, np.array(w))])
    psi = net.table.dense().reshape(N_STATES, N_ACTIONS, REWARD_DIM)
    greedy = tuple(int(a) for a in (psi[:TERMINAL] @ np.array(w)).argmax(axis=1))
    np.testing.assert_allclose(psi, successor_features(greedy, gamma), atol=1e-5)
    assert (psi[0] @ np.array(w)).max() == pytest.approx(optimal_value(w, gamma), abs=1e-4)


def test_planning_on_a_stochastic_pool_is_the_policy_evaluation_of_the_greedy_policy():
    # Three states, two actions, outcomes fed in proportion to their probabilities: the pool is this model exactly.
    # The planned SFs must solve ψ = r̄ + γ P_π ψ (a linear system) for their greedy policy π, and that policy must be
    # optimal for w: its Q = w·ψ solves the scalar Bellman optimality equation.
    rng, gamma, w = np.random.default_rng(2), 0.9, np.array([0.6, 0.4])
    n_states, n_actions = 3, 2
    outcomes = [
        (s, a, s2, k) for s in range(n_states) for a in range(n_actions) for s2, k in enumerate(rng.integers(1, 4, 3))
    ]
    s, a, s2 = (np.repeat([o[i] for o in outcomes], [o[3] for o in outcomes]) for i in range(3))
    rewards = np.stack([s + a, s2 * 2], axis=1).astype(np.float32)  # depends on the outcome: a mean per (s, a)
    experience = Experience.from_transitions(s, a, s2, np.zeros(len(s)), rewards, n_states, n_actions)
    net = TabularSFNetwork(spaces.Discrete(n_states), spaces.Discrete(n_actions), 2)
    pooled = PooledReplay(gamma)
    pooled.add(experience)
    pooled.plan([(net, w)])
    psi = net.table.dense().astype(np.float64).reshape(n_states, n_actions, 2)

    counts = np.zeros((n_states, n_actions, n_states))
    np.add.at(counts, (s, a, s2), 1)
    p = counts / counts.sum(axis=2, keepdims=True)
    r = np.zeros((n_states, n_actions, 2))
    np.add.at(r, (s, a), rewards)
    r /= counts.sum(axis=2)[..., None]
    policy = (psi @ w).argmax(axis=1)
    p_pi = p[np.arange(n_states), policy]  # (S, S'): under the policy
    v_pi = np.linalg.solve(np.eye(n_states) - gamma * p_pi, r[np.arange(n_states), policy])
    np.testing.assert_allclose(psi, r + gamma * p @ v_pi, atol=1e-4)
    q = np.zeros((n_states, n_actions))
    for _ in range(3_000):  # scalar value iteration
        q = r @ w + gamma * p @ q.max(axis=1)
    np.testing.assert_allclose(psi @ w, q, atol=1e-4)


def resource_gathering_run(run_dir, **kwargs) -> MASFOLS:
    learner = dict(
        CHAIN_LEARNER,
        gamma=0.95,
        buffer_size=10_000,
        planning_sweeps=5,
        planning_interval=200,
        optimistic_init="rmax_1.25",
    )
    learner.pop("policy")
    return MASFOLS(
        mo.make("resource-gathering-v0"), steps_per_iteration=400, learner_kwargs=learner, pool_replay=True,
        validation_weights=2, test_weights=3, eval_episodes=2, seed=5,
        run_dir=run_dir, **kwargs,
    )  # fmt: skip


def files(folder) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


def without_times(path) -> list:
    return [
        {k: v for k, v in row.items() if k not in ("wall_time", "eval_time")} for row in json.loads(path.read_text())
    ]


def test_a_run_stopped_in_an_iteration_and_resumed_writes_the_same_files(tmp_path):
    whole = resource_gathering_run(tmp_path / "whole").learn(max_iterations=3)
    resource_gathering_run(tmp_path / "cut").learn(max_iterations=3, callback=StopAfter(600))  # mid-iteration 2
    assert json.loads((tmp_path / "cut" / "checkpoint.json").read_text())["iteration"] == 1
    MASFOLS.load(tmp_path / "cut", mo.make("resource-gathering-v0")).learn(max_iterations=3)

    assert without_times(tmp_path / "cut" / "evaluation.json") == without_times(tmp_path / "whole" / "evaluation.json")
    for folder in ("experience", "policy_set"):
        assert files(tmp_path / "cut" / folder) == files(tmp_path / "whole" / folder)
    assert len(files(tmp_path / "whole" / "experience")) == 3
    assert len(whole.callback.pooled.experience) == 3 * 400  # every step of every iteration is in the pool


def test_a_missing_or_corrupt_experience_file_stops_the_resume(tmp_path):
    resource_gathering_run(tmp_path).learn(max_iterations=2)
    (tmp_path / "experience" / "iteration_002.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="iteration_002.npz is not an experience file"):
        MASFOLS.load(tmp_path, mo.make("resource-gathering-v0")).learn(max_iterations=3)
    (tmp_path / "experience" / "iteration_001.npz").unlink()
    with pytest.raises(ValueError, match="iteration 1's is missing"):
        MASFOLS.load(tmp_path, mo.make("resource-gathering-v0")).learn(max_iterations=3)


def test_pooled_replay_is_refused_with_several_agents_or_without_tables():
    learner = {k: v for k, v in CHAIN_LEARNER.items() if k != "policy"}
    with pytest.raises(ValueError, match="single-agent env, not 2 agents"):
        MASFOLS(ParallelChainEnv(2), learner_kwargs=learner, pool_replay=True)
    with pytest.raises(ValueError, match="must be 'TabularPolicy'"):
        MASFOLS(Fig1MOMDP(one_hot=True), policy="MlpPolicy", learner_kwargs={"learning_starts": 0}, pool_replay=True)


def test_a_run_killed_before_its_checkpoint_leaves_on_disk_the_set_of_its_checkpoint(tmp_path, monkeypatch):
    resource_gathering_run(tmp_path).learn(max_iterations=1)
    after_one = GPIPolicy.load(tmp_path / "policy_set", retired=True)

    class Killed(BaseException):
        pass

    def killed(self, history, checkpoint):
        raise Killed

    with monkeypatch.context() as patch:  # iteration 2 re-plans every table, stages Π and dies before its checkpoint
        patch.setattr(RunDirectory, "write_iteration", killed)
        with pytest.raises(Killed):
            MASFOLS.load(tmp_path, mo.make("resource-gathering-v0")).learn(max_iterations=2)
    staged = GPIPolicy.load(tmp_path / "policy_set" / "manifest.next.json", retired=True)
    assert not all(same_tables(staged.subset([i]), after_one.subset([i])) for i in range(len(after_one)))

    state = RunDirectory(tmp_path).read_checkpoint()
    for loaded in (  # what a user, `evaluate` and a resume read: the checkpoint's
        GPIPolicy.load(tmp_path / "policy_set", retired=True),
        load_policy_set(RunDirectory(tmp_path), state["n_policies"], iteration=state["iteration"], record=True),
    ):
        assert same_tables(loaded, after_one)


def same_tables(one: GPIPolicy, other: GPIPolicy) -> bool:
    states = [[file_state(net) for net in policy_set.networks] for policy_set in (one, other)]
    return len(states[0]) == len(states[1]) and all(
        a.keys() == b.keys() and all(th.equal(a[k], b[k]) for k in a) for a, b in zip(*states, strict=True)
    )

"""Training throughput (env steps per second of ``learn``), each against a baseline in the same run.

1. **MLP**: ``SFDQN("MlpPolicy")`` on MO-Gymnasium's vector-reward ``four-room-v0`` vs SB3's own ``DQN`` on the
   same env scalarised by ``LinearReward`` (``w · r``): same [64, 64] network, buffer, batch, train frequency,
   exploration and target updates. Target ≥ 0.85×. Also the candidate fix of the issue for the TD update, one
   online forward pass over ``[s, s']`` instead of two passes (``s'`` without gradient, then ``s``), both in a
   learner (note) and alone on one buffer at batches 32, 64 and 256 (rows): it does not pay, so it is not
   adopted (the backward pass then runs over ``2B`` rows).
2. **Tabular**: ``SFDQN("TabularPolicy")`` (the paper's Table 1 settings) vs a plain numpy loop of tabular SF
   Q-learning with experience replay on the same env ("xy" observations): same ε-greedy schedule, uniform
   replay sampling, batch, α, γ and train frequency. The ratio is what SB3's loop costs over bare numpy.
3. **Multi-agent**: ``MultiAgentRunner`` on the two-agent Four-Room (tabular learners, same settings) vs two
   single-agent ``SFDQN.learn`` loops on MO-Gymnasium's Four-Room ("xy"): joint steps/s vs
   ``N / (t_1 + t_2)`` for two loops of ``N`` steps each (the same number of agent transitions).

Learners are timed in interleaved chunks of steps (``learn(n, reset_num_timesteps=False)``); ratios are medians of
the per-round ratios (both sides timed in the same round).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch as th
from sfgpi_envs.four_room import FourRoomParallelEnv
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from torch.nn import functional as F

from benchmarks._common import Row, fmt_rate, fmt_time, interleaved_samples, paired_ratio
from benchmarks.envs import four_room, scalarized_four_room
from sb3_sfgpi import SFDQN
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.sfdqn.networks import greedy_actions
from sb3_sfgpi.sfdqn.policies import SFDQNPolicy

NAME = "training"
TARGET_DQN = 0.85
WEIGHTS = np.array([0.5, 0.3, 0.2])

# Every learner explores with the same constant ε, whatever its schedule bookkeeping (chunked learn() calls,
# a runner-level total): acting costs depend on ε, so it must be the same on both sides of a comparison.
EPSILON = dict(exploration_initial_eps=0.1, exploration_final_eps=0.1)
MLP_KWARGS = dict(
    **EPSILON,
    learning_rate=1e-3,
    buffer_size=100_000,
    learning_starts=100,
    batch_size=32,
    train_freq=1,
    gradient_steps=1,
    target_update_interval=500,
    policy_kwargs=dict(net_arch=[64, 64]),
)
# The paper's Table 1 / the four-room domain (buffer 10^5 instead of 10^6: only allocation differs; constant ε).
TABULAR_KWARGS = dict(
    **EPSILON,
    learning_rate=0.1,
    gamma=0.95,
    buffer_size=100_000,
    batch_size=32,
    learning_starts=0,
    train_freq=1,
)


def _silent(model):
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


class OnePassPolicy(SFDQNPolicy):
    """
    The candidate fix for the MLP update, measured and not adopted: the online network sees ``[s, s']`` in one
    forward pass (the ``s'`` half detached) instead of one pass on ``s'`` without gradient and one on ``s``.
    """

    def td_update(self, replay_buffer, batch_size, gamma, max_grad_norm, vec_normalize_env=None):  # noqa: ANN001
        batch = replay_buffer.sample(batch_size, env=vec_normalize_env)
        rows = th.arange(batch_size)
        online = self.sf_net(th.cat([batch.observations, batch.next_observations]))
        current_psi = online[:batch_size][rows, batch.actions.long().flatten()]
        with th.no_grad():
            next_online = online[batch_size:].detach()
            next_actions = greedy_actions(next_online, self.weights)
            next_psi = self.sf_net_target(batch.next_observations)
            target_psi = batch.rewards + (1 - batch.dones) * gamma * next_psi[rows, next_actions]
        return self.gradient_step(F.smooth_l1_loss(current_psi, target_psi), max_grad_norm)


class SB3LoopOnly(SFDQN):
    """SFDQN with acting and learning removed (always action 0, no update): what SB3's loop alone costs."""

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        pass

    def predict(self, observation, state=None, episode_start=None, deterministic=False, w=None):  # noqa: ANN001
        return np.zeros(1, dtype=np.int64), state


# ---------------------------------------------------------------------------------------------------------------
# Plain numpy tabular SF Q-learning with experience replay (the tabular baseline)
# ---------------------------------------------------------------------------------------------------------------


class NumpyTabularSF:
    """
    Tabular SF Q-learning with uniform experience replay, in numpy: what ``SFDQN("TabularPolicy")`` computes.

    ε-greedy in ``w · ψ`` with the constant ``ε = exploration_final_eps``; every ``train_freq`` steps one batch
    of ``batch_size`` uniformly sampled transitions moves each sampled entry by
    ``α (r + γ (1 - terminated) ψ(s', a*) - ψ(s, a))``, ``a* = argmax_a w · ψ(s', a)`` (time-limit
    truncations bootstrap, as in SFDQN).
    """

    def __init__(self, env, weights: np.ndarray, seed: int, **kw):
        self.env, self.kw = env, kw
        self.rng = np.random.default_rng(seed)
        nvec = env.observation_space.nvec
        self.strides = np.array([nvec[1], 1])
        self.n_actions, d = int(env.action_space.n), len(weights)
        self.psi = np.zeros((int(np.prod(nvec)), self.n_actions, d), dtype=np.float32)
        self.w = np.asarray(weights, dtype=np.float32)
        size = kw["buffer_size"]
        self.states, self.next_states = np.zeros(size, np.int64), np.zeros(size, np.int64)
        self.actions, self.dones = np.zeros(size, np.int64), np.zeros(size, np.float32)
        self.rewards = np.zeros((size, d), np.float32)
        self.pos, self.full, self.t = 0, False, 0
        obs, _ = env.reset(seed=seed)
        self.s = int(obs @ self.strides)

    def learn(self, n_steps: int) -> None:
        kw, rng, psi, w, env, strides = self.kw, self.rng, self.psi, self.w, self.env, self.strides
        states, next_states, actions, rewards, dones = (
            self.states,
            self.next_states,
            self.actions,
            self.rewards,
            self.dones,
        )
        alpha, gamma, batch, size = kw["learning_rate"], kw["gamma"], kw["batch_size"], kw["buffer_size"]
        eps = kw["exploration_final_eps"]
        s = self.s
        for _ in range(n_steps):
            a = int(rng.integers(self.n_actions)) if rng.random() < eps else int(np.argmax(psi[s] @ w))
            obs, r, terminated, truncated, _ = env.step(a)
            s2 = int(obs @ strides)
            pos = self.pos
            states[pos], actions[pos], rewards[pos], next_states[pos], dones[pos] = s, a, r, s2, terminated
            self.pos = pos + 1
            if self.pos == size:
                self.pos, self.full = 0, True
            self.t += 1
            if self.t > kw["learning_starts"] and self.t % kw["train_freq"] == 0:
                idx = rng.integers(0, size if self.full else self.pos, size=batch)
                ss, aa, ss2 = states[idx], actions[idx], next_states[idx]
                a_star = np.argmax(psi[ss2] @ w, axis=1)
                target = rewards[idx] + (1 - dones[idx])[:, None] * gamma * psi[ss2, a_star]
                np.add.at(psi, (ss, aa), alpha * (target - psi[ss, aa]))
            s = s2
            if terminated or truncated:
                obs, _ = env.reset()
                s = int(obs @ strides)
        self.s = s


# ---------------------------------------------------------------------------------------------------------------
# The multi-agent runner with fixed weights (no OLS, no evaluation)
# ---------------------------------------------------------------------------------------------------------------


class FixedWeights(BaseCallback):
    """Runner-level callback that starts one iteration with fixed weights (once) and nothing else."""

    def __init__(self, weights: dict[str, np.ndarray], total_timesteps: int):
        super().__init__()
        self.fixed = weights
        self.total = total_timesteps

    def _on_training_start(self) -> None:
        if not self.model.learners:  # type: ignore[attr-defined]
            self.model.start_iteration(self.fixed, 0, self.total)  # type: ignore[attr-defined]
            for learner in self.model.learners.values():  # type: ignore[attr-defined]
                _silent(learner)

    def _on_step(self) -> bool:
        return True


def chunked_interleaved(
    makers: dict[str, Callable[[], Callable[[int], Any]]],
    chunk: int,
    repeats: int,
    clock: Callable[[], float] = time.perf_counter,
) -> dict:
    """
    Seconds per chunk of ``chunk`` steps of each learner, timed in interleaved rounds (one sample per round).

    Each maker builds its learner (untimed) and returns ``advance(n)``, which trains it ``n`` more steps. One
    untimed chunk warms every learner up (imports, first allocations, the first learning steps).

    :param clock: wall time (default) or ``time.process_time`` (seconds of this process's CPU)
    """
    advances = {name: make() for name, make in makers.items()}
    for advance in advances.values():
        advance(chunk)
    chunks = {name: (lambda a=a: a(chunk)) for name, a in advances.items()}
    return interleaved_samples(chunks, repeats, warmup=0, clock=clock)


def _median(samples: dict[str, list[float]]) -> dict[str, float]:
    return {name: float(np.median(values)) for name, values in samples.items()}


def run(quick: bool = False) -> list[Row]:
    return [*run_mlp(quick), *run_tabular(quick), *run_multiagent(quick)]


def run_mlp(quick: bool = False) -> list[Row]:
    """MLP SFDQN vs SB3's DQN, the candidate one-pass TD update vs the current one, the conditioned TD update."""
    return [_mlp_against_dqn_row(quick), *_td_update_rows(quick), _conditioned_update_row(quick)]


def _conditioned_update_row(quick: bool) -> Row:
    """
    ``ConditionedMlpPolicy``'s TD update (the deep preset's: 4 × 256, batch 128 learned for w and for support
    weights) with its default optimizer (Adam, ``foreach``) against Adam's loop over the parameters.
    """
    import mo_gymnasium as mo

    kwargs = dict(learning_starts=100, batch_size=128, buffer_size=2_000, seed=0)
    models = {}
    for name, optimizer_kwargs in (("foreach", {}), ("loop", {"foreach": False})):
        model = _silent(SFDQN("ConditionedMlpPolicy", mo.make("minecart-v0"), **kwargs,
                              policy_kwargs={"optimizer_kwargs": optimizer_kwargs}))  # fmt: skip
        model.set_weight_support(np.eye(3))
        model.learn(300)
        models[name] = model
    samples = interleaved_samples(
        {name: lambda m=m: m.policy.td_update(m.replay_buffer, 128, 0.98, 10.0) for name, m in models.items()},
        repeats=5 if quick else 11,
        number=10 if quick else 40,
    )
    ratio, q1, q3 = paired_ratio(samples, "loop", "foreach")
    return Row(
        "training",
        "ConditionedMlpPolicy TD update (4 × 256, 2 × 128 rows), Adam foreach vs its loop over the parameters",
        fmt_time(float(np.median(samples["foreach"]))),
        fmt_time(float(np.median(samples["loop"]))),
        ratio,
        "",
        None,
        f"the policy's default (foreach) against the loop; per-round quartiles {q1:.2f}–{q3:.2f}",
    )


def _mlp_against_dqn_row(quick: bool) -> Row:
    """Training steps per second of MLP SFDQN against SB3's DQN on the scalarised env, chunks interleaved."""
    repeats = 5 if quick else 21
    chunk = 200 if quick else 300

    def sfdqn(policy="MlpPolicy"):
        model = _silent(SFDQN(policy, four_room(), weights=WEIGHTS, seed=0, **MLP_KWARGS))
        return lambda n: model.learn(n, reset_num_timesteps=False)

    def dqn():
        model = _silent(DQN("MlpPolicy", scalarized_four_room(WEIGHTS), seed=0, **MLP_KWARGS))
        return lambda n: model.learn(n, reset_num_timesteps=False)

    samples = chunked_interleaved(
        {"sfdqn": sfdqn, "dqn": dqn, "one-pass": lambda: sfdqn(OnePassPolicy)}, chunk, repeats
    )
    times = _median(samples)
    ratio, q1, q3 = paired_ratio(samples, "dqn", "sfdqn")
    one_pass = paired_ratio(samples, "dqn", "one-pass")[0]
    return Row(
        "training",
        "MLP SFDQN vs SB3 DQN, four-room-v0",
        fmt_rate(chunk / times["sfdqn"], "steps"),
        fmt_rate(chunk / times["dqn"], "steps"),
        ratio,
        f"≥ {TARGET_DQN}×",
        ratio >= TARGET_DQN,
        f"per-round ratios: quartiles {q1:.2f}–{q3:.2f}; with the one-pass TD update: {one_pass:.2f}× DQN; "
        f"{repeats} interleaved chunks of {chunk} steps",
    )


def _td_update_rows(quick: bool) -> list[Row]:
    """The TD update alone, on one filled buffer: one online pass over [s, s'] vs two passes (current)."""
    model = _silent(SFDQN("MlpPolicy", four_room(), weights=WEIGHTS, seed=0, **MLP_KWARGS))
    model.learn(500)
    current, candidate = model.policy, copy.deepcopy(model.policy)
    candidate.__class__ = OnePassPolicy
    rows = []
    for batch in (32, 64, 256):
        samples = interleaved_samples(
            {
                "current": lambda b=batch: current.td_update(model.replay_buffer, b, 0.99, 10.0),
                "one-pass": lambda b=batch: candidate.td_update(model.replay_buffer, b, 0.99, 10.0),
            },
            repeats=7 if quick else 15,
            number=50 if quick else 200,
        )
        ratio, q1, q3 = paired_ratio(samples, "current", "one-pass")
        rows.append(
            Row(
                "training",
                f"MLP TD update, batch {batch}: one online pass over [s, s′] vs the current two",
                fmt_time(float(np.median(samples["one-pass"]))),
                fmt_time(float(np.median(samples["current"]))),
                ratio,
                "",
                None,
                f"the candidate fix of the issue, not adopted; per-round quartiles {q1:.2f}–{q3:.2f}",
            )
        )
    return rows


def run_tabular(quick: bool = False) -> list[Row]:
    """Tabular SFDQN vs plain numpy tabular SF Q-learning."""
    rows = []
    repeats = 5 if quick else 11
    chunk = 500 if quick else 2_000

    def tabular(cls=SFDQN):
        model = _silent(cls("TabularPolicy", four_room(xy=True), weights=WEIGHTS, seed=0, **TABULAR_KWARGS))
        return lambda n: model.learn(n, reset_num_timesteps=False)

    def numpy_loop():
        return NumpyTabularSF(four_room(xy=True), WEIGHTS, seed=0, **TABULAR_KWARGS).learn

    samples = chunked_interleaved(
        {"sb3": tabular, "numpy": numpy_loop, "loop": lambda: tabular(SB3LoopOnly)}, chunk, repeats
    )
    times = _median(samples)
    rows.append(
        Row(
            "training",
            "tabular SFDQN vs numpy SF Q-learning, four-room xy",
            fmt_rate(chunk / times["sb3"], "steps"),
            fmt_rate(chunk / times["numpy"], "steps"),
            paired_ratio(samples, "numpy", "sb3")[0],
            "→ 1×",
            None,
            f"SB3's loop alone (no acting, no learning): {fmt_rate(chunk / times['loop'], 'steps')}, "
            f"{paired_ratio(samples, 'numpy', 'loop')[0]:.2f}× numpy; {repeats} interleaved chunks of {chunk} steps",
        )
    )
    return rows


def run_multiagent(quick: bool = False) -> list[Row]:
    """The multi-agent runner vs two single-agent learn loops."""
    rows = []
    repeats = 5 if quick else 11
    chunk = 300 if quick else 1_000

    def runner():
        env = FourRoomParallelEnv(observation_mode="xy")
        ma = MultiAgentRunner(env, default_learner_factory(policy="TabularPolicy", **TABULAR_KWARGS), seed=0)
        callback = FixedWeights({"agent_0": WEIGHTS, "agent_1": WEIGHTS[::-1].copy()}, 10**9)
        return lambda n: ma.learn(n, callback)

    def two_singles():
        models = [
            _silent(SFDQN("TabularPolicy", four_room(xy=True), weights=w, seed=i, **TABULAR_KWARGS))
            for i, w in enumerate([WEIGHTS, WEIGHTS[::-1].copy()])
        ]
        return lambda n: [m.learn(n, reset_num_timesteps=False) for m in models]

    samples = chunked_interleaved({"runner": runner, "singles": two_singles}, chunk, repeats)
    times = _median(samples)
    rows.append(
        Row(
            "training",
            "MultiAgentRunner (2 tabular agents, Four-Room) vs 2 × SFDQN.learn",
            fmt_rate(chunk / times["runner"], "joint steps"),
            fmt_rate(chunk / times["singles"], "joint steps"),
            paired_ratio(samples, "singles", "runner")[0],
            "",
            None,
            f"baseline: N / (t₁ + t₂), two single-agent loops of N steps; {repeats} chunks of {chunk} steps",
        )
    )
    return rows

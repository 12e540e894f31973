"""GPI action selection: ``GPIPolicy.predict`` (one batched pass) vs a per-policy Python loop.

Policy sets of |Π| ∈ {4, 16, 64} random networks, batches of 1 and 256 observations:

* MLP: traffic-sized SF networks (``Box(15,)`` observations, 2 actions, d = 2, hidden [64, 64]);
* tabular: Four-Room tables (``MultiDiscrete([13, 13])`` "xy" observations, 4 actions, d = 3);
* conditioned: the deep preset's weight-conditioned networks, each bound to its own weights (minecart-sized:
  ``Box(7,)`` observations, 6 actions, d = 3, hidden [128, 128, 128], two heads).

The baseline runs the same networks one after the other (``net(obs) @ w``, then max over policies and argmax
over actions). The "vmap" column is the generic ``stack_module_state`` + ``vmap`` path that ``predict`` used
before the specialised stacked paths (same code as the old ``predict``), kept as a before/after reference.
Target: ≥ 5× at |Π| = 64, batch 1. The latency is per decision (per observation).
"""

from __future__ import annotations

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import FlattenExtractor

from benchmarks._common import Row, calls_for, fmt_time, interleaved
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.sfdqn import SFNetwork, TabularSFNetwork
from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork
from sb3_sfgpi.stacking import StackedVmap

NAME = "gpi"
TARGET = 5.0


def mlp_network(seed: int) -> SFNetwork:
    th.manual_seed(seed)
    space = spaces.Box(0.0, 1.0, shape=(15,), dtype=np.float32)
    extractor = FlattenExtractor(space)
    return SFNetwork(space, spaces.Discrete(2), extractor, extractor.features_dim, 2, net_arch=[64, 64])


def conditioned_network(seed: int) -> ConditionedSFNetwork:
    th.manual_seed(seed)
    space = spaces.Box(-1.0, 1.0, shape=(7,), dtype=np.float32)
    extractor = FlattenExtractor(space)
    return ConditionedSFNetwork(space, spaces.Discrete(6), extractor, extractor.features_dim, 3, net_arch=[128] * 3)


def tabular_network(seed: int) -> TabularSFNetwork:
    net = TabularSFNetwork(spaces.MultiDiscrete([13, 13]), spaces.Discrete(4), 3)
    generator = th.Generator().manual_seed(seed)
    net.table.set_dense(th.randn((net.table.n_rows, net.table.width), generator=generator).numpy())
    return net


def loop_predict(networks: list, observation: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The baseline: GPI with one forward pass per policy."""
    obs_tensor, vectorized = networks[0].obs_to_tensor(observation)
    weights = th.as_tensor(validate_weights(w, networks[0].reward_dim), dtype=th.float32)
    with th.no_grad():
        q = th.stack([net(obs_tensor) @ weights for net in networks]).max(dim=0).values
    actions = q.argmax(dim=1).numpy()
    return actions if vectorized else actions[0]


def vmap_predict(policy_set: GPIPolicy, stacked: StackedVmap, observation: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The previous ``GPIPolicy.predict``: SB3's obs_to_tensor, then vmap over the stacked module state."""
    weights = th.as_tensor(validate_weights(w, policy_set.reward_dim), dtype=th.float32)
    obs_tensor, vectorized = policy_set.networks[0].obs_to_tensor(observation)
    with th.no_grad():
        actions = (stacked.psi(obs_tensor) @ weights).max(dim=0).values.argmax(dim=1).numpy()
    return actions if vectorized else actions[0]


def run(quick: bool = False) -> list[Row]:
    rows = []
    repeats, seconds = (5, 0.03) if quick else (11, 0.15)
    kinds = {
        "MLP": (mlp_network, spaces.Box(0.0, 1.0, shape=(15,), dtype=np.float32), 2),
        "tabular": (tabular_network, spaces.MultiDiscrete([13, 13]), 3),
        "conditioned": (conditioned_network, spaces.Box(-1.0, 1.0, shape=(7,), dtype=np.float32), 3),
    }
    for kind, (make, space, d) in kinds.items():
        for n_policies in (4, 16, 64):
            networks = [make(seed) for seed in range(n_policies)]
            policy_set = GPIPolicy()
            for seed, net in enumerate(networks):  # a conditioned member is bound to its weights: its own
                own = np.random.default_rng(seed).dirichlet(np.ones(d)) if kind == "conditioned" else np.ones(d)
                policy_set.add(net, weights=own)
            stacked = StackedVmap(policy_set.networks) if kind != "tabular" else None  # tables: no torch parameters
            w = np.random.default_rng(0).dirichlet(np.ones(d))
            for batch in (1, 256):
                space.seed(batch)
                obs = space.sample() if batch == 1 else np.stack([space.sample() for _ in range(batch)])
                q = policy_set.q_values(obs, w)
                chosen = np.atleast_1d(policy_set.predict(obs, w)[0])
                np.testing.assert_allclose(q[np.arange(len(chosen)), chosen], q.max(axis=1), rtol=1e-5)
                loop_actions = np.atleast_1d(loop_predict(policy_set.networks, obs, w))
                np.testing.assert_allclose(q[np.arange(len(chosen)), loop_actions], q.max(axis=1), rtol=1e-5)
                functions = {
                    "predict": lambda s=policy_set, o=obs, w=w: s.predict(o, w),
                    "loop": lambda s=policy_set, o=obs, w=w: loop_predict(s.networks, o, w),
                }
                if stacked is not None:
                    functions["vmap"] = lambda s=policy_set, k=stacked, o=obs, w=w: vmap_predict(s, k, o, w)
                number = calls_for(functions["loop"], seconds)
                times = interleaved(functions, repeats, number)
                ratio = times["loop"] / times["predict"]
                big = n_policies == 64 and batch == 1
                rows.append(
                    Row(
                        "GPI predict",
                        f"{kind} |Π|={n_policies} batch={batch}",
                        f"{fmt_time(times['predict'] / batch)}/decision",
                        f"{fmt_time(times['loop'] / batch)}/decision",
                        ratio,
                        f"≥ {TARGET:g}×" if big else "",
                        ratio >= TARGET if big else None,
                        f"vmap path (before): {fmt_time(times['vmap'] / batch)}/decision, "
                        f"{times['loop'] / times['vmap']:.1f}× the loop"
                        if stacked is not None
                        else "",
                    )
                )
    return rows

"""Memory: resident size of a million-transition replay buffer and of a 64-policy set.

Every measurement runs in a fresh Python process (``python -m benchmarks.bench_memory --child ...``): imports
first, then the resident set size (RSS) before and after building the object and writing to every element of its
arrays (numpy allocates lazily: untouched pages cost nothing).

* **Replay buffers** of 1,000,000 transitions (one env): ``MOReplayBuffer`` vs SB3's ``ReplayBuffer`` (scalar
  rewards) on the same spaces, with and without ``optimize_memory_usage``:

  - Four-Room "xy": ``MultiDiscrete([13, 13])`` observations (``int64``), 4 actions, d = 3;
  - Four-Room "full" (the ``four-room`` preset's): ``MultiDiscrete([13, 13] + [2] * 12)`` (``int64``);
  - traffic: ``Box(0, 1, (15,), float32)`` observations, 2 actions, d = 2.

  The ratio is SB3's bytes / ours: the vector rewards cost ``4 (d - 1)`` bytes more per transition.
* **Policy sets** of 64 policies in a ``GPIPolicy`` after one ``predict`` (which builds the stacked parameters):
  traffic-sized MLP SF networks (15 inputs, [64, 64], 2 actions × d = 2) and Four-Room tables (169 states ×
  4 actions × d = 3, every row stored). The baseline is the bytes of the parameters (a table's stored rows) themselves
  (one copy).
"""

from __future__ import annotations

import gc
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks._common import Row, fmt_bytes, rss_bytes

NAME = "memory"
N = 1_000_000
BUFFERS = [  # (label, space, d, n_actions)
    ("Four-Room xy", "xy", 3, 4),
    ("Four-Room full", "full", 3, 4),
    ("traffic", "traffic", 2, 2),
]


def _space(kind: str):
    import numpy as np
    from gymnasium import spaces

    if kind == "xy":
        return spaces.MultiDiscrete([13, 13])
    if kind == "full":
        return spaces.MultiDiscrete([13, 13] + [2] * 12)
    return spaces.Box(0.0, 1.0, shape=(15,), dtype=np.float32)


def child_buffer(kind: str, d: int, n_actions: int, which: str, optimize: bool) -> dict:
    from gymnasium import spaces
    from stable_baselines3.common.buffers import ReplayBuffer

    from sb3_sfgpi.common.buffers import MOReplayBuffer

    gc.collect()
    before = rss_bytes()
    space, actions = _space(kind), spaces.Discrete(n_actions)
    if which == "mo":
        buffer = MOReplayBuffer(N, space, actions, device="cpu", optimize_memory_usage=optimize, reward_dim=d)
    else:
        buffer = ReplayBuffer(
            N, space, actions, device="cpu", optimize_memory_usage=optimize, handle_timeout_termination=not optimize
        )
    arrays = [
        getattr(buffer, name)
        for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
        if getattr(buffer, name, None) is not None
    ]
    for array in arrays:
        array.fill(1)
    return {"rss": rss_bytes() - before, "nbytes": sum(a.nbytes for a in arrays)}


def child_policy_set(kind: str, n_policies: int) -> dict:
    import numpy as np
    import torch as th
    from gymnasium import spaces
    from stable_baselines3.common.torch_layers import FlattenExtractor

    from sb3_sfgpi.gpi import GPIPolicy
    from sb3_sfgpi.sfdqn import SFNetwork, TabularSFNetwork

    th.set_num_threads(1)

    def make():
        if kind == "mlp":
            space = spaces.Box(0.0, 1.0, shape=(15,), dtype=np.float32)
            extractor = FlattenExtractor(space)
            return SFNetwork(space, spaces.Discrete(2), extractor, extractor.features_dim, 2, net_arch=[64, 64]), 2
        net = TabularSFNetwork(spaces.MultiDiscrete([13, 13]), spaces.Discrete(4), 3)
        net.table.set_dense(np.ones((net.table.n_rows, net.table.width)))  # every row learned
        return net, 3

    # Warm up the allocator and torch with one throw-away set, then measure a fresh one.
    warm = GPIPolicy()
    net, d = make()
    warm.add(net, weights=np.ones(d))
    warm.predict(net.observation_space.sample(), np.ones(d))
    del warm, net
    gc.collect()
    before = rss_bytes()
    policy_set = GPIPolicy()
    for _ in range(n_policies):
        net, d = make()
        policy_set.add(net, weights=np.ones(d))
        del net
    policy_set.predict(policy_set.observation_space.sample(), np.ones(d))
    gc.collect()
    first = policy_set.networks[0]
    if isinstance(first, TabularSFNetwork):
        params = first.table.stored_values().nbytes * n_policies
    else:
        params = sum(p.numel() * p.element_size() for p in first.parameters()) * n_policies
    return {"rss": rss_bytes() - before, "nbytes": params}


def _measure(args: list[str], repeats: int, env: dict[str, str] | None = None) -> dict:
    root = Path(__file__).resolve().parents[1]
    results = []
    for _ in range(repeats):
        out = subprocess.run(
            [sys.executable, "-m", "benchmarks.bench_memory", "--child", *args],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
            env=None if env is None else {**os.environ, **env},
        )
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    if "results" in results[0]:
        return results[0]
    return {"rss": statistics.median(r["rss"] for r in results), "nbytes": results[0]["nbytes"]}


def run(quick: bool = False) -> list[Row]:
    repeats = 1 if quick else 3
    rows = []
    # --quick measures the eight buffers one after the other in one process, each freed before the next. glibc
    # raises its mmap threshold after freeing a mapped block, and later arrays under 32 MB would then come from the
    # heap, already resident: the fixed threshold keeps every array in its own mapping, as in a fresh process.
    # The full run gives each buffer its own fresh processes.
    batch = _measure(["buffers"], 1, {"MALLOC_MMAP_THRESHOLD_": "131072"})["results"] if quick else None
    for label, kind, d, n_actions in BUFFERS:
        for optimize in (False, True):
            if batch is not None:
                ours, sb3 = batch[f"{kind}-mo-{int(optimize)}"], batch[f"{kind}-sb3-{int(optimize)}"]
            else:
                ours = _measure(["buffer", kind, str(d), str(n_actions), "mo", str(int(optimize))], repeats)
                sb3 = _measure(["buffer", kind, str(d), str(n_actions), "sb3", str(int(optimize))], repeats)
            rows.append(
                Row(
                    "memory",
                    f"MOReplayBuffer 10⁶ transitions, {label}{', optimize_memory_usage' if optimize else ''}",
                    fmt_bytes(ours["rss"]),
                    fmt_bytes(sb3["rss"]),
                    sb3["rss"] / ours["rss"],
                    "",
                    None,
                    f"baseline: SB3 ReplayBuffer (scalar rewards); array bytes {fmt_bytes(ours['nbytes'])} "
                    f"(SB3 {fmt_bytes(sb3['nbytes'])}), {ours['rss'] / N:.0f} B/transition",
                )
            )
    for kind, label in (("mlp", "MLP [64, 64], traffic-sized"), ("tabular", "tabular Four-Room")):
        result = _measure(["set", kind, "64"], repeats)
        rows.append(
            Row(
                "memory",
                f"GPIPolicy of 64 policies, {label}",
                fmt_bytes(result["rss"]),
                fmt_bytes(result["nbytes"]),
                result["nbytes"] / result["rss"],
                "",
                None,
                "baseline: the parameters' bytes (one copy); the set keeps each network and one stacked copy",
            )
        )
    return rows


def _child(argv: list[str]) -> None:
    if argv[0] == "buffers":
        results = {}
        for _, kind, d, n_actions in BUFFERS:
            for optimize in (False, True):
                for which in ("mo", "sb3"):
                    results[f"{kind}-{which}-{int(optimize)}"] = child_buffer(kind, d, n_actions, which, optimize)
                    gc.collect()
        print(json.dumps({"results": results}))
        return
    if argv[0] == "buffer":
        kind, d, n_actions, which, optimize = argv[1:]
        result = child_buffer(kind, int(d), int(n_actions), which, bool(int(optimize)))
    else:
        result = child_policy_set(argv[1], int(argv[2]))
    print(json.dumps(result))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(sys.argv[2:])

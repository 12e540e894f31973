"""Traffic env: decisions per second against raw libsumo, and parallel evaluation with 1 vs 2 processes.

1. **Env vs raw libsumo.** ``TrafficSignalEnv`` (three intersections, ``delta_time = 5`` s) driven by a fixed
   random keep/change sequence, against a bare libsumo loop over the same network, demand and seed that sends the
   same light states at the same seconds (recorded from the env) and makes the same TraCI queries: per simulated
   second the vehicles and persons on every approach, the accumulated waiting time of vehicles that enter or leave
   it, every person's waiting time and the four departure/arrival counters; per decision the waiting time of every
   vehicle on the approaches and the vehicle number and halting number of every incoming lane. What is left is
   the env's own Python (bookkeeping, observations, rewards, infos, PettingZoo dicts). Only the stepping is timed
   (not SUMO's start or reload). Target ≥ 0.8×.
2. **Parallel evaluation.** Episodes of SUMO's fixed-time program (the evaluation of a baseline) in a pool of
   spawned worker processes, 1 vs 2 workers, pools started and warmed up before timing. Uses the library's
   ``sb3_sfgpi.evaluation_jobs.ParallelEvaluator`` when it exists, else a local ``ProcessPoolExecutor`` running
   ``sfgpi_envs.traffic.run_program_episode``. On a machine shared with other jobs the second process may not get a
   core of its own.
"""

from __future__ import annotations

import multiprocessing
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import Row, fmt_rate

NAME = "traffic"
TARGET = 0.8


def _env(**kwargs: Any):
    from sfgpi_envs.traffic import TrafficSignalEnv

    return TrafficSignalEnv(**kwargs)


def record_episode(num_seconds: int, seed: int, actions: np.ndarray, workdir: Path) -> tuple[list[str], dict, list]:
    """
    Run one env episode with the given actions and record what the raw loop needs to replay it.

    :return: SUMO arguments (route file copied into ``workdir``), the light states sent per second
        (``{time: [(tls, state), ...]}``), and the intersection layouts
    """
    env = _env(num_seconds=num_seconds, seed=seed)
    try:
        env.reset(seed=seed)  # binds the simulation; the second reset below reuses the binding
        changes: dict[int, list[tuple[str, str]]] = {}
        send = env._set_state

        def recording(tls: str, state: str) -> None:
            changes.setdefault(env.sim_time, []).append((tls, state))
            send(tls, state)

        env._set_state = recording
        env.reset(seed=seed)
        for row in actions:
            if not env.agents:
                break
            env.step(dict(zip(env.possible_agents, (int(a) for a in row), strict=True)))
        args = env.sumo_command(seed)
        route = Path(args[args.index("--route-files") + 1])
        copied = workdir / route.name
        shutil.copy(route, copied)
        args[args.index("--route-files") + 1] = str(copied)
        return args, changes, [env.layouts[a] for a in env.possible_agents]
    finally:
        env.close()


def env_episode(num_seconds: int, seed: int, actions: np.ndarray) -> tuple[float, int]:
    """Seconds spent in ``env.step`` over one episode, and the number of decisions."""
    env = _env(num_seconds=num_seconds, seed=seed)
    try:
        env.reset(seed=seed)
        agents = env.possible_agents
        start = time.perf_counter()
        n = 0
        for row in actions:
            if not env.agents:
                break
            env.step(dict(zip(agents, (int(a) for a in row), strict=True)))
            n += 1
        return time.perf_counter() - start, n
    finally:
        env.close()


def raw_episode(args: list[str], changes: dict, layouts: list, num_seconds: int, delta_time: int) -> tuple[float, int]:
    """The same simulation and the same TraCI queries in a bare libsumo loop: seconds stepping, and decisions."""
    import libsumo
    from sfgpi_envs.traffic.sumo_backend import find_sumo_binary

    libsumo.start([find_sumo_binary(), *args])
    try:
        set_state = libsumo.trafficlight.setRedYellowGreenState
        simulation_step = libsumo.simulationStep
        vehicle_ids, person_ids = libsumo.edge.getLastStepVehicleIDs, libsumo.edge.getLastStepPersonIDs
        accumulated, person_wait = libsumo.vehicle.getAccumulatedWaitingTime, libsumo.person.getWaitingTime
        lane_count, lane_halting = libsumo.lane.getLastStepVehicleNumber, libsumo.lane.getLastStepHaltingNumber
        sim = libsumo.simulation
        counters = (
            sim.getDepartedNumber,
            sim.getArrivedNumber,
            sim.getDepartedPersonNumber,
            sim.getArrivedPersonNumber,
        )
        on: list[set[str]] = [set() for _ in layouts]
        decisions = 0
        start = time.perf_counter()
        for t in range(num_seconds):
            for tls, state in changes.get(t, ()):
                set_state(tls, state)
            simulation_step()
            for k, layout in enumerate(layouts):
                current: set[str] = set()
                for edge in layout.vehicle_edges:
                    current.update(vehicle_ids(edge))
                for v in current - on[k]:
                    accumulated(v)
                for v in on[k] - current:
                    try:
                        accumulated(v)
                    except libsumo.TraCIException:
                        pass
                on[k] = current
                for edge in layout.pedestrian_edges:
                    for p in person_ids(edge):
                        person_wait(p)
            for counter in counters:
                counter()
            if (t + 1) % delta_time == 0 or t + 1 == num_seconds:
                decisions += 1
                for k, layout in enumerate(layouts):
                    for v in on[k]:
                        accumulated(v)
                    for lane in layout.vehicle_lanes:
                        lane_count(lane)
                        lane_halting(lane)
        return time.perf_counter() - start, decisions
    finally:
        libsumo.close()


def _program_episode(seed: int, num_seconds: int) -> dict[str, float]:
    from sfgpi_envs.traffic import run_program_episode

    return run_program_episode("fixed-time", seed=seed, num_seconds=num_seconds)


def _warm(_: int) -> int:
    import sfgpi_envs.traffic  # noqa: F401 - import in the worker before timing

    return 0


class _LocalPool:
    """The fallback evaluator: fixed-time episodes in spawned processes."""

    name = "local ProcessPoolExecutor + run_program_episode"

    def __init__(self, workers: int, num_seconds: int):
        self.num_seconds = num_seconds
        self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        list(self.pool.map(_warm, range(workers)))

    def run(self, seeds: list[int]) -> None:
        list(self.pool.map(_program_episode, seeds, [self.num_seconds] * len(seeds)))

    def close(self) -> None:
        self.pool.shutdown()


class _LibraryPool:
    """The library's ParallelEvaluator running jobs without a policy (the env's fixed-time program acts)."""

    name = "sb3_sfgpi ParallelEvaluator"

    def __init__(self, workers: int, num_seconds: int):
        from sfgpi_envs.traffic import TrafficSignalEnv

        from sb3_sfgpi.evaluation_jobs import EvaluationJob, ParallelEvaluator

        self.job = EvaluationJob
        self.pool = ParallelEvaluator(
            TrafficSignalEnv, {"num_seconds": num_seconds, "signal_control": "fixed-time"}, workers=workers
        )
        self.run(list(range(10_000, 10_000 + workers)))  # spawn the workers and build their envs

    def run(self, seeds: list[int]) -> None:
        self.pool.run([self.job(seed) for seed in seeds])

    def close(self) -> None:
        self.pool.close()


def _make_pool(workers: int, num_seconds: int):
    try:
        return _LibraryPool(workers, num_seconds)
    except ImportError:
        return _LocalPool(workers, num_seconds)


def run(quick: bool = False) -> list[Row]:
    return [_env_row(quick), _parallel_evaluation_row(quick)]


def _env_row(quick: bool) -> Row:
    """The env against raw libsumo replaying the same episode: same states set, same queries."""
    num_seconds, delta_time = (200, 5) if quick else (500, 5)
    repeats = 3 if quick else 7
    actions = np.random.default_rng(0).integers(0, 2, size=(num_seconds // delta_time + 1, 3))
    workdir = Path(tempfile.mkdtemp(prefix="bench_traffic_"))
    try:
        args, changes, layouts = record_episode(num_seconds, 0, actions, workdir)
        env_times, raw_times = [], []
        for r in range(repeats + 1):  # the first round warms up
            order = ("env", "raw") if r % 2 == 0 else ("raw", "env")
            for side in order:
                if side == "env":
                    seconds, n_env = env_episode(num_seconds, 0, actions)
                    env_times.append(seconds)
                else:
                    seconds, n_raw = raw_episode(args, changes, layouts, num_seconds, delta_time)
                    raw_times.append(seconds)
        assert n_env == n_raw, (n_env, n_raw)
        t_env, t_raw = float(np.median(env_times[1:])), float(np.median(raw_times[1:]))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    ratio = t_raw / t_env
    return Row(
        "traffic env",
        f"3 intersections, {num_seconds} s episodes, delta_time {delta_time} s",
        fmt_rate(n_env / t_env, "decisions"),
        fmt_rate(n_raw / t_raw, "decisions"),
        ratio,
        f"≥ {TARGET}×",
        ratio >= TARGET,
        f"baseline: raw libsumo, same states and queries; median of {repeats} interleaved episodes",
    )


def _parallel_evaluation_row(quick: bool) -> Row:
    """Fixed-time episodes in a pool of two worker processes against one."""
    eval_seconds = 200 if quick else 500
    n_episodes = 4 if quick else 8
    pools = {workers: _make_pool(workers, eval_seconds) for workers in (1, 2)}
    try:
        samples: dict[int, list[float]] = {1: [], 2: []}
        for r in range(2 if quick else 3):
            for workers in (1, 2) if r % 2 == 0 else (2, 1):
                seeds = list(range(r * 100, r * 100 + n_episodes))
                start = time.perf_counter()
                pools[workers].run(seeds)
                samples[workers].append(time.perf_counter() - start)
        name = pools[1].name
    finally:
        for pool in pools.values():
            pool.close()
    t1, t2 = float(np.median(samples[1])), float(np.median(samples[2]))
    return Row(
        "parallel evaluation",
        f"fixed-time episodes ({eval_seconds} s), 2 processes vs 1",
        fmt_rate(n_episodes / t2, "episodes"),
        fmt_rate(n_episodes / t1, "episodes"),
        t1 / t2,
        "",
        None,
        f"{name}; {n_episodes} episodes per sample, warm pools, median of {len(samples[1])}",
    )

"""TrafficSignalEnv on the real simulator (short episodes)."""

from __future__ import annotations

import gc
import itertools
import os
import signal
import sys
from collections import defaultdict

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

libsumo = pytest.importorskip("libsumo")
traci = pytest.importorskip("traci")

from sfgpi_envs.traffic import (  # noqa: E402
    EPISODE_METRIC_KEYS,
    NET_FILE,
    PEDESTRIAN_METRIC_KEYS,
    ROUTE_FILE,
    SignalController,
    SignalProgram,
    SumoLoadError,
    SumoNotFoundError,
    TrafficSignalEnv,
    run_program_episode,
    sumo_backend,
)

SHORT = 150  # seconds per test episode


@pytest.fixture
def make_env():
    """Factory of environments that are all closed at teardown."""
    envs: list[TrafficSignalEnv] = []

    def factory(**kwargs) -> TrafficSignalEnv:
        kwargs.setdefault("num_seconds", SHORT)
        env = TrafficSignalEnv(**kwargs)
        envs.append(env)
        return env

    yield factory
    for env in envs:
        env.close()


# --------------------------------------------------------------------------------------------------
# independent per-second observers, registered as TraCI step listeners
# --------------------------------------------------------------------------------------------------
class WaitingRecorder(traci.StepListener):
    """Recomputes W^v and W^p (Eqs. 24-25) every simulated second, straight from the SUMO API.

    Incoming vehicle lanes and the pedestrian waiting area are read from the traffic light's controlled
    lanes; the incoming sidewalk from the junction's incoming edges.
    """

    def __init__(self, api, tls_ids):
        super().__init__()
        self.api = api
        self.veh_lanes, self.ped_edges = {}, {}
        for j in tls_ids:
            controlled = list(dict.fromkeys(api.trafficlight.getControlledLanes(j)))
            self.veh_lanes[j] = [ln for ln in controlled if not ln.startswith(":")]
            areas = [ln.rsplit("_", 1)[0] for ln in controlled if ln.startswith(":")]
            sidewalks = [
                e
                for e in api.junction.getIncomingEdges(j)
                if not e.startswith(":")
                and any("pedestrian" in api.lane.getAllowed(f"{e}_{k}") for k in range(api.edge.getLaneNumber(e)))
            ]
            self.ped_edges[j] = sidewalks + areas
        self.entry = defaultdict(dict)  # tls -> vehicle -> accumulated waiting time when first seen
        self.veh_on = defaultdict(set)
        self.ped_wait = defaultdict(lambda: defaultdict(float))  # tls -> person -> seconds standing
        self.ped_on = defaultdict(set)
        self.veh_gone = defaultdict(float)  # tls -> waiting time of the vehicles that left its lanes
        self.ped_gone = defaultdict(float)

    def step(self, t):
        api = self.api
        for j, lanes in self.veh_lanes.items():
            on = set()
            for lane in lanes:
                for v in api.lane.getLastStepVehicleIDs(lane):
                    on.add(v)
                    if v not in self.entry[j]:
                        self.entry[j][v] = api.vehicle.getAccumulatedWaitingTime(v)
            for v in self.veh_on[j] - on:
                self.veh_gone[j] += api.vehicle.getAccumulatedWaitingTime(v) - self.entry[j].pop(v)
            self.veh_on[j] = on
            persons = set()
            for e in self.ped_edges[j]:
                for p in api.edge.getLastStepPersonIDs(e):
                    persons.add(p)
                    if api.person.getWaitingTime(p) > 0:
                        self.ped_wait[j][p] += 1.0
            for p in self.ped_on[j] - persons:
                self.ped_gone[j] += self.ped_wait[j].pop(p, 0.0)
            self.ped_on[j] = persons
        return True

    def waiting(self, j):
        w_v = sum(self.api.vehicle.getAccumulatedWaitingTime(v) - self.entry[j][v] for v in self.veh_on[j])
        w_p = sum(self.ped_wait[j].get(p, 0.0) for p in self.ped_on[j])
        return w_v, w_p

    def waiting_so_far(self, j):
        """Waiting time spent at intersection ``j`` since the start, by the vehicles and persons gone too."""
        w_v, w_p = self.waiting(j)
        return self.veh_gone[j] + w_v, self.ped_gone[j] + w_p


class PhaseRecorder(traci.StepListener):
    """Records the signal state shown during every simulated second."""

    def __init__(self, api, tls_ids):
        super().__init__()
        self.api = api
        self.states = {j: [] for j in tls_ids}
        self.programs = {j: set() for j in tls_ids}

    def step(self, t):
        for j, seq in self.states.items():
            seq.append(self.api.trafficlight.getRedYellowGreenState(j))
            self.programs[j].add(self.api.trafficlight.getProgram(j))
        return True


def _runs(seq):
    return [(state, len(list(group))) for state, group in itertools.groupby(seq)]


def _check_phase_rules(seq, *, min_green, max_green, yellow_time, greens, yellows):
    runs = _runs(seq)
    assert len(runs) >= 2
    for k, (state, n) in enumerate(runs):
        last = k == len(runs) - 1
        if state in yellows:
            assert n == yellow_time or last, runs
            nxt = runs[k + 1][0] if not last else None
            assert last or nxt == greens[(yellows.index(state) + 1) % 2], runs
        else:
            assert state in greens, f"unexpected state {state}"
            assert n <= max_green, runs
            assert n >= min_green or last, runs
            assert last or runs[k + 1][0] == yellows[greens.index(state)], runs
    return [n for state, n in runs[:-1] if state in greens]


# --------------------------------------------------------------------------------------------------
# API
# --------------------------------------------------------------------------------------------------
def test_parallel_api(make_env):
    env = make_env(num_seconds=60, seed=0)
    parallel_api_test(env, num_cycles=15)


def test_momalands_api_test(make_env):
    api_test = pytest.importorskip("momaland.test.api_test").api_test
    conversions = pytest.importorskip("momaland.utils.conversions")
    api_test(conversions.mo_parallel_to_aec(make_env(num_seconds=60, seed=0)), num_cycles=15)


def test_spaces(make_env):
    env = make_env()
    assert env.possible_agents == ["J1", "J2", "J3"]
    for a in env.possible_agents:
        assert env.observation_space(a).shape == (15,)  # 2 (rho) + 1 (tau) + 2 x 6 lanes
        assert env.observation_space(a).dtype == np.float32
        assert env.action_space(a).n == 2
        rs = env.reward_space(a)
        assert rs.shape == (2,) and rs.dtype == np.float32 and rs is env.reward_spaces[a]


def test_observations_in_unit_box_and_episode_end(make_env):
    env = make_env(seed=1)
    obs, infos = env.reset()
    rng = np.random.default_rng(0)
    steps = 0
    while env.agents:
        for a, o in obs.items():
            assert o.dtype == np.float32 and env.observation_space(a).contains(o), o
            assert o[:2].sum() == 1.0  # one-hot green phase
        obs, rewards, terms, truncs, infos = env.step({a: int(rng.integers(2)) for a in env.agents})
        for a in rewards:
            assert rewards[a].shape == (2,) and rewards[a].dtype == np.float32
            info = infos[a]
            for key in ("vehicle_wait_total", "vehicle_wait_mean", "pedestrian_wait_total", "pedestrian_wait_mean"):
                assert info[key] >= 0
            if info["vehicles_incoming"]:
                mean = info["vehicle_wait_total"] / info["vehicles_incoming"]
                assert info["vehicle_wait_mean"] == pytest.approx(mean)
        steps += 1
    assert steps == SHORT // env.delta_time
    assert all(truncs.values()) and not any(terms.values())
    nonzero = np.concatenate(list(obs.values()))
    assert nonzero[3:].max() > 0  # lanes are not empty
    for a in env.possible_agents:
        assert set(EPISODE_METRIC_KEYS) <= set(infos[a]["episode"])
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


@pytest.mark.parametrize("backend", ["libsumo", "traci"])
def test_reward_is_change_of_waiting_times(make_env, listen, backend):
    env = make_env(seed=2, backend=backend, num_seconds=200 if backend == "libsumo" else 160)
    env.reset()
    api = env.sim.api
    rec = WaitingRecorder(api, env.possible_agents)
    listen(api, rec)
    prev = {j: (0.0, 0.0) for j in env.possible_agents}  # empty network at t = 0
    rng = np.random.default_rng(3)
    seen_v = seen_p = 0.0
    while env.agents:
        _, rewards, _, _, infos = env.step({a: int(rng.integers(2)) for a in env.agents})
        for j in env.possible_agents:
            w_v, w_p = rec.waiting(j)
            assert infos[j]["vehicle_wait_total"] == pytest.approx(w_v)
            assert infos[j]["pedestrian_wait_total"] == pytest.approx(w_p)
            expected = np.array([prev[j][0] - w_v, prev[j][1] - w_p], dtype=np.float32)
            np.testing.assert_allclose(rewards[j], expected, atol=1e-3)
            prev[j] = (w_v, w_p)
            seen_v, seen_p = max(seen_v, w_v), max(seen_p, w_p)
    assert seen_v > 0 and seen_p > 0  # both objectives were exercised


def test_delay_rewards_are_the_waiting_spent_during_the_step(make_env, listen):
    env = make_env(seed=2, num_seconds=200, objectives=["vehicle_delay", "pedestrian_delay"])
    env.reset()
    api = env.sim.api
    rec = WaitingRecorder(api, env.possible_agents)
    listen(api, rec)
    prev = {j: (0.0, 0.0) for j in env.possible_agents}
    returns = np.zeros(2)
    rng = np.random.default_rng(3)
    while env.agents:
        _, rewards, _, _, infos = env.step({a: int(rng.integers(2)) for a in env.agents})
        for j in env.possible_agents:
            spent = rec.waiting_so_far(j)
            np.testing.assert_allclose(rewards[j], np.subtract(prev[j], spent), atol=1e-3)
            prev[j] = spent
            returns += rewards[j]
    episode = infos[env.possible_agents[0]]["episode"]
    totals = [episode["vehicle_waiting_time_total"], episode["pedestrian_waiting_time_total"]]
    assert min(totals) > 0  # both objectives were exercised
    np.testing.assert_allclose(-returns, totals, rtol=1e-6)  # the returns are the episode's waiting, undiscounted


# --------------------------------------------------------------------------------------------------
# phase control
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("policy", "kwargs"),
    [
        ("random", {}),
        ("always_change", {}),
        ("always_keep", {}),
        ("random", {"delta_time": 3, "yellow_time": 4, "min_green": 7, "max_green": 20}),
        ("always_change", {"delta_time": 4, "yellow_time": 2, "min_green": 5, "max_green": 9}),
        ("random", {"early_change": "defer"}),
        ("always_change", {"early_change": "defer"}),
    ],
)
def test_min_max_green_and_yellow(make_env, listen, policy, kwargs):
    env = make_env(seed=4, num_seconds=200, **kwargs)
    env.reset()
    rec = PhaseRecorder(env.sim.api, env.possible_agents)
    listen(env.sim.api, rec)
    rng = np.random.default_rng(5)
    while env.agents:
        if policy == "random":
            actions = {a: int(rng.integers(2)) for a in env.agents}
        else:
            actions = dict.fromkeys(env.agents, 1 if policy == "always_change" else 0)
        env.step(actions)
    prog = SignalProgram.from_phases([s for s, _ in env.layouts["J1"].phases])
    min_g, max_g = env.min_green, env.max_green
    for j, seq in rec.states.items():
        assert len(seq) == 200
        assert rec.programs[j] == {"online"}  # SUMO's own program never runs
        greens = _check_phase_rules(
            seq,
            min_green=min_g,
            max_green=max_g,
            yellow_time=env.yellow_time,
            greens=prog.greens,
            yellows=prog.yellows,
        )
        if policy == "always_keep":
            assert set(greens) == {max_g}
        elif policy == "always_change" and env.early_change == "defer":
            assert set(greens) == {min_g}  # asked too early, made at min_green, off the 5 s grid
        elif policy == "always_change":
            assert all(min_g <= g < min_g + env.delta_time for g in greens), greens


def test_static_program_does_not_advance(make_env, listen):
    env = make_env(seed=0, max_green=1000)
    env.reset()
    rec = PhaseRecorder(env.sim.api, env.possible_agents)
    listen(env.sim.api, rec)
    while env.agents:
        env.step(dict.fromkeys(env.agents, 0))
    for seq in rec.states.values():
        assert set(seq) == {"GGrrG"}  # the static program would have switched after 30 s


def test_fixed_time_mode_runs_the_static_program(make_env, listen):
    env = make_env(seed=0, signal_control="fixed-time", num_seconds=100)
    env.reset()
    rec = PhaseRecorder(env.sim.api, env.possible_agents)
    listen(env.sim.api, rec)
    while env.agents:
        obs, *_ = env.step(dict.fromkeys(env.agents, 1))  # ignored
    for j, seq in rec.states.items():
        assert _runs(seq)[:4] == [("GGrrG", 30), ("yyrrr", 3), ("rrGGr", 30), ("rryyr", 3)]
        assert rec.programs[j] == {"0"}
        assert env.observation_space(j).contains(obs[j])


def test_signal_controller_unit():
    prog = SignalProgram(("G", "r"), ("y", "Y"))
    ctl = SignalController(prog, min_green=10, max_green=20, yellow_time=3)
    assert ctl.reset(0) == "G"
    assert ctl.act(1, 5) is None  # before min green: ignored
    assert ctl.act(1, 10) == "y" and ctl.in_yellow and ctl.green == 1
    assert ctl.act(1, 11) is None  # during yellow: ignored
    assert ctl.tick(12) is None
    assert ctl.tick(13) == "r" and not ctl.in_yellow and ctl.elapsed_green(13) == 0
    assert ctl.tick(32) is None
    assert ctl.tick(33) == "Y"  # forced after max green
    assert ctl.tick(36) == "G"


def test_signal_controller_defers_early_changes():
    prog = SignalProgram(("G", "r"), ("y", "Y"))
    ctl = SignalController(prog, min_green=10, max_green=20, yellow_time=3, defer_early=True)
    ctl.reset(0)
    assert ctl.act(1, 2) is None and ctl.deferred == 1  # too early: remembered
    assert ctl.tick(9) is None
    assert ctl.tick(10) == "y" and ctl.green == 1 and ctl.deferred is None  # made at min green
    assert ctl.tick(13) == "r" and ctl.elapsed_green(13) == 0
    assert ctl.act(1, 15) is None and ctl.act(0, 20) is None  # asked early, then kept: the later decision wins
    assert ctl.deferred is None and ctl.tick(23) is None and not ctl.in_yellow
    assert ctl.act(1, 21) is None and ctl.reset(22) == "G" and ctl.deferred is None  # reset forgets it
    assert ctl.act(1, 32) == "y"  # at min green or later: at once, as without deferral


def test_early_change_is_validated(make_env):
    with pytest.raises(ValueError, match="early_change must be one of"):
        make_env(early_change="queue")


# --------------------------------------------------------------------------------------------------
# seeding, reset, metrics
# --------------------------------------------------------------------------------------------------
def _rollout(env, seed):
    env.reset(seed=seed)
    rng = np.random.default_rng(0)
    out = []
    while env.agents:
        _, rewards, *_ = env.step({a: int(rng.integers(2)) for a in env.agents})
        out.append(np.stack([rewards[a] for a in env.possible_agents]))
    return np.stack(out), env.episode_metrics()


def test_seed_controls_sumo(make_env):
    env = make_env(num_seconds=100)
    r1, m1 = _rollout(env, 5)
    assert env.sumo_seed == 5
    r2, m2 = _rollout(env, 5)
    r3, _ = _rollout(env, 6)
    np.testing.assert_array_equal(r1, r2)
    assert m1 == m2
    assert not np.array_equal(r1, r3)


@pytest.mark.parametrize("program", ["fixed-time", "actuated", "max-pressure"])
def test_run_program_episode(program):
    m = run_program_episode(program, seed=0)
    assert set(m) == set(EPISODE_METRIC_KEYS) | set(PEDESTRIAN_METRIC_KEYS)  # the paper's network has crossings
    assert m["sim_time"] == 500
    assert m["vehicles_departed"] == 481  # 3 x 152 (one every 3.3 s) + 25 (one every 20 s)
    assert m["pedestrians_departed"] == 500
    assert 0 < m["vehicles_arrived"] <= m["vehicles_departed"]
    assert 0 < m["pedestrians_arrived"] <= m["pedestrians_departed"]  # they crossed all three roads
    for kind, n in (("vehicle", "vehicles_departed"), ("pedestrian", "pedestrians_departed")):
        assert m[f"{kind}_waiting_time_total"] > 0
        assert m[f"{kind}_waiting_time_mean"] == pytest.approx(m[f"{kind}_waiting_time_total"] / m[n])
        assert m[f"{kind}_waiting_time_mean"] < 120


def test_run_program_episode_rejects_unknown_program():
    with pytest.raises(ValueError, match="program"):
        run_program_episode("nope")
    with pytest.raises(ValueError, match="signal_control"):
        run_program_episode("actuated", signal_control="agent")


# --------------------------------------------------------------------------------------------------
# backends and errors
# --------------------------------------------------------------------------------------------------
def test_one_libsumo_simulation_per_process(make_env):
    first, second = make_env(seed=0), make_env(seed=0)
    first.reset()
    with pytest.raises(RuntimeError, match=r"close\(\).*backend='traci'"):
        second.reset()
    first.step({})  # the first environment still drives its own simulation
    assert first.sim_time == first.delta_time == libsumo.simulation.getTime()
    first.close()
    second.reset()
    second.step({})
    assert second.sim_time == libsumo.simulation.getTime() == second.delta_time
    second.close()
    # a dropped environment frees the slot
    third = TrafficSignalEnv(num_seconds=20)
    third.reset()
    del third
    gc.collect()
    fourth = make_env()
    fourth.reset()
    fourth.close()
    # a simulation started by hand is not taken over
    libsumo.start(["sumo", "-n", str(NET_FILE), "--no-step-log"])
    try:
        with pytest.raises(RuntimeError, match="outside"):
            fourth.reset()
    finally:
        libsumo.close()


def test_traci_runs_next_to_libsumo(make_env):
    envs = [
        make_env(seed=7, num_seconds=60),
        make_env(seed=7, num_seconds=60, backend="traci"),
        make_env(seed=7, num_seconds=60, backend="traci"),
    ]
    for e in envs:
        e.reset()
    assert envs[1].sim.label != envs[2].sim.label
    while envs[0].agents:
        outs = [e.step({"J1": 1, "J2": 0, "J3": 1}) for e in envs]
        for out in outs[1:]:
            for a in envs[0].possible_agents:
                np.testing.assert_array_equal(out[1][a], outs[0][1][a])
                np.testing.assert_array_equal(out[0][a], outs[0][0][a])


def test_missing_network_file(tmp_path):
    missing = tmp_path / "nope.net.xml"
    with pytest.raises(FileNotFoundError, match="nope.net.xml"):
        TrafficSignalEnv(net_file=missing)


def test_malformed_network_file(tmp_path):
    bad = tmp_path / "broken.net.xml"
    bad.write_text('<net version="1.20"><edge id="x"')
    with pytest.raises(ValueError, match=r"broken\.net\.xml.*not valid XML"):
        TrafficSignalEnv(net_file=bad)


def test_network_sumo_rejects(tmp_path, make_env):
    bad = tmp_path / "unknown_node.net.xml"
    bad.write_text(NET_FILE.read_text().replace('from="VO1" to="J1"', 'from="NOPE" to="J1"'))
    env = make_env(net_file=bad)
    with pytest.raises(SumoLoadError, match=r"(?s)unknown_node\.net\.xml.*Unknown from-node 'NOPE'"):
        env.reset()
    ok = make_env()  # the libsumo slot was released
    ok.reset()


def test_missing_route_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.rou.xml"):
        TrafficSignalEnv(route_file=tmp_path / "missing.rou.xml")


def test_sumo_not_installed(monkeypatch):
    monkeypatch.setitem(sys.modules, "libsumo", None)
    with pytest.raises(ImportError, match="pip install eclipse-sumo libsumo"):
        TrafficSignalEnv()
    monkeypatch.setitem(sys.modules, "sumo", None)
    monkeypatch.setenv("PATH", "")
    with pytest.raises(SumoNotFoundError, match="pip install eclipse-sumo libsumo"):
        sumo_backend.find_sumo_binary()


def test_simulation_dies_mid_episode_libsumo(make_env):
    env = make_env(seed=0)
    env.reset()
    env.step({})
    libsumo.close()  # something else ends the simulation
    with pytest.raises(RuntimeError, match="stopped unexpectedly at t=5"):
        env.step({})
    assert env.agents == []
    env.reset()  # recovers
    env.step({})


def test_simulation_dies_mid_episode_traci(make_env):
    env = make_env(seed=0, backend="traci", num_seconds=50)
    env.reset()
    env.step({})
    os.kill(env.sim.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match="stopped unexpectedly"):
        env.step({})


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"min_green": 20, "max_green": 10}, "min_green"),
        ({"yellow_time": 0}, "yellow_time"),
        ({"delta_time": 2.5}, "delta_time"),
        ({"signal_control": "magic"}, "signal_control"),
        ({"backend": "libsumo", "gui": True}, "traci"),
        ({"backend": "nope"}, "backend"),
    ],
)
def test_invalid_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrafficSignalEnv(route_file=ROUTE_FILE, **kwargs)


def test_invalid_action(make_env):
    env = make_env(seed=0)
    env.reset()
    with pytest.raises(ValueError, match="keep"):
        env.step({"J1": 2})

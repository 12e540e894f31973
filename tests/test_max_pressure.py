"""Max-pressure as a ``signal_control`` of the traffic env (RESCO's definition, vehicles only): the pressure against a
hand count, min/max green over episodes, fewer waiting vehicles than fixed-time, and its row in ``compare``. Real
SUMO, short episodes."""

from __future__ import annotations

import importlib.util
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytest.importorskip("libsumo")

from sfgpi_envs.traffic import NET_FILE, SignalProgram, TrafficSignalEnv, run_program_episode  # noqa: E402
from sfgpi_envs.traffic.max_pressure import MaxPressure, best_phase, phase_movements, phase_pressures  # noqa: E402

from sb3_sfgpi.cli import main  # noqa: E402

_SPEC = importlib.util.find_spec("sumo_rl")  # located, not imported: importing sumo_rl needs SUMO_HOME
_GRID = None if _SPEC is None or _SPEC.origin is None else Path(_SPEC.origin).parent / "nets" / "2x2grid"
needs_grid = pytest.mark.skipif(_GRID is None, reason="sumo-rl is not installed (its 2x2 grid has four greens)")


def _grid() -> dict[str, str]:
    return {"net_file": str(_GRID / "2x2.net.xml"), "route_file": str(_GRID / "2x2.rou.xml"), "objectives": ["co2"]}


def test_pressure_of_a_synthetic_light():
    # link 0: N->S (two links between the same lanes: one movement), 1: N->E (permissive 'g'), 2: W->E,
    # 3: a pedestrian crossing (from a walking area: not a vehicle movement)
    links = [
        [("n_0", "s_0", ":v0"), ("n_0", "s_0", ":v1")],
        [("n_0", "e_0", ":v2")],
        [("w_0", "e_0", ":v3")],
        [(":c_w0_0", ":c_c0_0", "")],
    ]
    greens = ["GgrG", "rrGr", "GGGr"]
    movements = phase_movements(links, greens, ["n_0", "w_0"])
    assert movements == (
        (("n_0", "s_0"), ("n_0", "e_0")),
        (("w_0", "e_0"),),
        (("n_0", "s_0"), ("n_0", "e_0"), ("w_0", "e_0")),
    )
    queue = {"n_0": 5, "s_0": 1, "e_0": 3, "w_0": 2, ":c_w0_0": 40}  # pedestrians would dominate, were they counted
    assert phase_pressures(movements, queue) == [(5 - 1) + (5 - 3), 2 - 3, (5 - 1) + (5 - 3) + (2 - 3)]
    assert phase_pressures(movements, {}) == [0, 0, 0]
    with pytest.raises(ValueError, match="links"):
        phase_movements(links, ["GGr"], ["n_0"])
    assert best_phase([3, 5, 5], current=0) == 1  # the largest; among ties the lowest index
    assert best_phase([3, 5, 5], current=2) == 2  # a tie with the green shown keeps it
    assert best_phase([9, 5, 5], current=0, exclude_current=True) == 1  # after max green: another one
    assert best_phase([0, 0], current=1) == 1


def _hand_count(net_file: Path, api, tls: str, greens: tuple[str, ...]) -> list[int]:
    """Each green's pressure from the network file's connections and the vehicles' speeds (no halting counter)."""
    root = ET.parse(net_file).getroot()
    normal = {e.get("id") for e in root.iter("edge") if e.get("function", "normal") == "normal"}
    links: dict[int, set[tuple[str, str]]] = {}
    for con in root.iter("connection"):
        if con.get("tl") == tls and con.get("from") in normal:
            move = (f"{con.get('from')}_{con.get('fromLane')}", f"{con.get('to')}_{con.get('toLane')}")
            links.setdefault(int(con.get("linkIndex")), set()).add(move)

    def halting(lane: str) -> int:
        return sum(api.vehicle.getSpeed(v) < 0.1 for v in api.lane.getLastStepVehicleIDs(lane))

    pressures = []
    for state in greens:
        moves = {m for k, ms in links.items() if state[k] in "Gg" for m in ms}
        pressures.append(sum(halting(a) - halting(b) for a, b in moves))
    return pressures


@pytest.mark.parametrize("network", ["paper", pytest.param("2x2grid", marks=needs_grid)])
def test_pressures_equal_a_hand_count_in_sumo(network):
    kwargs = {} if network == "paper" else _grid()
    env = TrafficSignalEnv(num_seconds=150, signal_control="max-pressure", seed=3, **kwargs)
    try:
        env.reset()
        api = env.sim.api
        programs = {t: SignalProgram.from_phases([s for s, _ in lay.phases], t) for t, lay in env.layouts.items()}
        controller = MaxPressure.from_simulation(api, programs, env.layouts)
        nonzero = 0
        while env.agents:
            env.step({})
            for i, (tls, program) in enumerate(programs.items()):
                expected = _hand_count(env.net_file, api, tls, program.greens)
                assert controller.pressures(i) == expected, (env.sim_time, tls)
                nonzero += any(expected)
        assert nonzero > 10  # queues were there to count
    finally:
        env.close()


def _greens(env: TrafficSignalEnv) -> dict[str, list[tuple[int, int, int, list[int]]]]:
    """Run an episode; per light, ``(green, start, end, pressures when it ended)`` of every green shown (the last one
    ends with the episode), from the states the env sends to SUMO; the yellows between are checked to last
    ``yellow_time``."""
    env.reset()
    api, agents = env.sim.api, env.possible_agents
    programs = {t: SignalProgram.from_phases([s for s, _ in lay.phases], t) for t, lay in env.layouts.items()}
    pressure = MaxPressure.from_simulation(api, programs, env.layouts).pressures  # the halting of the last step
    sent = {a: [(env.sim_time, api.trafficlight.getRedYellowGreenState(a), [])] for a in agents}
    send = env._set_state  # the env's one path to the lights: recorded, not replaced

    def record(tls: str, state: str) -> None:
        sent[tls].append((env.sim_time, state, pressure(agents.index(tls))))
        send(tls, state)

    env._set_state = record
    while env.agents:
        env.step({a: 1 for a in agents})  # actions are ignored
    greens = {}
    for tls, states in sent.items():
        lookup = programs[tls].lookup()  # states not in it: yellows derived between two greens
        shown = [(t, *lookup.get(state, (-1, True)), p) for t, state, p in states] + [(env.sim_time, -1, True, [])]
        pairs = list(zip(shown, shown[1:], strict=False))
        assert all(not a[2] or b[0] - a[0] == env.yellow_time or b[0] == env.sim_time for a, b in pairs)
        greens[tls] = [(a[1], a[0], b[0], b[3]) for a, b in pairs if not a[2]]
    return greens


@pytest.mark.parametrize(
    ("network", "delta_time", "early_change"),
    [("paper", 1, "ignore"), ("paper", 5, "defer"), pytest.param("2x2grid", 5, "ignore", marks=needs_grid)],
)
def test_min_and_max_green_hold_over_an_episode(network, delta_time, early_change):
    kwargs = {} if network == "paper" else _grid()
    env = TrafficSignalEnv(num_seconds=400, signal_control="max-pressure", delta_time=delta_time, min_green=7,
                           max_green=20, early_change=early_change, seed=1, **kwargs)  # fmt: skip
    try:
        greens = _greens(env)
    finally:
        env.close()
    durations = []
    for tls, shown in greens.items():
        for (g, t0, t1, pressures), (g_next, *_) in zip(shown, shown[1:], strict=False):
            assert 7 <= t1 - t0 <= 20, (tls, g, t0, t1)
            durations.append(t1 - t0)
            if t1 - t0 == 20:  # ended by max green: the other green of largest pressure follows
                assert g_next == best_phase(pressures, g, exclude_current=True), (tls, t1, pressures)
            elif early_change == "ignore":  # ended at a decision: the green of largest pressure, another one
                assert g_next == best_phase(pressures, g) != g, (tls, t1, pressures)
        assert shown[-1][2] - shown[-1][1] <= 20
    assert 20 in durations  # max green ended some greens (the W-E roads never run dry)
    assert min(durations) < 20  # and pressure others


def test_max_pressure_waits_less_than_fixed_time_on_the_paper_network():
    mp = run_program_episode("max-pressure", seed=0, num_seconds=500)
    fixed = run_program_episode("fixed-time", seed=0, num_seconds=500)
    assert mp["vehicles_departed"] == fixed["vehicles_departed"] == 481  # the same demand
    assert mp["vehicle_waiting_time_mean"] < 0.75 * fixed["vehicle_waiting_time_mean"]


def test_max_pressure_needs_no_actions():
    env = TrafficSignalEnv(NET_FILE, num_seconds=20, signal_control="max-pressure", seed=0)
    try:
        env.reset()
        _, _, _, _, infos = env.step({"J1": 0, "J2": 1})  # ignored, as fixed-time's, even for some agents only
        assert set(infos) == set(env.possible_agents) and infos["J1"]["time"] == 5
    finally:
        env.close()


def test_compare_has_a_max_pressure_row(tmp_path):
    run = tmp_path / "run"
    train = ["train", "traffic", "--iterations", "1", "--steps-per-iteration", "8", "--set", "n_test_weights=2",
             "--set", "validation_weights=0", "--set", "eval_workers=0", "--no-progress", "--seed", "0",
             "--env", "num_seconds=40", "--learner", "learning_starts=4", "--learner", "batch_size=4"]  # fmt: skip
    assert main([*train, "--out", str(run)]) == 0
    output = tmp_path / "compare.json"
    assert main(["compare", str(run), "--w", "1", "0", "--episodes", "1", "--workers", "0", "-o", str(output)]) == 0
    rows = json.loads(output.read_text())["rows"]
    assert [r["label"] for r in rows] == ["GPI w=[1,0]", "fixed-time", "actuated", "max-pressure"]
    row = rows[-1]
    env_kwargs = json.loads((run / "run.json").read_text())["env_kwargs"]  # the preset's: early_change="defer"
    expected = run_program_episode("max-pressure", seed=1000, **env_kwargs)
    assert row["episode_metrics"]["vehicle_waiting_time_mean"]["mean"] == pytest.approx(
        expected["vehicle_waiting_time_mean"]
    )
    assert len(row["traces"]["vehicle_wait_total"]["mean"]) == 8
    figure = tmp_path / "tradeoff.png"
    assert main(["plot", str(output), "--kind", "tradeoff", "-o", str(figure)]) == 0
    assert figure.read_bytes()[:4] == b"\x89PNG"

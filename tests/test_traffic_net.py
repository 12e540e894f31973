"""The three-intersection network: its build is reproducible and it has the layout of paper Sec. 5.2."""

from __future__ import annotations

import importlib.util
import math
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest
from sfgpi_envs.traffic import (
    NET_FILE,
    NETS_DIR,
    ROUTE_FILE,
    SignalProgram,
    read_network,
    write_actuated_programs,
)
from sfgpi_envs.traffic.scenario import trim_demand

BUILD_SCRIPT = NETS_DIR / "build.py"


def _strip(text: str) -> str:
    """Drop XML comments (netconvert's header with date and options) and blank lines."""
    import re

    text = re.sub(r"<!--.*?-->", "", text, flags=re.DOTALL)
    return "\n".join(line.rstrip() for line in text.splitlines() if line.strip())


@pytest.mark.skipif(
    importlib.util.find_spec("sumo") is None and shutil.which("netconvert") is None,
    reason="netconvert not installed (pip install eclipse-sumo)",
)
def test_build_reproduces_committed_network(tmp_path):
    out = tmp_path / "rebuilt.net.xml"
    proc = subprocess.run(
        [sys.executable, str(BUILD_SCRIPT), "--output", str(out)], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert _strip(out.read_text()) == _strip(NET_FILE.read_text()), (
        "the committed network differs from a fresh build; run `python envs/traffic/nets/build.py`"
    )


def test_network_layout():
    root = ET.parse(NET_FILE).getroot()
    nodes = {
        j.get("id"): (float(j.get("x")), float(j.get("y")))
        for j in root.iter("junction")
        if not j.get("id").startswith(":")
    }
    edges = {e.get("id"): e for e in root.iter("edge") if e.get("function") is None}
    # every link is one-way, joins nodes 150 m apart and has two vehicle lanes
    assert len(edges) == 10
    for e in edges.values():
        (x0, y0), (x1, y1) = nodes[e.get("from")], nodes[e.get("to")]
        assert math.hypot(x1 - x0, y1 - y0) == pytest.approx(150.0)
        lanes = list(e.iter("lane"))
        vehicle_lanes = [ln for ln in lanes if "pedestrian" not in ln.get("allow", "").split()]
        assert len(vehicle_lanes) == 2
        vertical = e.get("type") == "vertical"
        assert len(lanes) == (3 if vertical else 2)  # a sidewalk along the vertical links only
    # one crossing per intersection, over the W-E approach
    crossings = {e.get("id"): e.get("crossingEdges") for e in root.iter("edge") if e.get("function") == "crossing"}
    assert crossings == {":J1_c0": "HO1_J1", ":J2_c0": "HO2_J2", ":J3_c0": "HO3_J3"}


def test_layout_and_programs():
    layouts = read_network(NET_FILE)
    assert list(layouts) == ["J1", "J2", "J3"]
    for tid, lay in layouts.items():
        i = tid[1]
        assert len(lay.vehicle_lanes) == 4
        assert set(lay.vehicle_edges) == {f"HO{i}_J{i}", "VO1_J1" if i == "1" else f"J{int(i) - 1}_J{i}"}
        assert lay.waiting_areas == (f":J{i}_w0",)
        assert len(lay.sidewalk_edges) == 1
        assert lay.n_lanes == 6
        prog = SignalProgram.from_phases([s for s, _ in lay.phases], tid)
        assert len(prog.greens) == 2
        ns, we = prog.greens
        # N-S green: vertical vehicles and the crossing; W-E green: horizontal vehicles only
        assert ns == "GGrrG" and we == "rrGGr"
        assert prog.yellows == ("yyrrr", "rryyr")


def test_actuated_programs_follow_the_static_phases(tmp_path):
    path = write_actuated_programs(read_network(NET_FILE).values(), 10, 50, tmp_path / "a.add.xml")
    logics = list(ET.parse(path).getroot().iter("tlLogic"))
    assert {lg.get("id") for lg in logics} == {"J1", "J2", "J3"}
    for lg in logics:
        assert (lg.get("type"), lg.get("programID")) == ("actuated", "actuated")
        phases = [(p.get("state"), p.get("duration"), p.get("minDur"), p.get("maxDur")) for p in lg.iter("phase")]
        assert phases == [
            ("GGrrG", "30", "10", "50"),
            ("yyrrr", "3", None, None),
            ("rrGGr", "30", "10", "50"),
            ("rryyr", "3", None, None),
        ]


def test_demand():
    root = ET.parse(ROUTE_FILE).getroot()
    periods = {f.get("from"): float(f.get("period")) for f in root.iter("flow")}
    assert periods == {"HO1_J1": 3.3, "HO2_J2": 3.3, "HO3_J3": 3.3, "VO1_J1": 20.0}
    (pf,) = root.iter("personFlow")
    assert float(pf.get("period")) == 1.0
    walk = pf.find("walk")
    assert (walk.get("from"), walk.get("to")) == ("VO1_J1", "J3_VD1")


def test_trim_demand(tmp_path):
    out = trim_demand(ROUTE_FILE, 120, tmp_path)
    root = ET.parse(out).getroot()
    ends = [float(e.get("end")) for e in root.iter() if e.tag in ("flow", "personFlow")]
    assert ends and all(end == 120 for end in ends)
    assert trim_demand(out, 500, tmp_path) == out  # nothing to cut: the file itself


def test_programs_need_two_greens_and_take_more():
    with pytest.raises(ValueError, match="at least 2 green phases"):
        SignalProgram.from_phases(["GGrr", "yyrr", "rrrr"], "X")
    three = SignalProgram.from_phases(["GGrr", "yyrr", "rrGG", "rryy", "GrGr", "yryr"], "X")
    assert three.greens == ("GGrr", "rrGG", "GrGr") and three.yellows == ("yyrr", "rryy", "yryr")
    assert three.transition(0, 1) == "yyrr"  # the program's yellow
    assert three.transition(0, 2) == "Gyrr"  # derived: links green now and red next turn yellow
    derived = SignalProgram.from_phases(["GGrrG", "rrGGr"], "X")  # no yellow phases: derived
    assert derived.yellows == ("yyrry", "rryyr")

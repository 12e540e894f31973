"""Static description of the signalised intersections of a SUMO network, read from its ``.net.xml``.

Reading the file directly (instead of asking a running simulation) gives the agents, their incoming
lanes and hence the observation spaces before SUMO is started, and validates the file early: SUMO
1.28 crashes the whole process on a malformed network instead of reporting an error.

For every traffic light the layout lists

* the incoming vehicle lanes it controls (in link-index order),
* the pedestrian approach: the incoming sidewalks that lead to the *waiting areas* (walking areas in
  front of a signalised crossing) and those waiting areas,
* the capacities used to normalise densities and queues, and the phases of its static program.
"""

from __future__ import annotations

import functools
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

VEHICLE_SPACE_M = 7.5
"""Road length one queued vehicle occupies: SUMO's default passenger car (5 m) plus its minGap (2.5 m)."""

PEDESTRIAN_STRIPE_M = 0.65
"""Width of one stripe of SUMO's striping pedestrian model (``--pedestrian.striping.stripe-width``)."""

PEDESTRIAN_SPACE_M = 0.465
"""Length one standing pedestrian occupies in a stripe: default pedestrian length (0.215 m) + minGap (0.25 m)."""

DEFAULT_LANE_WIDTH_M = 3.2
"""SUMO's default lane width, used when a lane has no ``width`` attribute."""


@dataclass(frozen=True)
class IntersectionLayout:
    """Incoming lanes and signal program of one traffic light.

    :param tls_id: traffic-light id (also the agent id).
    :param vehicle_lanes: controlled incoming vehicle lanes, in link-index order, without repetition.
    :param vehicle_edges: the edges of ``vehicle_lanes``, in order of first appearance.
    :param sidewalk_edges: edges whose sidewalks lead into a waiting area of this intersection.
    :param waiting_areas: walking areas in front of a signalised crossing of this intersection.
    :param vehicle_capacity: capacity (vehicles) of each lane of ``vehicle_lanes``.
    :param pedestrian_capacity: capacity (persons) of each edge of ``sidewalk_edges + waiting_areas``
        (only the pedestrian lanes of an edge count).
    :param phases: ``(state, duration)`` of each phase of the static program in the file.
    """

    tls_id: str
    vehicle_lanes: tuple[str, ...]
    vehicle_edges: tuple[str, ...]
    sidewalk_edges: tuple[str, ...]
    waiting_areas: tuple[str, ...]
    vehicle_capacity: tuple[float, ...]
    pedestrian_capacity: tuple[float, ...]
    phases: tuple[tuple[str, float], ...]

    @property
    def pedestrian_edges(self) -> tuple[str, ...]:
        """Edges of the pedestrian approach: incoming sidewalks, then waiting areas."""
        return self.sidewalk_edges + self.waiting_areas

    @property
    def n_lanes(self) -> int:
        """Number of incoming "lanes" in the observation (vehicle lanes + pedestrian approach edges)."""
        return len(self.vehicle_lanes) + len(self.sidewalk_edges) + len(self.waiting_areas)


def vehicle_lane_capacity(length: float) -> float:
    """Number of vehicles a queue on a lane of ``length`` metres holds (at least 1).

    :param length: lane length [m].
    :return: capacity.
    """
    return max(1.0, length / VEHICLE_SPACE_M)


def pedestrian_area_capacity(length: float, width: float) -> float:
    """Number of standing pedestrians a sidewalk or walking area of the given size holds (at least 1).

    :param length: length [m] as reported by SUMO.
    :param width: width [m].
    :return: capacity: stripes across the width times pedestrians along the length.
    """
    stripes = max(1, math.floor(width / PEDESTRIAN_STRIPE_M))
    return max(1.0, stripes * length / PEDESTRIAN_SPACE_M)


def read_network(path: str | os.PathLike[str]) -> dict[str, IntersectionLayout]:
    """Read the signalised intersections of a network file.

    Results are cached per file path, size and modification time.

    :param path: the ``.net.xml`` file.
    :return: one layout per traffic light, in file order.
    :raises FileNotFoundError: if the file does not exist.
    :raises ValueError: if it is not well-formed XML, not a SUMO network or has no traffic light
        (the message names the file and the problem).
    """
    p = Path(path).resolve()
    if not p.is_file():
        raise FileNotFoundError(f"network file {p} does not exist")
    st = p.stat()
    return dict(_read_network_cached(str(p), st.st_mtime_ns, st.st_size))


@functools.lru_cache(maxsize=16)
def _read_network_cached(path: str, mtime_ns: int, size: int) -> tuple[tuple[str, IntersectionLayout], ...]:
    del mtime_ns, size  # cache keys only
    root = _parse_net(path)
    edges = _read_edges(root, path)
    programs = _read_programs(root, path)
    links, into = _read_connections(root, programs)
    return tuple((tid, _layout(tid, program, links[tid], into, edges, path)) for tid, program in programs.items())


@dataclass(frozen=True)
class _Edges:
    """What the layouts need of a network's edges and lanes."""

    function: dict[str, str]
    """``function`` attribute of every edge (``"normal"`` when absent)."""
    lane_size: dict[str, tuple[float, float]]
    """``(length, width)`` of every lane."""
    pedestrian_lanes: dict[str, list[str]]
    """The lanes of an edge that pedestrians use (all lanes of walking areas and crossings)."""


def _parse_net(path: str) -> ET.Element:
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"network file {path} is not valid XML: {exc}") from exc
    if root.tag != "net":
        raise ValueError(f"network file {path} is not a SUMO network: root element <{root.tag}>, expected <net>")
    return root


def _read_edges(root: ET.Element, path: str) -> _Edges:
    edges = _Edges({}, {}, {})
    for edge in root.iter("edge"):
        eid = edge.get("id", "")
        edges.function[eid] = edge.get("function", "normal")
        for lane in edge.iter("lane"):
            lid = lane.get("id", "")
            edges.lane_size[lid] = (float(lane.get("length", "0")), float(lane.get("width", DEFAULT_LANE_WIDTH_M)))
            if "pedestrian" in lane.get("allow", "").split() or edges.function[eid] in ("walkingarea", "crossing"):
                edges.pedestrian_lanes.setdefault(eid, []).append(lid)
    if not edges.function:
        raise ValueError(f"network file {path} contains no edges")
    return edges


def _read_programs(root: ET.Element, path: str) -> dict[str, tuple[tuple[str, float], ...]]:
    programs: dict[str, tuple[tuple[str, float], ...]] = {}
    for logic in root.iter("tlLogic"):
        tid = logic.get("id", "")
        if tid not in programs:  # first (default) program of each traffic light
            programs[tid] = tuple((ph.get("state", ""), float(ph.get("duration", "0"))) for ph in logic.iter("phase"))
    if not programs:
        raise ValueError(f"network file {path} has no traffic lights (<tlLogic>)")
    return programs


def _read_connections(
    root: ET.Element, programs: dict[str, tuple[tuple[str, float], ...]]
) -> tuple[dict[str, list[tuple[int, str, str]]], dict[str, list[str]]]:
    """``(link index, from edge, from lane)`` of each traffic light's links, and the edges leading into each edge."""
    links: dict[str, list[tuple[int, str, str]]] = {tid: [] for tid in programs}
    into: dict[str, list[str]] = {}
    for con in root.iter("connection"):
        src, dst = con.get("from", ""), con.get("to", "")
        tid = con.get("tl")
        if tid is not None and tid in links:
            links[tid].append((int(con.get("linkIndex", "-1")), src, f"{src}_{con.get('fromLane', '0')}"))
        into.setdefault(dst, []).append(src)
    return links, into


def _layout(
    tid: str,
    program: tuple[tuple[str, float], ...],
    links: list[tuple[int, str, str]],
    into: dict[str, list[str]],
    edges: _Edges,
    path: str,
) -> IntersectionLayout:
    veh_lanes: list[str] = []
    areas: list[str] = []
    for _, src, lane in sorted(links):
        if edges.function.get(src) == "normal":
            if lane not in veh_lanes:
                veh_lanes.append(lane)
        elif edges.function.get(src) == "walkingarea" and src not in areas:
            areas.append(src)
    missing = [lane for lane in veh_lanes if lane not in edges.lane_size]
    if missing:
        raise ValueError(f"network file {path}: traffic light {tid} controls unknown lanes {missing}")
    sidewalks = list(dict.fromkeys(s for a in areas for s in into.get(a, ()) if edges.function.get(s) == "normal"))
    pedestrian_capacity = tuple(
        sum(pedestrian_area_capacity(*edges.lane_size[lid]) for lid in edges.pedestrian_lanes.get(e, [])) or 1.0
        for e in sidewalks + areas
    )
    return IntersectionLayout(
        tls_id=tid,
        vehicle_lanes=tuple(veh_lanes),
        vehicle_edges=tuple(dict.fromkeys(lane.rsplit("_", 1)[0] for lane in veh_lanes)),
        sidewalk_edges=tuple(sidewalks),
        waiting_areas=tuple(areas),
        vehicle_capacity=tuple(vehicle_lane_capacity(edges.lane_size[lane][0]) for lane in veh_lanes),
        pedestrian_capacity=pedestrian_capacity,
        phases=program,
    )

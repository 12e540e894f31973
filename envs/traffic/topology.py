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
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"network file {path} is not valid XML: {exc}") from exc
    if root.tag != "net":
        raise ValueError(f"network file {path} is not a SUMO network: root element <{root.tag}>, expected <net>")

    function: dict[str, str] = {}
    lane_size: dict[str, tuple[float, float]] = {}
    ped_lanes: dict[str, list[str]] = {}
    for edge in root.iter("edge"):
        eid = edge.get("id", "")
        function[eid] = edge.get("function", "normal")
        for lane in edge.iter("lane"):
            lid = lane.get("id", "")
            lane_size[lid] = (float(lane.get("length", "0")), float(lane.get("width", DEFAULT_LANE_WIDTH_M)))
            allow = lane.get("allow", "").split()
            if "pedestrian" in allow or function[eid] in ("walkingarea", "crossing"):
                ped_lanes.setdefault(eid, []).append(lid)
    if not function:
        raise ValueError(f"network file {path} contains no edges")

    programs: dict[str, tuple[tuple[str, float], ...]] = {}
    for logic in root.iter("tlLogic"):
        tid = logic.get("id", "")
        if tid not in programs:  # first (default) program of each traffic light
            programs[tid] = tuple((ph.get("state", ""), float(ph.get("duration", "0"))) for ph in logic.iter("phase"))
    if not programs:
        raise ValueError(f"network file {path} has no traffic lights (<tlLogic>)")

    links: dict[str, list[tuple[int, str, str]]] = {tid: [] for tid in programs}
    into: dict[str, list[str]] = {}
    for con in root.iter("connection"):
        src, dst = con.get("from", ""), con.get("to", "")
        lane = f"{src}_{con.get('fromLane', '0')}"
        tid = con.get("tl")
        if tid is not None and tid in links:
            links[tid].append((int(con.get("linkIndex", "-1")), src, lane))
        into.setdefault(dst, []).append(src)

    layouts = []
    for tid, program in programs.items():
        veh_lanes: list[str] = []
        areas: list[str] = []
        for _, src, lane in sorted(links[tid]):
            if function.get(src) == "normal":
                if lane not in veh_lanes:
                    veh_lanes.append(lane)
            elif function.get(src) == "walkingarea" and src not in areas:
                areas.append(src)
        veh_edges = list(dict.fromkeys(lane.rsplit("_", 1)[0] for lane in veh_lanes))
        sidewalks = list(dict.fromkeys(s for a in areas for s in into.get(a, ()) if function.get(s) == "normal"))
        missing = [lane for lane in veh_lanes if lane not in lane_size]
        if missing:
            raise ValueError(f"network file {path}: traffic light {tid} controls unknown lanes {missing}")
        ped_cap = []
        for e in sidewalks + areas:
            lanes = ped_lanes.get(e, [])
            ped_cap.append(sum(pedestrian_area_capacity(*lane_size[lid]) for lid in lanes) or 1.0)
        layouts.append(
            (
                tid,
                IntersectionLayout(
                    tls_id=tid,
                    vehicle_lanes=tuple(veh_lanes),
                    vehicle_edges=tuple(veh_edges),
                    sidewalk_edges=tuple(sidewalks),
                    waiting_areas=tuple(areas),
                    vehicle_capacity=tuple(vehicle_lane_capacity(lane_size[lane][0]) for lane in veh_lanes),
                    pedestrian_capacity=tuple(ped_cap),
                    phases=program,
                ),
            )
        )
    return tuple(layouts)

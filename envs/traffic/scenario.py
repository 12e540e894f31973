"""Files of the three-intersection pedestrian scenario and preparation of the per-episode demand.

The scenario (paper Sec. 5.2) lives in ``envs/traffic/nets/``: the plain XML sources, the built
network :data:`NET_FILE` and the demand :data:`ROUTE_FILE`.

:func:`write_actuated_programs` writes SUMO actuated programs for the lights of any network (the "actuated"
baseline).

SUMO expands a ``personFlow`` into individual persons when it loads the route file, so a flow that
lasts a simulated day makes every (re)load slow. :func:`trim_demand` writes a copy of a route file
whose flows end with the episode.
"""

from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from pathlib import Path

from .signals import is_green
from .topology import IntersectionLayout

NETS_DIR = Path(__file__).resolve().parent / "nets"
"""Folder holding the scenario's sources and built network."""

NET_FILE = NETS_DIR / "three_junctions.net.xml"
"""Built network (three signalised intersections, one pedestrian crossing each)."""

ROUTE_FILE = NETS_DIR / "three_junctions.rou.xml"
"""Demand: vehicle flows HO1-HO3 (every 3.3 s), VO1 (every 20 s), one pedestrian per second VO1 -> VD1."""

_FLOW_TAGS = frozenset({"flow", "personFlow", "containerFlow"})
_DEMAND_TAGS = frozenset({"vehicle", "trip", "person", "container", *_FLOW_TAGS})


def warn_if_no_demand(route_file: str | os.PathLike[str]) -> None:
    """Warn where a route file holds no vehicle, trip, person or flow (e.g. a network file passed as routes): the
    episodes would run with every reward 0. Files that are not XML are left to :func:`trim_demand` to refuse."""
    try:
        root = ET.parse(route_file).getroot()
    except (ET.ParseError, OSError):
        return
    if not any(element.tag in _DEMAND_TAGS for element in root.iter()):
        kind = " (its root is <net>: a network file?)" if root.tag == "net" else ""
        warnings.warn(
            f"route file {route_file} holds no vehicle, trip, person or flow{kind}: no traffic, every reward is 0",
            stacklevel=3,
        )


def trim_demand(route_file: str | os.PathLike[str], end: float, directory: str | os.PathLike[str]) -> Path:
    """Write a copy of ``route_file`` whose flows stop at ``end``.

    Only the ``end`` attribute of ``flow``, ``personFlow`` and ``containerFlow`` elements is lowered
    (to ``end``) where it is larger, and flows that begin at ``end`` or later are left out; everything departing
    before ``end`` is unchanged.

    :param route_file: SUMO route file.
    :param end: simulated time [s] after which no flow inserts anything.
    :param directory: folder receiving the copy.
    :return: path of the copy, or of ``route_file`` itself when no flow outlasts ``end``.
    :raises ValueError: if the route file is not well-formed XML (the message names the file).
    """
    route_file = Path(route_file)
    try:
        tree = ET.parse(route_file)
    except ET.ParseError as exc:
        raise ValueError(f"route file {route_file} is not valid XML: {exc}") from exc
    changed = False
    for parent in list(tree.getroot().iter()):
        for elem in list(parent):
            if elem.tag not in _FLOW_TAGS or "end" not in elem.attrib:
                continue
            try:
                flow_begin, flow_end = float(elem.get("begin", "0")), float(elem.attrib["end"])
            except ValueError:
                continue
            if flow_begin >= end:  # inserts nothing before the end; SUMO refuses a flow ending before it begins
                parent.remove(elem)
                changed = True
            elif flow_end > end:
                elem.set("end", f"{end:g}")
                changed = True
    if not changed:
        return route_file
    out = Path(directory) / f"{route_file.stem}.until{end:g}{''.join(route_file.suffixes[-1:])}"
    tree.write(out, encoding="UTF-8", xml_declaration=True)
    return out


def write_actuated_programs(
    layouts: Iterable[IntersectionLayout], min_green: int, max_green: int, path: str | os.PathLike[str]
) -> Path:
    """Write an additional file with an actuated program (``programID="actuated"``) for each traffic light.

    Each program has the phases of the light's static program; its green phases are extended by SUMO's gap-based
    actuation between ``min_green`` and ``max_green`` seconds. Loaded as an additional file, the program becomes
    the active one.

    :param layouts: the lights (:func:`~.topology.read_network`).
    :param min_green: minimum green [s] (``minDur``).
    :param max_green: maximum green [s] (``maxDur``).
    :param path: the file to write.
    :return: ``path``.
    """
    root = ET.Element("additional")
    for layout in layouts:
        logic = ET.SubElement(root, "tlLogic", id=layout.tls_id, type="actuated", programID="actuated", offset="0")
        for state, duration in layout.phases:
            phase = ET.SubElement(logic, "phase", duration=f"{duration:g}", state=state)
            if is_green(state):
                phase.set("minDur", str(min_green))
                phase.set("maxDur", str(max_green))
    ET.ElementTree(root).write(path, encoding="UTF-8", xml_declaration=True)
    return Path(path)

"""Files of the three-intersection pedestrian scenario and preparation of the per-episode demand.

The scenario (paper Sec. 5.2) lives in ``envs/traffic/nets/``: the plain XML sources, the built
network :data:`NET_FILE`, the demand :data:`ROUTE_FILE` and the actuated signal programs
:data:`ACTUATED_FILE` (an additional file for the "actuated" baseline).

SUMO expands a ``personFlow`` into individual persons when it loads the route file, so a flow that
lasts a simulated day makes every (re)load slow. :func:`trim_demand` writes a copy of a route file
whose flows end with the episode.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

NETS_DIR = Path(__file__).resolve().parent / "nets"
"""Folder holding the scenario's sources and built network."""

NET_FILE = NETS_DIR / "three_junctions.net.xml"
"""Built network (three signalised intersections, one pedestrian crossing each)."""

ROUTE_FILE = NETS_DIR / "three_junctions.rou.xml"
"""Demand: vehicle flows HO1-HO3 (every 3.3 s), VO1 (every 20 s), one pedestrian per second VO1 -> VD1."""

ACTUATED_FILE = NETS_DIR / "actuated.add.xml"
"""Actuated signal programs (programID ``"actuated"``), loaded as an additional file."""

_FLOW_TAGS = frozenset({"flow", "personFlow", "containerFlow"})


def trim_demand(route_file: str | os.PathLike[str], end: float, directory: str | os.PathLike[str]) -> Path:
    """Write a copy of ``route_file`` whose flows stop at ``end``.

    Only the ``end`` attribute of ``flow``, ``personFlow`` and ``containerFlow`` elements is lowered
    (to ``end``) where it is larger; everything departing before ``end`` is unchanged.

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
    for elem in tree.getroot().iter():
        if elem.tag in _FLOW_TAGS and "end" in elem.attrib:
            try:
                flow_end = float(elem.attrib["end"])
            except ValueError:
                continue
            if flow_end > end:
                elem.set("end", f"{end:g}")
                changed = True
    if not changed:
        return route_file
    out = Path(directory) / f"{route_file.stem}.until{end:g}{''.join(route_file.suffixes[-1:])}"
    tree.write(out, encoding="UTF-8", xml_declaration=True)
    return out

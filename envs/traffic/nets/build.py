"""Build the SUMO network of the three-intersection pedestrian scenario from its plain XML sources.

Run ``python envs/traffic/nets/build.py`` (or import :func:`build_network`) to regenerate
``three_junctions.net.xml`` next to this script. ``netconvert`` is taken from the installed
``eclipse-sumo`` package (``sumo.SUMO_HOME/bin``) and otherwise from ``PATH``; no environment
variables need to be set.

The sources are:

* ``three_junctions.nod.xml``  -- nodes (origins, destinations and the three signalised junctions),
* ``three_junctions.typ.xml``  -- edge types (two vehicle lanes; the N-S road adds a sidewalk),
* ``three_junctions.edg.xml``  -- edges (one-way, 150 m),
* ``three_junctions.con.xml``  -- straight-only connections and one crossing per junction,
* ``three_junctions.tll.xml``  -- the static two-green-phase signal programs ("fixed-time").

The generated file starts with an XML comment that records the date and the netconvert options;
:func:`strip_header` removes it so that two builds can be compared.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

NETS_DIR = Path(__file__).resolve().parent
"""Folder holding the network sources and the built network."""

PREFIX = "three_junctions"
"""Common file-name prefix of the scenario's sources."""

NET_FILE = NETS_DIR / f"{PREFIX}.net.xml"
"""The committed, built network."""

NETCONVERT_OPTIONS: tuple[str, ...] = (
    "--no-turnarounds",
    "true",
    "--offset.disable-normalization",
    "true",
    "--no-warnings",
    "true",
)
"""Options passed to netconvert in addition to the input/output files."""

_HEADER_RE = re.compile(r"<!--.*?-->", re.DOTALL)


def find_netconvert() -> str:
    """Locate the ``netconvert`` executable.

    :return: path of the executable, from the ``eclipse-sumo`` package if installed, else from ``PATH``.
    :raises FileNotFoundError: if neither provides it (the message says how to install SUMO).
    """
    try:
        import sumo  # type: ignore[import-not-found]

        candidate = Path(sumo.SUMO_HOME) / "bin" / "netconvert"
        for path in (candidate, candidate.with_suffix(".exe")):
            if path.is_file() and os.access(path, os.X_OK):
                return str(path)
    except ImportError:
        pass
    found = shutil.which("netconvert")
    if found is None:
        raise FileNotFoundError("netconvert not found: install SUMO with `pip install eclipse-sumo libsumo`")
    return found


def build_network(output: str | os.PathLike[str] | None = None, *, netconvert: str | None = None) -> Path:
    """Run netconvert on the plain XML sources.

    :param output: path of the ``.net.xml`` to write; defaults to :data:`NET_FILE` (the committed network).
    :param netconvert: netconvert executable; found with :func:`find_netconvert` when omitted.
    :return: the path of the written network.
    :raises RuntimeError: if netconvert fails (its output is included in the message).
    """
    out = Path(output).resolve() if output is not None else NET_FILE
    cmd = [
        netconvert or find_netconvert(),
        "--node-files",
        f"{PREFIX}.nod.xml",
        "--type-files",
        f"{PREFIX}.typ.xml",
        "--edge-files",
        f"{PREFIX}.edg.xml",
        "--connection-files",
        f"{PREFIX}.con.xml",
        "--tllogic-files",
        f"{PREFIX}.tll.xml",
        *NETCONVERT_OPTIONS,
        "--output-file",
        str(out),
    ]
    # Run inside the sources folder so that the recorded input paths are relative.
    proc = subprocess.run(cmd, cwd=NETS_DIR, capture_output=True, text=True, check=False)
    if proc.returncode != 0 or not out.is_file():
        raise RuntimeError(f"netconvert failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return out


def strip_header(text: str) -> str:
    """Remove the comments (generation date, options) from a network file's text.

    :param text: content of a ``.net.xml`` file.
    :return: the content without XML comments and without blank lines.
    """
    text = _HEADER_RE.sub("", text)
    return "\n".join(line.rstrip() for line in text.splitlines() if line.strip())


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point.

    :param argv: arguments (default: ``sys.argv[1:]``).
    :return: process exit code.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", "-o", default=None, help=f"output .net.xml (default: {NET_FILE.name})")
    args = parser.parse_args(argv)
    path = build_network(args.output)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Start, reload and close one SUMO simulation, in-process through libsumo or over a TraCI socket.

* ``libsumo`` (default, fastest) runs SUMO inside this Python process. It holds a single simulation
  per process, and starting a second one silently replaces the first. :class:`SumoSimulation`
  therefore keeps a module-level registry: while one libsumo simulation is live, starting another
  raises :class:`RuntimeError` that names the fixes (close the first, or use ``backend="traci"``).
* ``traci`` starts a ``sumo`` (or ``sumo-gui``) process and talks to it over a socket under a unique
  connection label, so any number of them can run in one process.

The object exposes ``api``: the ``libsumo`` module or the ``traci`` connection, which offer the same
domains (``api.vehicle``, ``api.trafficlight``, ...) and ``api.simulationStep()``.

SUMO is looked up in the ``eclipse-sumo`` Python package first (``sumo.SUMO_HOME``), then on
``PATH``; no environment variable has to be set.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
import shutil
import socket
import subprocess
import tempfile
import weakref
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

INSTALL_HINT = "pip install eclipse-sumo libsumo"
"""How to install SUMO and libsumo."""

BACKENDS = ("libsumo", "traci")
"""Supported backends."""


class SumoNotFoundError(ImportError):
    """SUMO, libsumo or TraCI is not installed."""


class SumoLoadError(RuntimeError):
    """SUMO refused to load a simulation (broken network, routes or options)."""


def find_sumo_binary(gui: bool = False) -> str:
    """Locate the ``sumo`` (or ``sumo-gui``) executable.

    :param gui: look for ``sumo-gui`` instead of ``sumo``.
    :return: path of the executable.
    :raises SumoNotFoundError: if it is neither in the ``eclipse-sumo`` package nor on ``PATH``.
    """
    name = "sumo-gui" if gui else "sumo"
    try:
        import sumo  # type: ignore[import-not-found]

        base = Path(sumo.SUMO_HOME) / "bin" / name
        for candidate in (base, base.with_suffix(".exe")):
            if candidate.is_file() and os.access(candidate, os.X_OK):
                return str(candidate)
    except ImportError:
        pass
    found = shutil.which(name)
    if found is None:
        raise SumoNotFoundError(f"SUMO executable {name!r} not found. Install SUMO with `{INSTALL_HINT}`.")
    return found


def import_libsumo() -> ModuleType:
    """Import ``libsumo``.

    :return: the module.
    :raises SumoNotFoundError: if it is not installed (the message says how to install it).
    """
    try:
        import libsumo  # type: ignore[import-not-found]
    except ImportError as exc:
        raise SumoNotFoundError(
            f"libsumo is not available ({exc}). Install it with `{INSTALL_HINT}`, or use backend='traci'."
        ) from exc
    return libsumo


def import_traci() -> ModuleType:
    """Import ``traci``.

    :return: the module.
    :raises SumoNotFoundError: if it is not installed (the message says how to install it).
    """
    try:
        import traci  # type: ignore[import-not-found]
    except ImportError as exc:
        raise SumoNotFoundError(
            f"traci is not available ({exc}). Install it with `pip install traci eclipse-sumo`."
        ) from exc
    return traci


# --- the one-libsumo-simulation-per-process registry ------------------------------------------------
_libsumo_owner: weakref.ref[SumoSimulation] | None = None
_libsumo_token: object | None = None
_labels = itertools.count()


def _release_libsumo(token: object) -> None:
    """Close the libsumo simulation if ``token`` still owns it (also run when the owner is collected)."""
    global _libsumo_owner, _libsumo_token
    if _libsumo_token is not token:
        return
    _libsumo_owner, _libsumo_token = None, None
    try:
        import libsumo  # type: ignore[import-not-found]

        if libsumo.simulation.isLoaded():
            libsumo.close()
    except Exception:  # noqa: BLE001 - best effort during cleanup
        pass


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


class SumoSimulation:
    """One SUMO simulation that can be (re)started with new arguments.

    :param backend: ``"libsumo"`` (in-process) or ``"traci"`` (separate process).
    :param gui: run ``sumo-gui`` (requires ``backend="traci"``).
    :raises ValueError: for an unknown backend or ``gui`` with libsumo.
    :raises SumoNotFoundError: if the backend or the SUMO executable is not installed.
    """

    def __init__(self, backend: str = "libsumo", gui: bool = False) -> None:
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if gui and backend != "traci":
            raise ValueError("gui=True needs backend='traci' (libsumo cannot drive sumo-gui)")
        self.backend = backend
        self.gui = gui
        self.api: Any = None
        """``libsumo`` module or ``traci`` connection while running, else ``None``."""
        self._token: object | None = None
        self._finalizer: weakref.finalize | None = None
        self._label: str | None = None
        self._stderr: Any = None
        self._proc: subprocess.Popen[bytes] | None = None
        if backend == "libsumo":
            self._module = import_libsumo()
            self.errors: tuple[type[BaseException], ...] = (
                self._module.TraCIException,
                self._module.FatalTraCIError,
            )
        else:
            self._module = import_traci()
            # a dead SUMO process can also surface as a socket error
            self.errors = (self._module.exceptions.TraCIException, self._module.exceptions.FatalTraCIError, OSError)
        self.binary = find_sumo_binary(gui)

    @property
    def running(self) -> bool:
        """Whether a simulation is loaded."""
        return self.api is not None

    @property
    def pid(self) -> int | None:
        """Process id of the SUMO process (TraCI backend while running), else ``None``."""
        return self._proc.pid if self._proc is not None and self.running else None

    @property
    def label(self) -> str | None:
        """TraCI connection label (``None`` with libsumo)."""
        return self._label

    def start(self, args: Sequence[str]) -> None:
        """Start a simulation, or reload the running one with new arguments (fast: same process).

        :param args: SUMO command-line arguments, without the executable.
        :raises RuntimeError: if another libsumo simulation is live in this process.
        :raises SumoLoadError: if SUMO refuses the arguments (message includes SUMO's complaint).
        """
        args = list(args)
        if self.running:
            self._reload(args)
        elif self.backend == "libsumo":
            self._start_libsumo(args)
        else:
            self._start_traci(args)

    def close(self) -> None:
        """Stop the simulation (no-op if not running). Safe to call several times."""
        api, self.api = self.api, None
        if self.backend == "libsumo":
            if self._token is not None:
                _release_libsumo(self._token)
                self._token = None
            if self._finalizer is not None:
                self._finalizer.detach()
                self._finalizer = None
        elif api is not None:
            try:
                api.close()
            except Exception:  # noqa: BLE001 - the process may already be gone
                pass
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            self._proc = None
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None
        self._label = None

    # --- libsumo --------------------------------------------------------------------------------
    def _start_libsumo(self, args: list[str]) -> None:
        global _libsumo_owner, _libsumo_token
        libsumo = self._module
        owner = _libsumo_owner() if _libsumo_owner is not None else None
        if owner is not None and owner is not self:
            raise RuntimeError(
                "another libsumo simulation is already running in this process (libsumo holds one simulation "
                "per process, and a second one would silently take over the first). Close the first "
                "environment with env.close(), or create this one with backend='traci'."
            )
        if libsumo.simulation.isLoaded():
            raise RuntimeError(
                "a libsumo simulation started outside this environment is running in this process. "
                "Close it with libsumo.close(), or create this environment with backend='traci'."
            )
        token = object()
        _libsumo_owner, _libsumo_token = weakref.ref(self), token
        try:
            libsumo.start([self.binary, *args])
        except self.errors as exc:
            _release_libsumo(token)
            raise SumoLoadError(self._explain(args, exc)) from exc
        self._token = token
        self._finalizer = weakref.finalize(self, _release_libsumo, token)
        self.api = libsumo

    # --- traci ------------------------------------------------------------------------------------
    def _start_traci(self, args: list[str]) -> None:
        traci = self._module
        label = f"sfgpi_traffic_{os.getpid()}_{next(_labels)}"
        port = _free_port()
        cmd = [self.binary, *args, "--remote-port", str(port)]
        if self.gui:
            cmd += ["--start", "--quit-on-end"]
        self._stderr = tempfile.TemporaryFile(mode="w+")
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=self._stderr)
        try:
            # traci.init waits 1 s between connection attempts; poll faster and keep its chatter quiet.
            with contextlib.redirect_stdout(io.StringIO()):
                conn = traci.main.connect(port, 600, "localhost", proc, 0.05, label=label)
        except self.errors as exc:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
            raise SumoLoadError(self._explain(args, exc, self._read_stderr())) from exc
        self._label = label
        self._proc = proc
        self.api = conn

    def _read_stderr(self) -> str:
        if self._stderr is None:
            return ""
        self._stderr.flush()
        self._stderr.seek(0)
        text = self._stderr.read()
        self._stderr.seek(0, os.SEEK_END)
        return text

    # --- both -------------------------------------------------------------------------------------
    def _reload(self, args: list[str]) -> None:
        try:
            self.api.load(args)
        except self.errors as exc:
            complaint = self._read_stderr() if self.backend == "traci" else ""
            self.close()
            raise SumoLoadError(self._explain(args, exc, complaint)) from exc

    def _explain(self, args: list[str], exc: BaseException, complaint: str = "") -> str:
        """Build an error message with SUMO's own complaint (re-running the sumo binary if needed)."""
        if not complaint.strip():
            complaint = _sumo_complaint(find_sumo_binary(False), args)
        files = [
            args[i + 1]
            for i, a in enumerate(args[:-1])
            if a in ("-n", "--net-file", "-r", "--route-files", "-a", "--additional-files")
        ]
        detail = complaint.strip() or str(exc)
        return f"SUMO could not load the simulation (files: {', '.join(files)}): {detail}"


def _sumo_complaint(binary: str, args: list[str]) -> str:
    """Run the ``sumo`` executable on ``args`` and return the errors it prints (empty if it loads fine)."""
    cmd = [binary, *args]
    if "--end" not in args:
        cmd += ["--end", "0"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    out = (proc.stderr + "\n" + proc.stdout).splitlines()
    start = next((i for i, ln in enumerate(out) if ln.startswith("Error")), len(out))
    lines = [ln for ln in out[start:] if ln.strip() and not ln.startswith(("Warning", "Quitting"))]
    if proc.returncode < 0:
        lines.append(f"(sumo crashed with signal {-proc.returncode})")
    return "\n".join(lines)

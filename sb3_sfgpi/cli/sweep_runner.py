"""Sweeps: many ``sb3-sfgpi train`` runs as Ray tasks, each writing its own run directory, resumable.

A sweep is a list of :class:`RunSpec` (domain, algorithm, seed, weights, further ``train`` options). Every run is
one Ray task that runs ``sb3-sfgpi train`` in its worker process into ``out/<run name>``: its output goes to
``train.log`` there, and ``sweep.json`` there records the run's spec, its attempts (process, host, folder, start)
and, once it ended, that it finished. A task whose worker dies (killed, out of memory, a node lost) is retried by
Ray and continues from the run's last checkpoint (``train --resume``), so its results are those of an uninterrupted run;
a sweep run again skips the runs that finished with the same spec. Ray is started locally with the machine's
cores unless an address is given (or ``RAY_ADDRESS`` is set): then the runs go to that cluster, whose nodes must
have this package installed and either all see ``out`` (a shared filesystem) or, with ``shared_filesystem=False``,
send their run directories home (:mod:`sb3_sfgpi.cli.run_shipping`).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import signal
import socket
import threading
import unicodedata
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from sb3_sfgpi.cli.ray_cluster import joined_ray
from sb3_sfgpi.cli.run_shipping import node_run_directory, start_store
from sb3_sfgpi.common.serialization import atomic_write_json
from sb3_sfgpi.common.weights import format_weights
from sb3_sfgpi.run_directory import RunDirectory

#: Seconds between two looks at the Ctrl-C flag while the runs go on.
POLL_SECONDS = 1.0

ALGORITHMS = ("ma-sfols", "random", "fixed")
#: The file of a run directory where the sweep records the run's spec, attempts and end.
SWEEP_FILE = "sweep.json"


@dataclass(frozen=True)
class RunSpec:
    """
    One run of a sweep: ``sb3-sfgpi train DOMAIN --algo ALGO --seed SEED [--w W] OPTIONS``.

    :param domain: an installed domain (``four-room``, ``traffic``, ...)
    :param algo: ``ma-sfols``, ``random`` or ``fixed`` (then ``w`` is required)
    :param seed: the run's seed
    :param w: the weights of ``fixed``
    :param options: further ``train`` options, e.g. ``("--iterations", "3", "--env", "num_seconds=200")``
    :param name: the run directory's name (default: domain, algorithm, weights and seed)
    :raises ValueError: an unknown algorithm, a negative seed, weights missing or not wanted
    """

    domain: str
    algo: str = "ma-sfols"
    seed: int = 0
    w: tuple[float, ...] | None = None
    options: tuple[str, ...] = ()
    name: str | None = None

    def __post_init__(self) -> None:
        if self.algo not in ALGORITHMS:
            raise ValueError(f"algo must be one of {', '.join(ALGORITHMS)}, got {self.algo!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if (self.algo == "fixed") != (self.w is not None):
            raise ValueError(f"weights w are for algo 'fixed' and it needs them (run {self.run_name!r})")
        check_options(self.options)
        object.__setattr__(self, "w", None if self.w is None else tuple(float(x) for x in self.w))
        object.__setattr__(self, "options", tuple(self.options))
        check_run_name(self.run_name)

    @property
    def run_name(self) -> str:
        """The name of the run's directory in the sweep's output."""
        if self.name:
            return self.name
        weights = "" if self.w is None else "-w" + format_weights(self.w).strip("[]").replace(",", "-")
        return f"{self.domain}-{self.algo}{weights}-s{self.seed}"

    def train_argv(self, run_dir: Path, resume: bool) -> list[str]:
        """The ``sb3-sfgpi`` arguments that train (or continue) this run in ``run_dir``."""
        weights = [] if self.w is None else ["--w", *map(str, self.w)]
        base = ["train", self.domain, "--algo", self.algo, "--seed", str(self.seed), *weights, "--out", str(run_dir)]
        return [*base, "--no-progress", *(["--resume"] if resume else []), *self.options]

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "w": None if self.w is None else list(self.w), "options": list(self.options)}


#: The ``train`` options a sweep sets itself (a run's options may not set them, nor abbreviate them).
RESERVED_OPTIONS = ("--algo", "--seed", "--w", "--out", "--resume")


def check_options(options: Any) -> None:
    """
    Refuse a run's ``train`` options unless they are a list of strings that set none of :data:`RESERVED_OPTIONS`,
    written out or abbreviated (``--se``; ``train`` refuses abbreviations, but a spec is refused before it runs).

    :raises ValueError: naming the problem
    """
    if not isinstance(options, (list, tuple)) or not all(isinstance(o, str) for o in options):
        raise ValueError(f'options must be a list of strings, e.g. ["--iterations", "3"], got {options!r}')
    names = {o.partition("=")[0] for o in options if o.startswith("--") and len(o.partition("=")[0]) > 2}
    reserved = sorted({r for r in RESERVED_OPTIONS for n in names if r.startswith(n)})
    if reserved:
        raise ValueError(f"options may not set {reserved} (nor abbreviate them): the sweep sets them")
    if {"-h", "--help"} & names | {"-h"} & set(options):
        raise ValueError("options may not ask for --help: a run would print it and count as finished")


def check_run_name(name: Any) -> None:
    """
    Refuse a run name that is not one path component: a run's directory is ``out/<name>``, never outside ``out``.

    :raises ValueError: naming the problem
    """
    if (
        not isinstance(name, str)
        or name in ("", ".", "..")
        or any(c in name for c in "/\\\0")
        or len(name.encode(errors="replace")) > 200
        or not name.isprintable()
    ):
        raise ValueError(
            f"a run name must be one printable path component (no '/', '\\', '.' or '..', at most 200 bytes), "
            f"got {name!r}"
        )


def _normalised(name: str) -> str:
    """The name as file systems may compare it (Unicode NFC, case folded): two runs must differ in it."""
    return unicodedata.normalize("NFC", name).casefold()


@dataclass
class RunOutcome:
    """
    How a run of a sweep ended: ``finished`` (now or before: ``skipped``), ``failed`` with its error, or
    ``interrupted`` (the sweep was stopped by Ctrl-C before the run ended; running the sweep again continues it).
    """

    spec: RunSpec
    run_dir: Path
    status: str
    attempts: int = 0
    summary: dict[str, Any] = field(default_factory=dict)
    error: str = ""


def grid(
    domains: Sequence[str],
    algos: Sequence[str],
    seeds: Sequence[int],
    weights: Sequence[Sequence[float]] = (),
    options: Sequence[str] = (),
) -> list[RunSpec]:
    """
    The runs of domains × algorithms × seeds; ``fixed`` makes one run per entry of ``weights``.

    :raises ValueError: ``fixed`` without weights, weights without ``fixed``, options that are not a list of strings,
        or an invalid run
    """
    check_options(options)  # before tuple(): a string would become its characters
    if ("fixed" in algos) != bool(weights):
        raise ValueError("weights are for the algorithm 'fixed', and 'fixed' needs weights")
    return [
        RunSpec(domain, algo, seed, w, tuple(options))
        for domain in domains
        for algo in algos
        for w in (weights if algo == "fixed" else [None])
        for seed in seeds
    ]


def read_spec(path: str | Path) -> list[RunSpec]:
    """
    The runs of a sweep file: JSON, either ``{"runs": [{"domain": ..., "algo": ..., "seed": ..., "w": ...,
    "options": [...]}, ...]}`` or a grid ``{"domains": [...], "algos": [...], "seeds": [...], "weights": [...],
    "options": [...]}``.

    :raises ValueError: a file that is not such JSON, with what is wrong in it
    """
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"sweep file {path}: {error}") from error
    if not isinstance(data, dict):
        raise ValueError(f"sweep file {path}: expected a JSON object with 'runs' or a grid")
    try:
        if "runs" in data:
            return [
                RunSpec(**{**run, "w": run.get("w"), "options": run.get("options", ())}) for run in _runs(data["runs"])
            ]
        unknown = set(data) - {"domains", "algos", "seeds", "weights", "options"}
        if unknown:
            raise ValueError(f"unknown keys {sorted(unknown)}")
        return grid(data["domains"], data["algos"], data["seeds"], data.get("weights", ()), data.get("options", ()))
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"sweep file {path}: {error}") from error


def _runs(runs: Any) -> list[dict[str, Any]]:
    if not isinstance(runs, list) or not all(isinstance(run, dict) for run in runs):
        raise ValueError("'runs' must be a list of objects")
    return runs


def train_run(spec: RunSpec, run_dir: Path) -> RunOutcome:
    """
    Train (or continue) one run in this process, as a sweep's task does; its output is appended to ``train.log``.

    :raises RuntimeError: the run stopped with an error (the task is retried and continues from the checkpoint)
    :raises ValueError: the run's arguments are refused (not retried)
    """
    with RunDirectory(run_dir).lock(f"sb3-sfgpi sweep run {spec.run_name}"):  # one writer: sweep.json, train.log
        return _train_run(spec, run_dir)


def _train_run(spec: RunSpec, run_dir: Path) -> RunOutcome:
    from sb3_sfgpi.cli import main

    record = _read_record(run_dir)
    attempt = {"pid": os.getpid(), "host": socket.gethostname(), "dir": str(run_dir), "started": _now()}
    record = {"spec": spec.to_json(), "attempts": [*record.get("attempts", []), attempt], "finished": False}
    _write_record(run_dir, record)
    argv = spec.train_argv(run_dir, resume=RunDirectory(run_dir).has_checkpoint())
    with open(run_dir / "train.log", "a") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        print(f"--- attempt {len(record['attempts'])}: sb3-sfgpi {' '.join(argv)}", flush=True)
        try:
            code = main(argv)
        except SystemExit as error:  # argparse refused an option: a refused run, not a dead worker to retry
            code = error.code if isinstance(error.code, int) else 2
    if code == 2:
        raise ValueError(f"{spec.run_name}: train refused its arguments (see {run_dir / 'train.log'})")
    if code != 0:
        raise RuntimeError(f"{spec.run_name}: train stopped with exit code {code} (see {run_dir / 'train.log'})")
    _write_record(run_dir, {**record, "finished": True, "ended": _now()})
    return _outcome(spec, run_dir, "finished")


def train_run_shipped(spec: RunSpec, store: Any, out: Path) -> RunOutcome:
    """
    :func:`train_run` in a folder of this node, its run directory sent home to ``store`` (see
    :mod:`sb3_sfgpi.cli.run_shipping`).

    :param out: the sweep's directory on the driver's machine (where the outcome says the run is)
    """
    with node_run_directory(store, spec.run_name) as work:
        outcome = train_run(spec, work)
    return replace(outcome, run_dir=out / spec.run_name)


def run_sweep(
    specs: Iterable[RunSpec],
    out: str | Path,
    address: str | None = None,
    num_cpus: int | None = None,
    cpus_per_run: float = 1.0,
    max_retries: int = 3,
    progress_bar: bool = True,
    shared_filesystem: bool = True,
) -> list[RunOutcome]:
    """
    Run every spec as a Ray task (those that finished with the same spec before are skipped).

    :param specs: the runs
    :param out: the sweep's directory (one run directory per run); paths in the runs' options should be absolute
    :param address: a Ray cluster to join (``ray start --head`` prints it); None: ``RAY_ADDRESS``, else a local Ray
    :param num_cpus: CPUs of a local Ray (default: the machine's)
    :param cpus_per_run: CPUs Ray reserves for each run (at most the cluster's: a task asking more would wait for
        ever)
    :param max_retries: how often a run whose worker died, or that stopped with an error, is tried again
    :param progress_bar: a bar over the runs
    :param shared_filesystem: every node sees ``out``; False: each run works in its node's temporary directory and
        sends its run directory to ``out`` on this machine after every checkpoint and at its end (a retried run
        continues from the last checkpoint that arrived)
    :return: per run, in the order given, how it ended
    :raises ValueError: two runs with the same name
    """
    specs, out = list(specs), Path(out).resolve()  # the workers' directory may not be this process's
    names = [spec.run_name for spec in specs]
    normalised = [_normalised(name) for name in names]
    if len(set(normalised)) != len(names):
        same = sorted({n for n, key in zip(names, normalised, strict=True) if normalised.count(key) > 1})
        raise ValueError(f"two runs of the sweep have the same name: {same}")
    outcomes: dict[str, RunOutcome] = {
        spec.run_name: _outcome(spec, out / spec.run_name, "skipped") for spec in specs if _finished(spec, out)
    }
    pending = [spec for spec in specs if spec.run_name not in outcomes]
    bar = tqdm(total=len(specs), initial=len(outcomes), desc="sweep", unit="run", disable=not progress_bar)
    if pending:
        _run_pending(pending, out, outcomes, bar, address, num_cpus, cpus_per_run, max_retries, shared_filesystem)
    bar.close()
    return [outcomes[name] for name in names]


def _run_pending(
    pending: list[RunSpec],
    out: Path,
    outcomes: dict[str, RunOutcome],
    bar: Any,
    address: str | None,
    num_cpus: int | None,
    cpus_per_run: float,
    max_retries: int,
    shared_filesystem: bool,
) -> None:
    """
    The runs not finished before, as Ray tasks, their outcomes recorded as they end. Ctrl-C at any moment, Ray's
    start-up included (which a KeyboardInterrupt would leave half done), stops them: the handler only sets a flag,
    looked at once Ray is up and every :data:`POLL_SECONDS`; the runs are cancelled (their checkpoints stay) and
    recorded as ``interrupted``.
    """
    ray, refs = None, {}
    with _ctrl_c_flag() as interrupted:
        try:
            ray = joined_ray(address, num_cpus)
            if interrupted.is_set():
                raise KeyboardInterrupt
            cpus = min(cpus_per_run, ray.cluster_resources().get("CPU", cpus_per_run))
            options = dict(num_cpus=cpus, max_retries=max_retries, retry_exceptions=[RuntimeError])
            if shared_filesystem:
                task = ray.remote(train_run).options(**options)
                refs = {task.remote(spec, out / spec.run_name): spec for spec in pending}
            else:
                task, store = ray.remote(train_run_shipped).options(**options), start_store(ray, out)
                refs = {task.remote(spec, store, out): spec for spec in pending}
            while refs:
                if interrupted.is_set():
                    raise KeyboardInterrupt
                ready, _ = ray.wait(list(refs), num_returns=1, timeout=POLL_SECONDS)
                for ref in ready:
                    spec = refs.pop(ref)
                    outcomes[spec.run_name] = _collect(ray, ref, spec, out / spec.run_name)
                    bar.update(1)
        except KeyboardInterrupt:
            _interrupted(ray, refs, outcomes, out)
            for spec in pending:  # interrupted before Ray took them
                outcomes.setdefault(spec.run_name, _outcome(spec, out / spec.run_name, "interrupted"))


@contextlib.contextmanager
def _ctrl_c_flag() -> Iterator[threading.Event]:
    """
    An event set by Ctrl-C (SIGINT) instead of a KeyboardInterrupt, for the time of the ``with`` block. Off the main
    thread, where no handler can be installed, an event that is never set (a KeyboardInterrupt stays as it is).
    """
    interrupted = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield interrupted
        return

    def on_sigint(signum: int, frame: Any) -> None:
        interrupted.set()

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield interrupted
    finally:
        signal.signal(signal.SIGINT, previous)


def _interrupted(ray: Any, refs: dict[Any, RunSpec], outcomes: dict[str, RunOutcome], out: Path) -> None:
    """Cancel the runs not ended yet and record them as ``interrupted``."""
    for ref in refs:
        with contextlib.suppress(Exception):
            ray.cancel(ref)
    with contextlib.suppress(Exception):  # the runs stop at once; their errors are taken, not reported by Ray
        ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=30)
        for ref in ready:
            with contextlib.suppress(Exception):
                ray.get(ref)
    for spec in refs.values():
        outcomes[spec.run_name] = _outcome(spec, out / spec.run_name, "interrupted")


def _collect(ray: Any, ref: Any, spec: RunSpec, run_dir: Path) -> RunOutcome:
    """The outcome of a finished task: its result, or ``failed`` with the last error."""
    try:
        return ray.get(ref)
    except Exception as error:  # a Ray error wrapping the task's, or the worker's death after the last retry
        cause = getattr(error, "cause", None) or error
        return _outcome(spec, run_dir, "failed", error=" ".join(str(cause).split())[:300])


def _finished(spec: RunSpec, out: Path) -> bool:
    record = _read_record(out / spec.run_name)
    return bool(record.get("finished")) and record.get("spec") == spec.to_json()


def _outcome(spec: RunSpec, run_dir: Path, status: str, error: str = "") -> RunOutcome:
    record = _read_record(run_dir)
    rows = RunDirectory(run_dir).read_summary() if RunDirectory(run_dir).has_evaluations() else []
    return RunOutcome(spec, run_dir, status, len(record.get("attempts", [])), rows[-1] if rows else {}, error)


def _read_record(run_dir: Path) -> dict[str, Any]:
    try:
        record = json.loads((run_dir / SWEEP_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return record if isinstance(record, dict) else {}


def _write_record(run_dir: Path, record: dict[str, Any]) -> None:
    atomic_write_json(run_dir / SWEEP_FILE, record)


def _now() -> str:
    return datetime.datetime.now().isoformat(timespec="seconds")

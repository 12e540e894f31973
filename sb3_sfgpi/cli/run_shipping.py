"""Run directories that come home: a sweep's runs on nodes that do not see the driver's ``--out``.

With ``sweep --no-shared-filesystem`` each run works in a folder of its node's temporary directory and sends a
snapshot of its run directory to the driver after every checkpoint and when it ends; a :class:`RunStore` actor on
the driver's node unpacks it into ``out/<run>``. A retried run (its worker or its node lost) starts from the last
snapshot that arrived, so it continues from that checkpoint as ``train --resume`` does.

A snapshot is taken while the run goes on writing. It holds the run as of one checkpoint: ``checkpoint.json`` is
read before and after the files, and the files again until it did not change between the two; the staged policy
set's manifest is read before the committed one (a commit renames the first to the second), so one of the two is
the set the checkpoint names; files a writer adds beyond the checkpoint are ignored by a resume.
"""

from __future__ import annotations

import contextlib
import io
import shutil
import tarfile
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sb3_sfgpi.run_directory import STAGED_MANIFEST, RunDirectory

#: Seconds between two looks of a run at its checkpoint, to send it home when it changed.
SHIP_SECONDS = 2.0
#: Files of a run directory that stay on the node: the writer's lock.
NOT_SHIPPED = (".lock",)
#: The most attempts at a snapshot while the checkpoint keeps changing (each iteration takes far longer than one).
SNAPSHOT_TRIES = 20


def snapshot(run_dir: Path) -> bytes:
    """
    A gzipped tar of ``run_dir`` as of its checkpoint (see the module docstring), its writer still running.

    :raises RuntimeError: the checkpoint changed during every try
    """
    checkpoint = run_dir / RunDirectory.CHECKPOINT
    for _ in range(SNAPSHOT_TRIES):
        before = _read(checkpoint)
        data = _tar(run_dir)
        if _read(checkpoint) == before:
            return data
    raise RuntimeError(f"{run_dir}: the checkpoint changed during {SNAPSHOT_TRIES} snapshots")


def _tar(run_dir: Path) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as archive:
        for path in sorted(run_dir.rglob("*"), key=lambda p: (p.name != STAGED_MANIFEST, p.as_posix())):
            if path.name in NOT_SHIPPED or path.is_symlink() or not path.is_file():
                continue
            try:
                mtime, data = path.stat().st_mtime, path.read_bytes()
            except FileNotFoundError:  # gone since the listing: not the checkpoint's
                continue
            info = tarfile.TarInfo(path.relative_to(run_dir).as_posix())
            info.size, info.mtime = len(data), int(mtime)
            archive.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def _read(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None


def unpack(data: bytes, target: Path) -> None:
    """
    Make ``target`` the run directory a :func:`snapshot` holds: unpacked beside it, then put in its place.

    :raises ValueError: a member that is not a plain file inside the directory
    """
    incoming, old = target.with_name(f".{target.name}.incoming"), target.with_name(f".{target.name}.old")
    shutil.rmtree(incoming, ignore_errors=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as archive:
        for member in archive.getmembers():
            parts = Path(member.name).parts
            if not member.isfile() or Path(member.name).is_absolute() or ".." in parts or parts[-1] in NOT_SHIPPED:
                raise ValueError(f"a run snapshot may hold only plain files inside the run, not {member.name!r}")
        archive.extractall(incoming, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    shutil.rmtree(old, ignore_errors=True)
    if target.exists():
        target.rename(old)
    incoming.rename(target)
    shutil.rmtree(old, ignore_errors=True)


class RunStore:
    """
    The driver's end (a Ray actor on the driver's node): the runs' directories in the sweep's ``out``.

    :param out: the sweep's directory on the driver's machine
    """

    def __init__(self, out: str):
        self.out = Path(out)

    def put(self, name: str, data: bytes) -> None:
        """Make ``out/name`` the run directory of the snapshot ``data``."""
        unpack(data, self.out / name)

    def get(self, name: str) -> bytes | None:
        """A snapshot of ``out/name`` (None: nothing of this run arrived yet)."""
        run_dir = self.out / name
        return snapshot(run_dir) if run_dir.is_dir() else None


def start_store(ray: Any, out: Path) -> Any:
    """A :class:`RunStore` for ``out``, pinned to this (the driver's) node."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
    return ray.remote(RunStore).options(num_cpus=0, scheduling_strategy=here).remote(str(out))


@contextlib.contextmanager
def node_run_directory(store: Any, name: str) -> Iterator[Path]:
    """
    The run's directory on this node for one attempt: the last snapshot the driver has, sent home after every
    checkpoint (a thread looks every :data:`SHIP_SECONDS`) and when the attempt ends, however it ends; removed then.
    """
    import ray

    work = Path(tempfile.mkdtemp(prefix="sb3-sfgpi-run-")) / name
    try:
        data = ray.get(store.get.remote(name))
        if data is not None:
            unpack(data, work)
        with _shipping(work, store, name):
            yield work
    finally:
        if work.is_dir():
            ray.get(store.put.remote(name, snapshot(work)))
        shutil.rmtree(work.parent, ignore_errors=True)


@contextlib.contextmanager
def _shipping(work: Path, store: Any, name: str) -> Iterator[None]:
    """Send ``work`` home whenever its checkpoint changed, until the block ends."""
    import ray

    stop = threading.Event()

    def ship() -> None:
        sent = _read(work / RunDirectory.CHECKPOINT)
        while not stop.wait(SHIP_SECONDS):
            current = _read(work / RunDirectory.CHECKPOINT)
            if current is not None and current != sent:
                ray.get(store.put.remote(name, snapshot(work)))
                sent = current

    thread = threading.Thread(target=ship, daemon=True, name="ship-run-home")
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()

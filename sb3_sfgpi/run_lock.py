"""The writer's lock of a run directory: one process writes a run at a time.

``fcntl.flock`` on the directory's ``.lock`` file, which names the holder (pid, host, command). The kernel releases
it when the holder's process ends, however it ends, so no stale lock is left after SIGKILL. Readers take no lock.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
from contextlib import suppress
from pathlib import Path

#: The locks this process holds: resolved path -> [file descriptor, number of holders] (a lock is re-entrant).
_HELD: dict[Path, list[int]] = {}


class RunDirectoryBusy(ValueError):
    """Another process writes the run directory (it holds the directory's lock)."""


class RunLock:
    """
    The writer's lock of a run directory: ``fcntl.flock`` on its ``.lock`` file, which names the holder (pid, host,
    command). The kernel releases it when the holder's process ends, however it ends (no stale lock after SIGKILL).
    Re-entrant within a process. Released by :meth:`release` or when the object is collected.
    """

    def __init__(self, path: Path, command: str):
        self.path = path.resolve()
        self._held = False
        self.path.mkdir(parents=True, exist_ok=True)
        if self.path in _HELD:
            _HELD[self.path][1] += 1
            self._held = True
            return
        refuse_links(self.path)  # a writer follows no link out of its run directory
        fd = os.open(self.path / ".lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 4096).decode(errors="replace")
            os.close(fd)
            raise RunDirectoryBusy(f"{path} is being written by another process ({_holder(holder)})") from None
        os.ftruncate(fd, 0)
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "command": command}
        os.write(fd, json.dumps(holder).encode())
        _HELD[self.path] = [fd, 1]
        self._held = True

    def release(self) -> None:
        """Release the lock (this holder's share of it); a no-op the second time."""
        if not self._held:
            return
        self._held = False
        held = _HELD[self.path]
        held[1] -= 1
        if held[1] == 0:
            del _HELD[self.path]
            os.close(held[0])  # closing the descriptor releases the lock; the file stays (no unlink race)

    def discard(self) -> None:
        """Release the lock and remove its file (the directory was made for a run that was then refused)."""
        if self._held and _HELD[self.path][1] == 1:
            with suppress(OSError):
                (self.path / ".lock").unlink()
        self.release()

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        self.release()


def refuse_links(path: Path) -> None:
    """
    Refuse a run directory that holds a symbolic link anywhere inside it: what a run writes (its lock, logs, Π,
    TensorBoard files, checkpoint) would go, or be deleted, wherever the link points.

    :raises ValueError: naming the first link found
    """
    for folder, names, files in os.walk(path, followlinks=False):
        for name in [*names, *files]:
            entry = Path(folder) / name
            if entry.is_symlink():
                raise ValueError(
                    f"{entry} is a symbolic link: a run directory must hold its own files (a writer would follow it "
                    "out of the directory); replace it with the file or folder it points to"
                )


def _holder(text: str) -> str:
    """The holder named in a lock file, as one line."""
    try:
        holder = json.loads(text)
        return f"pid {holder['pid']} on {holder['host']}: {holder['command']}"
    except (ValueError, KeyError, TypeError):
        return "a process that has not named itself yet"


def check_not_written(path: Path) -> None:
    """
    Refuse a directory that another process writes now (holds its lock); touches nothing.

    :raises RunDirectoryBusy: naming the holder
    """
    if not (path / ".lock").is_file():
        return
    with open(path / ".lock", "rb") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
            fcntl.flock(handle, fcntl.LOCK_UN)
        except BlockingIOError:
            if path.resolve() not in _HELD:
                holder = _holder(handle.read(4096).decode(errors="replace"))
                raise RunDirectoryBusy(f"{path} is being written by another process ({holder})") from None

"""JSON helpers: Gymnasium spaces as plain data, and atomic file writes.

Nothing here unpickles or evaluates anything: a file read through this module can only yield data.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces


def space_to_dict(space: spaces.Space) -> dict[str, Any]:
    """
    Describe a Box, Discrete, MultiDiscrete or MultiBinary space as JSON-serialisable data.

    :raises ValueError: any other space
    """
    if isinstance(space, spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    if isinstance(space, spaces.MultiDiscrete):
        return {"type": "MultiDiscrete", "nvec": space.nvec.tolist(), "start": np.asarray(space.start).tolist()}
    if isinstance(space, spaces.MultiBinary):
        return {"type": "MultiBinary", "n": np.asarray(space.n).tolist()}
    if isinstance(space, spaces.Box):
        return {
            "type": "Box",
            "low": _finite_or_str(space.low),
            "high": _finite_or_str(space.high),
            "shape": list(space.shape),
            "dtype": np.dtype(space.dtype).name,
        }
    raise ValueError(f"cannot describe {type(space).__name__} spaces as JSON")


#: The largest count a stored space may declare (actions, values of a component, elements of a Box): beyond, no
#: network or table of it fits in memory, and numpy's int64 arithmetic on it could overflow.
MAX_SPACE_SIZE = 2**31 - 1


def space_from_dict(data: dict[str, Any]) -> spaces.Space:
    """
    Rebuild a space described by :func:`space_to_dict`.

    :raises ValueError: unknown or malformed description, or counts beyond :data:`MAX_SPACE_SIZE`
    """
    try:
        kind = data["type"]
        if kind == "Discrete":
            return spaces.Discrete(int(_integers(data["n"], "n", 1)), start=int(_integers(data["start"], "start")))
        if kind == "MultiDiscrete":
            nvec, start = _integers(data["nvec"], "nvec", 1), _integers(data["start"], "start")
            return spaces.MultiDiscrete(nvec, start=start)
        if kind == "MultiBinary":
            n = _integers(data["n"], "n", 1)
            return spaces.MultiBinary(int(n) if n.ndim == 0 else n.tolist())
        if kind == "Box":
            dtype = np.dtype(data["dtype"])
            shape = tuple(int(n) for n in _integers(data["shape"], "shape", 1).reshape(-1))
            if np.prod(np.array(shape, dtype=np.float64)) > MAX_SPACE_SIZE:
                raise ValueError(f"a Box of shape {shape} is larger than {MAX_SPACE_SIZE} elements")
            low = np.array(data["low"], dtype=np.float64)
            high = np.array(data["high"], dtype=np.float64)
            return spaces.Box(low=low.astype(dtype), high=high.astype(dtype), shape=shape, dtype=dtype)
    except (KeyError, TypeError, ValueError, OverflowError) as error:
        raise ValueError(f"malformed space description {data!r}: {error}") from error
    raise ValueError(f"unknown space type {kind!r}")


def _integers(value: Any, name: str, low: int = -MAX_SPACE_SIZE) -> np.ndarray:
    """Integers of JSON (not bools, not floats) in ``[low, MAX_SPACE_SIZE]``, as an int64 array."""
    array = np.array(value)
    if array.dtype.kind not in "iu" or (array.size and (array.min() < low or array.max() > MAX_SPACE_SIZE)):
        raise ValueError(f"{name} must hold integers in [{low}, {MAX_SPACE_SIZE}], got {value!r}")
    return array.astype(np.int64)


def _finite_or_str(array: np.ndarray) -> list:
    # JSON has no infinities: keep them as the strings "inf" / "-inf" (np.array(...) reads them back).
    return np.where(np.isfinite(array), array.astype(np.float64), array.astype(str)).tolist()


def atomic_write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as JSON so that ``path`` holds either the old or the new content, never a part."""
    atomic_write_bytes(path, json.dumps(data, indent=2, allow_nan=False).encode())


def atomic_write_bytes(path: str | Path, payload: bytes) -> None:
    """
    Write ``payload`` to a temporary file beside ``path``, flush it to disk, then rename it over ``path``.

    :raises OSError: the write failed (a full disk, say): ``path`` is as it was, and the message names it
    """
    path = Path(path)
    try:
        _write_and_rename(path, payload)
    except OSError as error:
        raise OSError(error.errno, f"cannot write {path} ({error.strerror or error}); it is as it was") from error


def _write_and_rename(path: Path, payload: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # the mode of an ordinary file (mkstemp's is 0600)
        with os.fdopen(fd, "wb") as handle:
            handle.write(payload)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    """The process's umask (reading it means setting it: set it back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: The largest JSON file read (a run's or a policy set's): parsing takes several times its size in memory.
MAX_JSON_BYTES = 64 * 2**20


def read_json(path: str | Path, what: str) -> Any:
    """
    Read a JSON file.

    :param what: what the file is, for error messages
    :raises ValueError: missing or unreadable file, or one larger than :data:`MAX_JSON_BYTES`
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{what} {path} does not exist")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise ValueError(f"{what} {path} is larger than {MAX_JSON_BYTES // 2**20} MB: not a file sb3-sfgpi wrote")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:  # RecursionError: nested too deep
        raise ValueError(f"{what} {path} is not valid JSON (truncated or corrupt?): {error}") from error


def jsonable(value: Any) -> Any:
    """Numbers, strings, lists and dicts only (numpy values become Python ones, NaN None; the rest is dropped)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items() if jsonable(v) is not None}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None  # JSON has no NaN or infinity
    if isinstance(value, (int, float, str, bool)) or value is None:
        return value
    return None

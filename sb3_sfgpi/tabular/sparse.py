"""A table of successor features that holds the rows it has stored; every other row reads one default row.

Tables of large observation spaces are mostly never visited (the Four-Room with object flags visits a small
fraction of its rows), so :class:`SparseTable` keeps a growable array of the stored rows and a dense ``int32`` map
from a row to its slot in that array (``-1``: not stored). The array's last row is the default row, so a lookup is one
fancy index with no special case: slot ``-1`` reads the last row. A row reads exactly what a dense table holding
the default everywhere and the stored rows at their places would read.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Stored rows a new table has room for before it grows (it doubles).
INITIAL_CAPACITY = 1024


class SparseTable:
    """
    ``n_rows`` rows of ``width`` float32 values: the stored rows in slots, every other row the default row.

    :param n_rows: number of rows of the (dense) table it stands for
    :param width: values per row
    :param default: the value of every component of the rows not stored
    """

    def __init__(self, n_rows: int, width: int, default: float = 0.0):
        self.n_rows, self.width = n_rows, width
        self._reset(np.full(width, default, dtype=np.float32), INITIAL_CAPACITY)

    def _reset(self, default: np.ndarray, capacity: int) -> None:
        """Nothing stored, room for ``capacity`` rows, ``default`` as the default row."""
        self._values = np.empty((capacity + 1, self.width), dtype=np.float32)
        self._values[-1] = default
        self._rows = np.empty(capacity, dtype=np.int64)
        self._count = 0
        self._slot: np.ndarray | None = None  # built on first use (copies in a policy set rarely need theirs)

    def __len__(self) -> int:
        """The number of stored rows."""
        return self._count

    @property
    def default(self) -> np.ndarray:
        """The default row (a view: writing it changes every row not stored)."""
        return self._values[-1]

    @property
    def values(self) -> np.ndarray:
        """
        The storage, shape ``(capacity + 1, width)``: the stored rows in their slots, the default row last (a view,
        replaced when the table grows). Index it with :meth:`slots`.
        """
        return self._values

    def stored_rows(self) -> np.ndarray:
        """The row of each slot, in slot order (a view)."""
        return self._rows[: self._count]

    def stored_values(self) -> np.ndarray:
        """The values of each slot, in slot order (a view)."""
        return self._values[: self._count]

    def slot_map(self) -> np.ndarray:
        """For every row its slot, ``-1`` where not stored: ``int32``, shape ``(n_rows,)``."""
        if self._slot is None:
            self._slot = np.full(self.n_rows, -1, dtype=np.int32)
            self._slot[self.stored_rows()] = np.arange(self._count, dtype=np.int32)
        return self._slot

    def slots(self, rows: np.ndarray) -> np.ndarray:
        """The slots of ``rows`` (``-1``, the default row, where not stored), as ``int64``."""
        return self.slot_map().take(rows).astype(np.int64)

    def lookup(self, rows: np.ndarray) -> np.ndarray:
        """The values of ``rows``, shape ``(len(rows), width)`` (a copy)."""
        return self._values.take(self.slots(rows), axis=0)

    def store(self, rows: np.ndarray) -> np.ndarray:
        """
        Store ``rows`` that are not yet stored (each starts as the default row), growing if needed.

        :return: the slots of ``rows``, ``int64``
        """
        slot_map = self.slot_map()
        slots = slot_map.take(rows)
        if slots.min(initial=0) < 0:
            new = np.unique(np.asarray(rows)[slots < 0])
            self._grow(self._count + len(new))
            self._values[self._count : self._count + len(new)] = self._values[-1]
            self._rows[self._count : self._count + len(new)] = new
            slot_map[new] = np.arange(self._count, self._count + len(new), dtype=np.int32)
            self._count += len(new)
            slots = slot_map.take(rows)
        return slots.astype(np.int64)

    def slot_rows(self) -> np.ndarray:
        """The row of each slot, with room for every slot of the storage (a view, replaced when the table grows)."""
        return self._rows

    def reserve(self, extra: int) -> None:
        """Make room for ``extra`` more stored rows (compiled code stores them itself: :meth:`adopt_stored`)."""
        self._grow(self._count + extra)

    def adopt_stored(self, count: int) -> None:
        """
        Hold ``count`` stored rows: compiled code stored the new ones in the room :meth:`reserve` made, as
        :meth:`store` does (values, :meth:`slot_rows` and the slot map).
        """
        if not self._count <= count <= len(self._rows):
            raise ValueError(f"a table of {self._count} stored rows and room for {len(self._rows)} cannot hold {count}")
        self._count = count

    def _grow(self, needed: int) -> None:
        """Make room for ``needed`` stored rows (at least doubling), keeping the stored and default rows."""
        capacity = len(self._rows)
        if needed <= capacity:
            return
        capacity = max(needed, 2 * capacity)
        values = np.empty((capacity + 1, self.width), dtype=np.float32)
        values[: self._count], values[-1] = self.stored_values(), self.default
        rows = np.empty(capacity, dtype=np.int64)
        rows[: self._count] = self.stored_rows()
        self._values, self._rows = values, rows

    def fill(self, value: float) -> None:
        """Every row ``value``: nothing stored, the default row ``value``."""
        self._reset(np.full(self.width, value, dtype=np.float32), INITIAL_CAPACITY)

    def set_rows(self, rows: np.ndarray, values: np.ndarray, default: np.ndarray) -> None:
        """
        Hold exactly ``rows`` (distinct, in ``0..n_rows-1``: unchecked) with ``values``, and ``default`` elsewhere.
        """
        self._reset(np.asarray(default, dtype=np.float32), max(len(rows), 1))
        self._rows[: len(rows)] = rows
        self._values[: len(rows)] = values
        self._count = len(rows)

    def dense(self) -> np.ndarray:
        """The whole table, shape ``(n_rows, width)`` (a new array: for tests and small tables)."""
        return self._values.take(self.slot_map().astype(np.int64), axis=0)

    def set_dense(self, table: np.ndarray) -> None:
        """Hold ``table`` (shape ``(n_rows, width)``): its rows that differ from the default row are stored."""
        table = np.asarray(table, dtype=np.float32).reshape(self.n_rows, self.width)
        rows = np.flatnonzero((table != self.default).any(axis=1))
        self.set_rows(rows, table[rows], self.default.copy())

    def __getstate__(self) -> dict[str, Any]:
        # Copies (deepcopy, pickle) hold the stored rows only: no spare room, no slot map (rebuilt on first use).
        return {
            "n_rows": self.n_rows,
            "width": self.width,
            "rows": self.stored_rows().copy(),
            "values": self.stored_values().copy(),
            "default": self.default.copy(),
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.n_rows, self.width = state["n_rows"], state["width"]
        self.set_rows(state["rows"], state["values"], state["default"])

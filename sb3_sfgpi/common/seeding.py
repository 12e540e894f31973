"""Seeds of sub-tasks derived from the seed of a run."""

from __future__ import annotations

import zlib
from typing import Any


def derive_seed(seed: int, *parts: Any) -> int:
    """
    A seed for a sub-task (an iteration, an agent, an evaluation, ...) that depends only on ``seed`` and ``parts``.

    :param seed: the seed of the run
    :param parts: what names the sub-task, e.g. ``(iteration, agent)`` or ``("eval", i)``
    :return: a non-negative 31-bit integer
    """
    return zlib.crc32(repr((seed, *parts)).encode()) & 0x7FFFFFFF

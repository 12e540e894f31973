"""numpy's global random numbers (``np.random.rand``, ``np.random.randint``) drawn by compiled code, in place.

SB3 seeds ``np.random`` (``set_random_seed``) and the learners draw their minibatches and ε-greedy choices from it, so
a run's numbers depend on that stream. Compiled code that drew from a generator of its own would change every number
a run prints. Here the compiled code reads and advances the very state of numpy's global generator: the memory of
its Mersenne Twister (:func:`global_stream` makes numpy arrays over it) and the same arithmetic as numpy's legacy
``RandomState`` (:func:`random_integers`: masked rejection on 32-bit draws; :func:`random_double`: 53 bits from two
draws), so a draw here and the same draw by numpy give the same number and leave the same state, interleaved in any
order (``tests/test_numpy_random.py``).
"""

from __future__ import annotations

import ctypes

import numpy as np
from numba import njit

#: The Mersenne Twister's state: 624 words, then the position of the next one (numpy's ``mt19937_state``).
_N, _M = 624, 397
_UPPER, _LOWER = np.uint32(0x80000000), np.uint32(0x7FFFFFFF)
_MATRIX = np.uint32(0x9908B0DF)

_streams: dict[int, tuple[object, np.ndarray, np.ndarray]] = {}


def global_stream() -> tuple[np.ndarray, np.ndarray] | None:
    """
    Arrays over the state of numpy's global generator (``np.random.get_bit_generator()``): its 624 words (uint32)
    and its position (int32, one element), written by the compiled draws as numpy writes them; None where that
    generator is not a Mersenne Twister (``np.random.set_bit_generator`` can make it another), whose draws only numpy
    makes.
    """
    generator = np.random.get_bit_generator()
    if not isinstance(generator, np.random.MT19937):
        return None
    address = generator.ctypes.state_address
    cached = _streams.get(address)
    if cached is None or cached[0] is not generator:
        memory = np.ctypeslib.as_array((ctypes.c_uint32 * (_N + 1)).from_address(address))
        cached = _streams[address] = (generator, memory[:_N], memory[_N:].view(np.int32))  # holds the generator
    return cached[1], cached[2]


@njit(cache=True, nogil=True)
def _twist(key: np.ndarray) -> None:
    """The next 624 words of the Mersenne Twister, in place."""
    for i in range(_N):
        y = (key[i] & _UPPER) | (key[(i + 1) % _N] & _LOWER)
        value = key[(i + _M) % _N] ^ (y >> np.uint32(1))
        if y & np.uint32(1):
            value ^= _MATRIX
        key[i] = value


@njit(cache=True, nogil=True)
def next_uint32(key: np.ndarray, position: np.ndarray) -> np.uint32:
    """The generator's next 32-bit output (MT19937 with its tempering), advancing the state."""
    if position[0] >= _N:
        _twist(key)
        position[0] = 0
    y = key[position[0]]
    position[0] += 1
    y ^= y >> np.uint32(11)
    y ^= (y << np.uint32(7)) & np.uint32(0x9D2C5680)
    y ^= (y << np.uint32(15)) & np.uint32(0xEFC60000)
    return y ^ (y >> np.uint32(18))


@njit(cache=True, nogil=True)
def random_integers(key: np.ndarray, position: np.ndarray, low: int, high: int, out: np.ndarray) -> None:
    """
    ``out[:] = np.random.randint(low, high, size=len(out))`` for ``high - low <= 2**32``: each value the low bits of a
    32-bit draw under the smallest mask that covers ``high - 1 - low``, drawn again while beyond it; nothing drawn
    when ``high - low == 1``.
    """
    span = np.uint32(high - 1 - low)
    mask = span
    for shift in (1, 2, 4, 8, 16):
        mask |= mask >> np.uint32(shift)
    for i in range(out.shape[0]):
        value = np.uint32(0)
        if span:
            value = next_uint32(key, position) & mask
            while value > span:
                value = next_uint32(key, position) & mask
        out[i] = low + np.int64(value)


@njit(cache=True, nogil=True)
def random_double(key: np.ndarray, position: np.ndarray) -> float:
    """``np.random.rand()``: 27 and 26 bits of two draws, as a double in [0, 1)."""
    high = next_uint32(key, position) >> np.uint32(5)
    low = next_uint32(key, position) >> np.uint32(6)
    return (high * 67108864.0 + low) / 9007199254740992.0

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


#: PCG64's multiplier (numpy's ``PCG_DEFAULT_MULTIPLIER_128``), as its high and low 64-bit words.
_PCG_MULTIPLIER = (np.uint64(0x2360ED051FC65DA4), np.uint64(0x4385DF649FCCF645))
_LOW32 = np.uint64(0xFFFFFFFF)
#: The words of :func:`pcg64_words`: the 128-bit state and increment (high, low), the buffered half and its flag.
_STATE_HIGH, _STATE_LOW, _INC_HIGH, _INC_LOW, _HAS_UINT32, _UINTEGER = range(6)


def pcg64_words(generator: np.random.Generator) -> np.ndarray | None:
    """
    The state of a Generator's PCG64 as six uint64 words for :func:`pcg64_integer` (state and increment, high word
    first, then numpy's buffered 32-bit half and its flag), or None where its bit generator is another.
    """
    if not isinstance(generator.bit_generator, np.random.PCG64):
        return None
    state = generator.bit_generator.state
    words = [state["state"]["state"] >> 64, state["state"]["state"], state["state"]["inc"] >> 64, state["state"]["inc"]]
    words += [state["has_uint32"], state["uinteger"]]
    return np.array([word & 0xFFFFFFFFFFFFFFFF for word in words], dtype=np.uint64)


def set_pcg64_words(generator: np.random.Generator, words: np.ndarray) -> None:
    """Give a Generator's PCG64 the state :func:`pcg64_words` read (and compiled draws advanced)."""
    state, inc = (
        (int(words[_STATE_HIGH]) << 64) | int(words[_STATE_LOW]),
        (int(words[_INC_HIGH]) << 64) | int(words[_INC_LOW]),
    )
    generator.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": inc},
        "has_uint32": int(words[_HAS_UINT32]),
        "uinteger": int(words[_UINTEGER]),
    }


@njit(cache=True, nogil=True)
def _multiply_64(a: np.uint64, b: np.uint64) -> tuple[np.uint64, np.uint64]:
    """The 128-bit product of two 64-bit words, as (high, low)."""
    a_high, a_low, b_high, b_low = a >> np.uint64(32), a & _LOW32, b >> np.uint64(32), b & _LOW32
    low_low, cross = a_low * b_low, a_high * b_low + (a_low * b_low >> np.uint64(32))
    cross_low, cross_high = cross & _LOW32, cross >> np.uint64(32)
    cross_low += a_low * b_high
    return a_high * b_high + cross_high + (cross_low >> np.uint64(32)), (cross_low << np.uint64(32)) | (
        low_low & _LOW32
    )


@njit(cache=True, nogil=True)
def _pcg64_next64(words: np.ndarray) -> np.uint64:
    """PCG64's next 64-bit output (XSL-RR of the state after its LCG step), advancing the state."""
    high, low = _multiply_64(words[_STATE_LOW], _PCG_MULTIPLIER[1])
    high += words[_STATE_HIGH] * _PCG_MULTIPLIER[1] + words[_STATE_LOW] * _PCG_MULTIPLIER[0]
    low += words[_INC_LOW]
    high += words[_INC_HIGH] + np.uint64(low < words[_INC_LOW])
    words[_STATE_HIGH], words[_STATE_LOW] = high, low
    value, rotation = high ^ low, high >> np.uint64(58)
    return (value >> rotation) | (value << ((np.uint64(64) - rotation) & np.uint64(63)))


@njit(cache=True, nogil=True)
def _pcg64_next32(words: np.ndarray) -> np.uint64:
    """numpy's 32-bit draw of PCG64: the buffered upper half of the last 64-bit output, else a new output's lower."""
    if words[_HAS_UINT32]:
        words[_HAS_UINT32] = 0
        return words[_UINTEGER]
    value = _pcg64_next64(words)
    words[_HAS_UINT32], words[_UINTEGER] = 1, value >> np.uint64(32)
    return value & _LOW32


@njit(cache=True, nogil=True)
def pcg64_integer(words: np.ndarray, n: int) -> int:
    """
    ``Generator.integers(n)`` (int64, ``1 <= n < 2**32``) on the PCG64 state ``words``: Lemire's multiply-shift on
    32-bit draws, redrawn below numpy's threshold; nothing drawn when ``n == 1``. The same number, the same state left.
    """
    if n == 1:
        return 0
    bound = np.uint64(n)
    product = _pcg64_next32(words) * bound
    leftover = product & _LOW32
    if leftover < bound:
        threshold = (_LOW32 - (bound - np.uint64(1))) % bound
        while leftover < threshold:
            product = _pcg64_next32(words) * bound
            leftover = product & _LOW32
    return np.int64(product >> np.uint64(32))

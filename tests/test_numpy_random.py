"""Compiled draws from numpy's global generator: the numbers numpy would draw, and the state it would leave."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_sfgpi.tabular.numpy_random import (
    global_stream,
    pcg64_integer,
    pcg64_words,
    random_double,
    random_integers,
    set_pcg64_words,
)


@pytest.fixture
def restored_numpy_state():
    state = np.random.get_state()
    yield
    np.random.set_state(state)


def _numpy_draws(calls: list[tuple[int, int, int]]) -> list[np.ndarray]:
    return [np.random.randint(low, high, size=n) if high else np.random.rand(n) for low, high, n in calls]


def _compiled_draws(calls: list[tuple[int, int, int]]) -> list[np.ndarray]:
    key, position = global_stream()
    draws = []
    for low, high, n in calls:
        if high:
            out = np.empty(n, dtype=np.int64)
            random_integers(key, position, low, high, out)
        else:
            out = np.array([random_double(key, position) for _ in range(n)])
        draws.append(out)
    return draws


CALLS = st.lists(
    st.one_of(
        st.tuples(st.integers(0, 3), st.integers(1, 2**32), st.integers(0, 40)).map(
            lambda c: (c[0], c[0] + c[1], c[2])  # high - low in [1, 2**32]
        ),
        st.tuples(st.just(0), st.just(0), st.integers(0, 3)),  # rand(n)
    ),
    max_size=60,
)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), calls=CALLS)
def test_compiled_draws_are_numpys_draws_and_leave_its_state(seed, calls):
    saved = np.random.get_state()
    np.random.seed(seed)
    expected = _numpy_draws(calls)
    after = np.random.get_state()
    np.random.seed(seed)
    drawn = _compiled_draws(calls)
    state = np.random.get_state()
    np.random.set_state(saved)
    for mine, numpys in zip(drawn, expected, strict=True):
        np.testing.assert_array_equal(mine, numpys)
    assert state[2] == after[2] and np.array_equal(state[1], after[1])


@pytest.mark.parametrize("bits", range(33))
def test_every_mask_width_draws_numpys_integers(restored_numpy_state, bits):
    calls = [
        (0, 2**bits, 50),
        (0, min(2**bits + 1, 2**32), 50),
        (7, 7 + max(2**bits - 1, 1), 50),
    ]  # a span of every width
    np.random.seed(bits)
    expected = _numpy_draws(calls)
    np.random.seed(bits)
    for mine, numpys in zip(_compiled_draws(calls), expected, strict=True):
        np.testing.assert_array_equal(mine, numpys)


def test_compiled_and_numpy_draws_interleave_on_one_stream(restored_numpy_state):
    np.random.seed(3)
    expected = [np.random.randint(0, 1000, size=700), np.random.rand(5), np.random.randint(1, 10**6, size=600)]
    np.random.seed(3)
    key, position = global_stream()
    first = np.empty(700, dtype=np.int64)
    random_integers(key, position, 0, 1000, first)  # 700 draws: past a twist of the 624 words
    middle = np.random.rand(5)  # numpy goes on where the compiled code stopped
    last = np.empty(600, dtype=np.int64)
    random_integers(key, position, 1, 10**6, last)
    for mine, numpys in zip((first, middle, last), expected, strict=True):
        np.testing.assert_array_equal(mine, numpys)


def test_a_single_value_draws_nothing(restored_numpy_state):
    np.random.seed(0)
    before = np.random.get_state()[2]
    key, position = global_stream()
    out = np.empty(8, dtype=np.int64)
    random_integers(key, position, 4, 5, out)
    assert (out == 4).all() and np.random.get_state()[2] == before


def test_a_generator_that_is_not_a_mersenne_twister_has_no_stream():
    original = np.random.get_bit_generator()
    np.random.set_bit_generator(np.random.PCG64(0))
    try:
        assert global_stream() is None
    finally:
        np.random.set_bit_generator(original)
    assert global_stream() is not None


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1), calls=st.lists(st.tuples(st.integers(0, 2), st.integers(1, 2**32 - 1)), max_size=40)
)
def test_compiled_pcg64_integers_are_a_generators_and_leave_its_state(seed, calls):
    """``pcg64_integer`` draws ``Generator.integers(n)`` bit for bit, interleaved with numpy's own draws of the same
    generator (floats and 64-bit integers move its buffered half), and leaves the state numpy would."""
    compiled, reference = np.random.default_rng(seed), np.random.default_rng(seed)
    for kind, n in calls:
        if kind == 0:
            words = pcg64_words(compiled)
            drawn = pcg64_integer(words, n)
            set_pcg64_words(compiled, words)
            assert drawn == reference.integers(n)
        elif kind == 1:
            assert compiled.random() == reference.random()
        else:
            assert compiled.integers(2**40) == reference.integers(2**40)
        assert compiled.bit_generator.state == reference.bit_generator.state


def test_a_generator_that_is_not_pcg64_has_no_words():
    assert pcg64_words(np.random.Generator(np.random.MT19937(0))) is None

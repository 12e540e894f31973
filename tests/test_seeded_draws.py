"""MO-Gymnasium's minecart draws its ore from numpy's global generator; wrapped, its seed decides an episode."""

from __future__ import annotations

import mo_gymnasium as mo
import numpy as np

from sb3_sfgpi.cli.gym_domains import make_gym_env
from sb3_sfgpi.common.seeded_draws import SeededMines, with_seeded_draws

MINE = 0  # MO-Gymnasium minecart's action that mines


def mined(env, seed: int) -> np.ndarray:
    """The ore the cart holds after mining five times at the first mine, from ``reset(seed)`` (put there at once)."""
    env.reset(seed=seed)
    minecart = env.unwrapped
    minecart.cart.pos = minecart.mines[0].pos.copy()
    for _ in range(5):
        env.step(MINE)
    return minecart.cart.content.copy()


def test_minecart_draws_ore_from_the_global_generator_and_the_wrapper_from_its_seed():
    raw = mo.make("minecart-v0")
    np.random.seed(1)
    first = mined(raw, seed=0)
    np.random.seed(2)
    assert not np.array_equal(mined(raw, seed=0), first)  # the same seed, other ore: the global generator decided
    wrapped = with_seeded_draws(mo.make("minecart-v0"))
    assert isinstance(wrapped, SeededMines)
    np.random.seed(1)
    first = mined(wrapped, seed=0)
    np.random.seed(2)
    assert np.array_equal(mined(wrapped, seed=0), first)  # the seed decides
    assert not np.array_equal(mined(wrapped, seed=1), first)  # and still draws: another seed, other ore
    state = np.random.get_state()[1].copy()
    mined(wrapped, seed=0)
    assert np.array_equal(np.random.get_state()[1], state)  # the learners' global stream untouched


def test_only_minecart_is_wrapped_and_the_command_lines_envs_are():
    dst = mo.make("deep-sea-treasure-v0")
    assert with_seeded_draws(dst) is dst
    assert isinstance(make_gym_env("minecart-v0").env, SeededMines)

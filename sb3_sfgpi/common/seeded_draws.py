"""MO-Gymnasium envs whose episodes their seed does not decide, made to draw from their own generator.

A seeded ``reset`` must decide an episode: GPI's evaluation gives each test weight's episodes their own seeds, and
validation compares policy sets on the same seeds (common random numbers). MO-Gymnasium 1.3's minecart breaks this:
its mines draw ore with scipy's ``rvs()`` without a ``random_state``, that is from numpy's global generator, which
the learners draw from too. :func:`with_seeded_draws` wraps such envs (others are returned as they are).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym


class SeededMines(gym.Wrapper):
    """
    MO-Gymnasium's minecart with every mine's ore drawn from the env's own ``np_random``, which ``reset(seed)``
    seeds: the same ore distributions, drawn from a stream the seed decides.
    """

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        result = self.env.reset(seed=seed, options=options)
        minecart = self.env.unwrapped
        for mine in minecart.mines:  # type: ignore[attr-defined]
            for distribution in mine.distributions:
                distribution.random_state = minecart.np_random
        return result


def with_seeded_draws(env: gym.Env) -> gym.Env:
    """``env``, wrapped where its episodes draw from numpy's global generator (MO-Gymnasium's minecart)."""
    unwrapped = env.unwrapped
    minecart = type(unwrapped).__name__ == "Minecart" and type(unwrapped).__module__.startswith("mo_gymnasium")
    return SeededMines(env) if minecart else env

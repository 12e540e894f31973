"""Minecart's reference front with the trip home without ore that the env itself can drive.

MO-Gymnasium's ``convex_coverage_set(γ)`` of minecart prices every trip from a model of the cart's dynamics. Its
trip without ore, (0, 0, −0.249) at γ 0.98 (accelerate, idle, turn around, idle), does not bring the env's cart
home, so the set promises a point no policy reaches and every score against it is too low. :func:`cheapest_empty_trip`
finds the cheapest such trip by exhaustive search of the env itself, and :func:`convex_coverage_set` is MO-Gymnasium's
set with that trip in place of its own. Its trips with ore stay the model's: they are too long to search, and whether
they are optimal is not known (on minecart-v0 the deep preset's runs beat them on every seed; on
minecart-deterministic its ore trips stay below them).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import mo_gymnasium as mo
import numpy as np
from mo_gymnasium.envs.minecart.minecart import ACT_ACCEL, ACT_BRAKE, ACT_LEFT, ACT_NONE, ACT_RIGHT, FUEL_IDLE

MOVES = (ACT_LEFT, ACT_RIGHT, ACT_ACCEL, ACT_BRAKE, ACT_NONE)  # mining is of no use on a trip without ore
CartState = tuple[float, float, float, float, bool]  # x, y, speed, angle, departed


@dataclass(frozen=True)
class Trip:
    """A trip from the base back to it: its discounted fuel and its actions."""

    fuel: float
    actions: tuple[int, ...]


@functools.cache
def cheapest_empty_trip(env_id: str, gamma: float, max_steps: int = 50) -> Trip:
    """The trip home without ore of least discounted fuel, by breadth-first search over every sequence of ``MOVES``
    in the env ``env_id`` (about 234,000 env steps, 12 s; cached).

    Sequences that reach the same cart state at the same step are merged (the cheaper one is kept: what follows costs
    both the same); a branch is cut where one more step of idle fuel alone makes it no cheaper than the best trip
    found, which ends the search, since every step costs idle fuel.

    :param env_id: a MO-Gymnasium minecart env's id
    :param gamma: the discount of the fuel
    :param max_steps: the longest trip searched
    :return: the cheapest trip
    :raises ValueError: where no trip comes home within ``max_steps`` steps
    """
    minecart = mo.make(env_id).unwrapped
    minecart.reset(seed=0)
    idle = FUEL_IDLE * minecart.frame_skip  # the fuel of every step (negative)
    best = Trip(-np.inf, ())
    frontier: dict[CartState, Trip] = {_state(minecart.cart): Trip(0.0, ())}
    for step in range(max_steps):
        reached: dict[CartState, Trip] = {}
        for state, trip in frontier.items():
            for action in MOVES:
                after, fuel, home = _move(minecart, state, action)
                extended = Trip(trip.fuel + gamma**step * fuel, trip.actions + (action,))
                if home:
                    best = max(best, extended, key=lambda candidate: candidate.fuel)
                elif after not in reached or reached[after].fuel < extended.fuel:
                    reached[after] = extended
        frontier = {
            state: trip for state, trip in reached.items() if trip.fuel + idle * gamma ** (step + 1) > best.fuel
        }
        if not frontier and best.actions:
            return best
    raise ValueError(f"no trip brings the cart home without ore within {max_steps} steps")


def _state(cart: Any) -> CartState:
    return float(cart.pos[0]), float(cart.pos[1]), float(cart.speed), float(cart.angle), bool(cart.departed)


def _move(minecart: Any, state: CartState, action: int) -> tuple[CartState, float, bool]:
    """The cart's state after ``action`` from ``state``, the step's fuel and whether it came home."""
    cart = minecart.cart
    cart.pos = np.array(state[:2])
    cart.speed, cart.angle, cart.departed = state[2:]
    minecart.end = False
    _, reward, home, _, _ = minecart.step(action)
    return _state(cart), float(reward[-1]), bool(home)


def convex_coverage_set(env: Any, gamma: float) -> np.ndarray:
    """MO-Gymnasium's CCS of a minecart env, its trips without ore replaced by :func:`cheapest_empty_trip`.

    :return: one row per point, the fuel last
    """
    front = np.array(env.unwrapped.convex_coverage_set(gamma), dtype=float)
    without_ore = (front[:, :-1] == 0).all(axis=1)
    trip = np.zeros(front.shape[1])
    trip[-1] = cheapest_empty_trip(env.unwrapped.spec.id, gamma).fuel
    return np.vstack([front[~without_ore], trip])

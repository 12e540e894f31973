"""Minecart's reference front, searched in the env itself: every trip in it is one the env's cart drives.

MO-Gymnasium's ``convex_coverage_set(γ)`` of minecart prices trips from a model of the cart's dynamics that the env
does not follow: its trip without ore, (0, 0, −0.249) at γ 0.98, does not bring the env's cart home; the actions it
prices for its trips with ore, replayed in the env, turn the wrong way (those to the ore-1 mine mine ore 2) or do not
come home in their steps (those to the corner mine); and the env brings a full cart home in 14 steps where the
model's fastest takes 16. So the reference is searched in the env:

* :func:`cheapest_empty_trip`: the cheapest trip home without ore, exhaustively (branch and bound).
* :func:`ore_trips`: for every mine and number of mining actions, the trips of fewest steps for their fuel (more
  steps discount the ore; more fuel is worse for every weight), exhaustive over the trips that drive to one mine in
  at most ``outbound_steps`` steps, stop, mine, and drive home in at most ``return_steps``: equal cart states met at
  the same step are merged, and a branch is cut only where a bound shows a found trip no worse for every weight.
* :func:`searched_front`: the value vectors of both. Every point is driven, so its EU* is at most the true one; a
  run's EU/EU* exceeds 1 only with a trip outside the search (longer legs, two mines) or, on minecart-v0, by its
  draws of ore.

Ore is priced at the mines' means, as MO-Gymnasium prices it: exact on minecart-deterministic-v0, the expected ore
on minecart-v0 but for the cap at zero of its draws.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import mo_gymnasium as mo
import numpy as np
from mo_gymnasium.envs.minecart.minecart import (
    ACCELERATION,
    ACT_ACCEL,
    ACT_BRAKE,
    ACT_LEFT,
    ACT_MINE,
    ACT_NONE,
    ACT_RIGHT,
    BASE_RADIUS,
    BASE_SCALE,
    CART_SCALE,
    EPS_SPEED,
    FUEL_ACC,
    FUEL_IDLE,
    MINE_RADIUS,
    MINE_SCALE,
)

MOVES = (ACT_LEFT, ACT_RIGHT, ACT_ACCEL, ACT_BRAKE, ACT_NONE)  # every action but mining
CartState = tuple[float, float, float, float, bool]  # x, y, speed, angle, departed
#: The longest legs :func:`ore_trips` searches by default: EU* on minecart-deterministic's 50 test weights grows by
#: 0.001 from 8 + 10 to 9 + 11 steps (the experiments page has the search's convergence).
OUTBOUND_STEPS, RETURN_STEPS = 9, 11
_HOME, _MINE = BASE_RADIUS * BASE_SCALE, MINE_RADIUS * MINE_SCALE * CART_SCALE  # the env's radii of arrival


@dataclass(frozen=True)
class Trip:
    """A trip from the base back to it: its discounted fuel, its actions and the ore it brings home."""

    fuel: float
    actions: tuple[int, ...]
    ore: tuple[float, ...] = ()  # each type's amount on arrival, undiscounted; () for none

    def then(self, action: int, fuel: float, gamma: float) -> Trip:
        """The trip with ``action`` after it, its ``fuel`` discounted by the step it comes at."""
        return Trip(self.fuel + gamma ** len(self.actions) * fuel, self.actions + (action,))

    def value(self, gamma: float, n_ores: int) -> np.ndarray:
        """The trip's discounted return: each ore on its last step, then the fuel."""
        ore = np.zeros(n_ores) if not self.ore else np.array(self.ore) * gamma ** (len(self.actions) - 1)
        return np.append(ore, self.fuel)


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
    minecart = _made(env_id)
    idle = FUEL_IDLE * minecart.frame_skip  # the fuel of every step (negative)
    best = Trip(-np.inf, ())
    frontier: dict[CartState, Trip] = {_state(minecart.cart): Trip(0.0, ())}
    for step in range(max_steps):
        reached: dict[CartState, Trip] = {}
        for state, trip in frontier.items():
            for action in MOVES:
                after, fuel, home = _move(minecart, state, action)
                extended = trip.then(action, fuel, gamma)
                if home:
                    best = max(best, extended, key=lambda candidate: candidate.fuel)
                else:
                    _keep_cheaper(reached, after, extended)
        frontier = {
            state: trip for state, trip in reached.items() if trip.fuel + idle * gamma ** (step + 1) > best.fuel
        }
        if not frontier and best.actions:
            return best
    raise ValueError(f"no trip brings the cart home without ore within {max_steps} steps")


@functools.cache
def ore_trips(
    env_id: str, gamma: float, outbound_steps: int = OUTBOUND_STEPS, return_steps: int = RETURN_STEPS
) -> tuple[Trip, ...]:
    """For every mine and number of mining actions, the trips no other drives in fewer steps for as much fuel
    (searched as the module says; cached; minutes at the default legs).

    :param env_id: a MO-Gymnasium minecart env's id
    :param gamma: the discount of the fuel and the ore
    :param outbound_steps: the longest drive to a mine, its stop included
    :param return_steps: the longest drive home after mining
    :return: the trips, each mine's in turn
    """
    minecart = _made(env_id)
    base, trips = _state(minecart.cart), []
    _, mining_fuel, _ = _move(minecart, (0.5, 0.5, 1.0, 0.0, True), ACT_MINE)  # read off a moving cart: no draw
    for mine in minecart.mines:
        stops = _stops(minecart, base, mine.pos, gamma, outbound_steps)
        per_action = np.asarray(mine.distribution_means()) * minecart.frame_skip
        for mining in range(1, math.ceil(minecart.capacity / per_action.sum()) + 1):
            ore = per_action * mining * min(1.0, minecart.capacity / (per_action.sum() * mining))
            front: list[Trip] = []
            for stop, state in stops:
                mined = _mined(stop, mining, mining_fuel, gamma)
                if not _dominated(front, *_bound_home(minecart, state, len(mined.actions), mined.fuel, gamma)):
                    front = _drives_home(minecart, state, mined, gamma, return_steps, front)
            trips += [Trip(trip.fuel, trip.actions, tuple(ore.tolist())) for trip in front]
    return tuple(trips)


def searched_front(
    env: Any, gamma: float, outbound_steps: int = OUTBOUND_STEPS, return_steps: int = RETURN_STEPS
) -> np.ndarray:
    """The value vectors of a minecart env's :func:`ore_trips` and :func:`cheapest_empty_trip`: every point driven.

    :return: one row per trip, the fuel last
    """
    env_id, n_ores = env.unwrapped.spec.id, env.unwrapped.ore_cnt
    trips = ore_trips(env_id, gamma, outbound_steps, return_steps) + (cheapest_empty_trip(env_id, gamma),)
    return np.array([trip.value(gamma, n_ores) for trip in trips])


def _stops(
    minecart: Any, base: CartState, mine: np.ndarray, gamma: float, max_steps: int
) -> list[tuple[Trip, CartState]]:
    """Every drive from ``base`` that brakes within reach of ``mine`` in at most ``max_steps`` steps, merged where
    equal cart states meet at the same step; fewest steps first, then the cheapest."""
    frontier: dict[CartState, Trip] = {base: Trip(0.0, ())}
    stops: list[tuple[Trip, CartState]] = []
    for step in range(max_steps):
        reached: dict[CartState, Trip] = {}
        for state, trip in frontier.items():
            for action in MOVES:
                after, fuel, home = _move(minecart, state, action)
                extended, gap = trip.then(action, fuel, gamma), _gap(after, mine, _MINE)
                if home:
                    continue
                if action == ACT_BRAKE and gap <= 0:
                    stops.append((extended, after))
                elif _fewest_steps(after[2], gap, minecart.frame_skip) <= max_steps - step - 2:
                    _keep_cheaper(reached, after, extended)  # it can still move within reach and brake there
        frontier = reached
    return sorted(stops, key=lambda stop: (len(stop[0].actions), -stop[0].fuel))


def _mined(trip: Trip, mining: int, fuel: float, gamma: float) -> Trip:
    """``trip`` followed by ``mining`` mining actions of ``fuel`` each."""
    for _ in range(mining):
        trip = trip.then(ACT_MINE, fuel, gamma)
    return trip


def _drives_home(
    minecart: Any, start: CartState, trip: Trip, gamma: float, max_steps: int, front: list[Trip]
) -> list[Trip]:
    """``front`` with every drive home from ``start`` within ``max_steps`` steps that it does not dominate; branches
    that :func:`_bound_home` shows dominated are cut."""
    frontier: dict[CartState, Trip] = {start: trip}
    for _ in range(max_steps):
        reached: dict[CartState, Trip] = {}
        for state, so_far in frontier.items():
            step = len(so_far.actions)
            for action in MOVES:
                after, fuel, home = _move(minecart, state, action)
                extended = so_far.then(action, fuel, gamma)
                if home:
                    front = _with(front, extended)
                    continue
                steps, most_fuel = _bound_home(minecart, after, step + 1, extended.fuel, gamma)
                if steps <= len(trip.actions) + max_steps and not _dominated(front, steps, most_fuel):
                    _keep_cheaper(reached, after, extended)
        frontier = reached
    return front


def _bound_home(minecart: Any, state: CartState, step: int, fuel: float, gamma: float) -> tuple[int, float]:
    """At least how many steps a trip at ``state`` after ``step`` steps takes in all, and at most how much fuel it
    ends with: the fewest steps home in a straight line, each costing idle fuel, and an acceleration to set off where
    the cart stands (at the last of those steps: later ones cost more idle fuel than the acceleration's discount
    saves)."""
    n = max(1, _fewest_steps(state[2], _gap(state, np.zeros(2), _HOME), minecart.frame_skip))
    idle = FUEL_IDLE * minecart.frame_skip * sum(gamma ** (step + j) for j in range(n))
    setting_off = FUEL_ACC * minecart.frame_skip * gamma ** (step + n - 1) if state[2] < EPS_SPEED else 0.0
    return step + n, fuel + idle + setting_off


def _keep_cheaper(reached: dict[CartState, Trip], state: CartState, trip: Trip) -> None:
    """``trip`` in ``reached`` at ``state`` unless a trip there already has as much fuel left (what follows costs
    both the same)."""
    if state not in reached or reached[state].fuel < trip.fuel:
        reached[state] = trip


def _dominated(front: list[Trip], steps: int, fuel: float) -> bool:
    """Whether a trip of ``front`` takes at most ``steps`` steps with at least ``fuel``."""
    return any(len(trip.actions) <= steps and trip.fuel >= fuel for trip in front)


def _with(front: list[Trip], trip: Trip) -> list[Trip]:
    """``front`` with ``trip`` unless dominated, less the trips it dominates."""
    if _dominated(front, len(trip.actions), trip.fuel):
        return front
    return [kept for kept in front if not _dominated([trip], len(kept.actions), kept.fuel)] + [trip]


def _fewest_steps(speed: float, gap: float, frames: int) -> int:
    """The fewest steps of ``frames`` frames that can cover ``gap`` from ``speed``: in a straight line, accelerating
    at every frame (walls and the top speed only shorten it)."""
    steps = 0
    while gap > frames * steps * speed + ACCELERATION * frames * steps * (frames * steps + 1) / 2:
        steps += 1
    return steps


def _gap(state: CartState, centre: np.ndarray, radius: float) -> float:
    return math.hypot(state[0] - centre[0], state[1] - centre[1]) - radius


def _made(env_id: str) -> Any:
    minecart = mo.make(env_id).unwrapped
    minecart.reset(seed=0)
    return minecart


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

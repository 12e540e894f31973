"""Minecart's reference front: the searched trip home without ore is one the env drives, at the fuel the search
states; MO-Gymnasium's own is cheaper than any the env drives; the corrected set changes that point alone."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

mo = pytest.importorskip("mo_gymnasium")
if str(Path(__file__).resolve().parents[1]) not in sys.path:  # the benchmarks are not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.minecart_reference import MOVES, _move, _state, cheapest_empty_trip, convex_coverage_set  # noqa: E402

ENV_ID, GAMMA = "minecart-deterministic-v0", 0.98


def _drive(actions: tuple[int, ...]) -> tuple[int | None, np.ndarray]:
    """The step at which the cart came home (None: it did not) and the discounted return of ``actions``."""
    env = mo.make(ENV_ID)
    env.reset(seed=0)
    discounted = np.zeros(3)
    for step, action in enumerate(actions):
        _, reward, home, _, _ = env.step(action)
        discounted += GAMMA**step * reward.astype(float)
        if home:
            return step, discounted
    return None, discounted


def test_the_cheapest_trip_without_ore_is_driven_by_the_env_at_its_stated_fuel():
    trip = cheapest_empty_trip(ENV_ID, GAMMA)
    home_at, discounted = _drive(trip.actions)
    assert home_at == len(trip.actions) - 1  # home on its last action, not before
    assert discounted[:2].tolist() == [0.0, 0.0] and discounted[2] == pytest.approx(trip.fuel, abs=1e-12)
    assert trip.fuel == pytest.approx(-0.2809, abs=1e-4)  # turn, accelerate, turn back: 10 steps
    assert cheapest_empty_trip("minecart-v0", GAMMA) == trip  # the ore's randomness plays no part without ore


def test_mo_gymnasiums_trip_without_ore_is_cheaper_than_any_the_env_drives():
    """Its model's point (0, 0, -0.249) lies above the cheapest trip: a promise no policy keeps."""
    front = np.array(mo.make(ENV_ID).unwrapped.convex_coverage_set(GAMMA))
    modelled = front[(front[:, :2] == 0).all(axis=1), 2]
    assert modelled.shape == (1,) and modelled[0] > cheapest_empty_trip(ENV_ID, GAMMA).fuel + 0.03


def test_the_corrected_set_replaces_the_trip_without_ore_and_keeps_every_trip_with_ore():
    env = mo.make(ENV_ID)
    front, corrected = np.array(env.unwrapped.convex_coverage_set(GAMMA)), convex_coverage_set(env, GAMMA)
    with_ore = (front[:, :2] != 0).any(axis=1)
    assert corrected.shape == front.shape
    assert np.array_equal(corrected[:-1], front[with_ore].astype(float))
    assert corrected[-1].tolist() == [0.0, 0.0, cheapest_empty_trip(ENV_ID, GAMMA).fuel]


def test_a_search_too_short_for_any_trip_home_says_so():
    with pytest.raises(ValueError, match="within 5 steps"):
        cheapest_empty_trip(ENV_ID, GAMMA, max_steps=5)


@pytest.mark.slow
def test_no_trip_home_within_as_many_steps_is_cheaper_with_no_branch_cut():
    """Every cart state reachable in up to the trip's length of steps (merged, nothing cut): none comes home cheaper.
    (Longer trips cost more in idle fuel and one acceleration alone: 1 - 0.88 · 0.98^(n-1) > 0.2809 for n ≥ 12.)"""
    trip = cheapest_empty_trip(ENV_ID, GAMMA)
    minecart = mo.make(ENV_ID).unwrapped
    minecart.reset(seed=0)
    frontier, cheapest = {_state(minecart.cart): 0.0}, -np.inf
    for step in range(len(trip.actions) + 1):
        reached: dict = {}
        for state, fuel in frontier.items():
            for action in MOVES:
                after, cost, home = _move(minecart, state, action)
                if home:
                    cheapest = max(cheapest, fuel + GAMMA**step * cost)
                else:
                    reached[after] = max(reached.get(after, -np.inf), fuel + GAMMA**step * cost)
        frontier = reached
    assert cheapest == pytest.approx(trip.fuel, abs=1e-12)
    assert 1 - 0.88 * GAMMA**11 > -trip.fuel

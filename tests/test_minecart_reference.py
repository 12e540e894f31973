"""Minecart's reference front, searched in the env: every trip in it is driven by the env at the value it states, the
search's cuts lose no trip an uncut search finds, and MO-Gymnasium's modelled front disagrees with the env both ways."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

mo = pytest.importorskip("mo_gymnasium")
if str(Path(__file__).resolve().parents[1]) not in sys.path:  # the benchmarks are not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.minecart_reference import (  # noqa: E402
    ACT_BRAKE,
    ACT_MINE,
    ACT_NONE,
    MOVES,
    Trip,
    _move,
    _state,
    cheapest_empty_trip,
    ore_trips,
    searched_front,
)

ENV_ID, GAMMA = "minecart-deterministic-v0", 0.98
SHORT = (6, 8)  # legs short enough for the default run: 12 trips, a few seconds


def _drive(actions: tuple[int, ...], env_id: str = ENV_ID) -> tuple[int | None, np.ndarray]:
    """The step at which the cart came home (None: it did not) and the discounted return of ``actions``."""
    env = mo.make(env_id)
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


def test_every_ore_trip_is_driven_by_the_env_at_its_stated_value():
    trips = ore_trips(ENV_ID, GAMMA, *SHORT)
    assert len(trips) == 12  # a front of (steps, fuel) for each of the 5 mines and each count of mining actions
    for trip in trips:
        home_at, discounted = _drive(trip.actions)
        assert home_at == len(trip.actions) - 1
        assert discounted == pytest.approx(trip.value(GAMMA, 2), abs=1e-6)  # the env's rewards are float32


def test_minecart_v0s_trips_are_the_same_drives_with_its_mines_mean_ore():
    deterministic, stochastic = ore_trips(ENV_ID, GAMMA, *SHORT), ore_trips("minecart-v0", GAMMA, *SHORT)
    assert [(trip.actions, trip.fuel) for trip in stochastic] == [(trip.actions, trip.fuel) for trip in deterministic]
    env = mo.make("minecart-v0")
    for trip in stochastic:  # its fuel is the env's; its ore the mines' means (the draws are random)
        assert _drive(trip.actions, "minecart-v0")[1][2] == pytest.approx(trip.fuel, abs=1e-6)
    per_action = [np.asarray(mine.distribution_means()) * 4 for mine in env.unwrapped.mines]  # 4 frames an action
    loads = {tuple(np.round(ore * k * min(1, 1.5 / (ore.sum() * k)), 9)) for ore in per_action for k in (1, 2)}
    assert {tuple(np.round(trip.ore, 9)) for trip in stochastic} <= loads  # a cart holds 1.5


def test_each_trip_is_the_fastest_for_its_fuel_among_its_mines_and_mining_actions():
    trips = ore_trips(ENV_ID, GAMMA, *SHORT)
    for trip in trips:
        rivals = [other for other in trips if other.ore == trip.ore and other is not trip]
        assert not any(len(o.actions) <= len(trip.actions) and o.fuel >= trip.fuel for o in rivals)


def test_the_env_brings_a_full_cart_home_sooner_than_mo_gymnasiums_model_prices():
    """The model's fastest full cart of one ore arrives on step 16 (1.5 · 0.98^15); the env drives one home on 15."""
    modelled = np.array(mo.make(ENV_ID).unwrapped.convex_coverage_set(GAMMA))
    assert modelled[:, 0].max() == pytest.approx(1.5 * GAMMA**15)
    assert max(trip.value(GAMMA, 2)[0] for trip in ore_trips(ENV_ID, GAMMA, *SHORT)) == pytest.approx(1.5 * GAMMA**14)


def test_the_searched_front_holds_every_ore_trip_and_the_trip_without_ore():
    env = mo.make(ENV_ID)
    front = searched_front(env, GAMMA, *SHORT)
    trips = ore_trips(ENV_ID, GAMMA, *SHORT) + (cheapest_empty_trip(ENV_ID, GAMMA),)
    assert np.array_equal(front, np.array([trip.value(GAMMA, 2) for trip in trips]))
    assert Trip(-0.5, (3,)).value(GAMMA, 2).tolist() == [0.0, 0.0, -0.5]


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


def _uncut_trips(outbound_steps: int, return_steps: int) -> dict[tuple[float, ...], list[tuple[int, float]]]:
    """Each ore load's front of (steps, fuel), from every drive to a mine and back within the legs: equal cart states
    merged, nothing cut, the ore and the mining's fuel as the env gives them."""
    minecart = mo.make(ENV_ID).unwrapped
    minecart.reset(seed=0)
    stops, frontier = [], {_state(minecart.cart): 0.0}
    for step in range(outbound_steps):
        reached: dict = {}
        for state, fuel in frontier.items():
            for action in MOVES:
                after, cost, home = _move(minecart, state, action)
                if action == ACT_BRAKE and any(mine.mineable(minecart.cart) for mine in minecart.mines):
                    stops.append((step + 1, fuel + GAMMA**step * cost, after))
                elif not home:
                    reached[after] = max(reached.get(after, -np.inf), fuel + GAMMA**step * cost)
        frontier = reached
    loads: dict[tuple[float, ...], list[tuple[int, float]]] = {}
    for out_steps, out_fuel, stop in stops:
        home = _drives_home_uncut(minecart, stop, return_steps)
        _move(minecart, stop, ACT_NONE)
        minecart.cart.content = np.zeros(2)
        fuel = out_fuel
        for mining in range(1, 3):
            fuel += GAMMA ** (out_steps + mining - 1) * float(minecart.step(ACT_MINE)[1][2])
            ore = tuple(np.round(minecart.cart.content, 9))
            for back_steps, back_fuel in home:
                start = out_steps + mining
                loads.setdefault(ore, []).append((start + back_steps, fuel + GAMMA**start * back_fuel))
    return {ore: _pareto(trips) for ore, trips in loads.items()}


def _drives_home_uncut(minecart, start, max_steps: int) -> list[tuple[int, float]]:
    frontier, home = {start: 0.0}, []
    for step in range(max_steps):
        reached: dict = {}
        for state, fuel in frontier.items():
            for action in MOVES:
                after, cost, at_base = _move(minecart, state, action)
                if at_base:
                    home.append((step + 1, fuel + GAMMA**step * cost))
                else:
                    reached[after] = max(reached.get(after, -np.inf), fuel + GAMMA**step * cost)
        frontier = reached
    return home


def _pareto(trips: list[tuple[int, float]]) -> list[tuple[int, float]]:
    """The trips no other makes in as few steps with as much fuel, fewest steps first."""
    kept, most = [], -np.inf
    for steps, fuel in sorted(trips, key=lambda trip: (trip[0], -trip[1])):
        if fuel > most + 1e-9:
            kept.append((steps, fuel))
            most = fuel
    return kept


@pytest.mark.slow
def test_the_searchs_cuts_lose_no_trip_that_an_uncut_search_of_the_same_legs_finds():
    legs = SHORT
    searched: dict[tuple[float, ...], list[tuple[int, float]]] = {}
    for trip in ore_trips(ENV_ID, GAMMA, *legs):
        searched.setdefault(tuple(np.round(trip.ore, 9)), []).append((len(trip.actions), trip.fuel))
    uncut = _uncut_trips(*legs)
    assert searched.keys() == uncut.keys() and len(searched) == 8  # two loads at each outer mine, none at the corner
    for ore, trips in searched.items():
        assert [steps for steps, _ in sorted(trips)] == [steps for steps, _ in uncut[ore]]
        assert [fuel for _, fuel in sorted(trips)] == pytest.approx([fuel for _, fuel in uncut[ore]], abs=1e-9)

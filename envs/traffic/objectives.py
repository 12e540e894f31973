"""The objectives a traffic light can be rewarded on, one reward component each.

Every component is measured at the light's own intersection from two consecutive
:class:`~.monitor.Measurement` values (the previous decision and this one), handed over in a
:class:`~.hooks.LightView`, so that a larger reward is always better. A user's own objective is an
:class:`Objective` with a picklable ``reward(view)``, given in ``objectives=[...]`` beside the menu's names:

==========================  ==========================================================================  =========
name                        reward of a decision step                                                   unit
==========================  ==========================================================================  =========
``"vehicle_waiting"``       decrease of the waiting time of the vehicles on the incoming lanes          s
                            (paper Eq. 24)
``"pedestrian_waiting"``    decrease of the waiting time of the pedestrians on the approach of          s
                            the crossings (paper Eq. 25); needs signalised crossings
``"vehicle_delay"``         minus the waiting time the vehicles spent at the intersection during the    s
                            step, those that left during it included (summed over an episode: minus
                            the total that ``vehicle_waiting_time_mean`` averages)
``"pedestrian_delay"``      the same for the pedestrians on the approach of the crossings               s
``"vehicle_queue"``         minus the vehicles halting (below 0.1 m/s) on the incoming lanes            vehicles
                            (sumo-rl's ``queue`` reward)
``"co2"``                   minus the CO2 the vehicles on the incoming lanes emitted during the         g
                            step (SUMO's default emission model)
==========================  ==========================================================================  =========
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .hooks import LightView, check_picklable


@dataclass(frozen=True)
class Objective:
    """One reward component: one of the menu's, or a user's own.

    :param name: the name ``objectives=[...]`` takes (distinct among the env's objectives).
    :param label: what it measures, with the unit, for output and axes.
    :param reward: ``view -> reward`` of a decision step, from the light's :class:`~.hooks.LightView` (its previous
        and current :class:`~.monitor.Measurement`, and the SUMO API for anything else); larger is better. It must
        pickle (a module-level function, or a ``functools.partial`` of one).
    :param needs_pedestrians: only meaningful where the network has signalised crossings.
    """

    name: str
    label: str
    reward: Callable[[LightView], float]
    needs_pedestrians: bool = False


def vehicle_waiting(light: LightView) -> float:
    """Decrease of the waiting time of the vehicles on the incoming lanes (paper Eq. 24)."""
    return light.previous.vehicle_wait - light.current.vehicle_wait


def pedestrian_waiting(light: LightView) -> float:
    """Decrease of the waiting time of the pedestrians on the approach (paper Eq. 25)."""
    return light.previous.pedestrian_wait - light.current.pedestrian_wait


def vehicle_delay(light: LightView) -> float:
    """Minus the waiting time the vehicles spent at the intersection during the step."""
    return light.previous.vehicle_wait_episode - light.current.vehicle_wait_episode


def pedestrian_delay(light: LightView) -> float:
    """Minus the waiting time the pedestrians spent on the approach during the step."""
    return light.previous.pedestrian_wait_episode - light.current.pedestrian_wait_episode


def vehicle_queue(light: LightView) -> float:
    """Minus the halting vehicles on the incoming lanes."""
    return -float(light.current.halting)


def co2(light: LightView) -> float:
    """Minus the CO2 [g] the vehicles on the incoming lanes emitted during the step."""
    return (light.previous.co2_mg - light.current.co2_mg) / 1000.0


MENU: dict[str, Objective] = {
    o.name: o
    for o in (
        Objective("vehicle_waiting", "vehicle waiting [s]", vehicle_waiting),
        Objective("pedestrian_waiting", "pedestrian waiting [s]", pedestrian_waiting, needs_pedestrians=True),
        Objective("vehicle_delay", "vehicle waiting [s]", vehicle_delay),
        Objective("pedestrian_delay", "pedestrian waiting [s]", pedestrian_delay, needs_pedestrians=True),
        Objective("vehicle_queue", "halting vehicles", vehicle_queue),
        Objective("co2", "CO2 emitted [g]", co2),
    )
}
"""The objectives on offer, by name."""

DEFAULT_OBJECTIVES = ("vehicle_waiting", "pedestrian_waiting")
"""The paper's objectives (Sec. 5.2)."""


def select_objectives(items: Any) -> tuple[Objective, ...]:
    """The objectives given, in order.

    :param items: a sequence of at least one menu name or :class:`Objective` (a user's own), names distinct.
    :return: the objectives.
    :raises ValueError: a name not on the menu, something that is neither, a repeated name, an objective whose
        reward does not pickle, or nothing at all.
    """
    if isinstance(items, str) or not isinstance(items, Sequence) or not items:
        raise ValueError(
            f"objectives must be a non-empty list of names from {list(MENU)} or Objective(...)s, got {items!r}"
        )
    objectives = tuple(_objective(item) for item in items)
    names = [o.name for o in objectives]
    if len(set(names)) != len(names):
        raise ValueError(f"objectives must have distinct names, got {names}")
    return objectives


def _objective(item: Any) -> Objective:
    if isinstance(item, Objective):
        if not callable(item.reward):
            raise ValueError(f"objective {item.name!r}: reward must be a callable of a LightView, got {item.reward!r}")
        check_picklable(item.reward, f"the reward of objective {item.name!r}")
        return item
    if isinstance(item, str) and item in MENU:
        return MENU[item]
    if isinstance(item, str):
        raise ValueError(f"unknown objective {item!r}; the menu: {', '.join(MENU)}")
    raise ValueError(
        f"an objective is a menu name ({', '.join(MENU)}) or an Objective(name, label, reward), got {item!r}"
    )


def reward_scales(scale: Any, names: Sequence[str]) -> np.ndarray:
    """One positive finite factor per objective.

    :param scale: one number for all, one per objective (in order), or a mapping name -> factor (objectives it
        does not name keep 1; names of the menu that are not selected are ignored; a user's objective is named as
        its ``Objective``).
    :param names: the selected objectives' names.
    :return: the factors, float64 of shape ``(len(names),)``.
    :raises ValueError: a factor that is not a positive finite number, a wrong length, a name neither on the menu
        nor selected.
    """
    if isinstance(scale, Mapping):
        unknown = [k for k in scale if k not in MENU and k not in names]
        if unknown:
            raise ValueError(
                f"reward_scale names an unknown objective {unknown[0]!r}; the menu: {', '.join(MENU)}, and the "
                f"selected: {', '.join(names)}"
            )
        bad = [k for k, v in scale.items() if not _positive_finite(v)]  # every factor given, selected or not
        if bad:
            raise ValueError(f"reward_scale of {bad[0]!r} must be a positive finite number, got {scale[bad[0]]!r}")
        values = [scale.get(n, 1.0) for n in names]
    elif isinstance(scale, (list, tuple, np.ndarray)):
        values = list(scale)
    else:
        values = [scale] * len(names)
    if len(values) != len(names) or not all(map(_positive_finite, values)):
        raise ValueError(
            f"reward_scale must be a positive finite number, {len(names)} of them ({', '.join(names)}) or a mapping "
            f"objective -> factor, got {scale!r}"
        )
    return np.array(values, dtype=np.float64)


def _positive_finite(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float, np.number)) and 0 < value < np.inf

"""The objectives a traffic light can be rewarded on, one reward component each.

Every component is measured at the light's own intersection from two consecutive
:class:`~.monitor.Measurement` values (the previous decision and this one), so that a larger reward is
always better:

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

from .monitor import Measurement


@dataclass(frozen=True)
class Objective:
    """One reward component.

    :param name: the name ``objectives=[...]`` takes.
    :param label: what it measures, with the unit, for output and axes.
    :param reward: ``(previous, current) -> reward`` of a decision step.
    :param needs_pedestrians: only meaningful where the network has signalised crossings.
    """

    name: str
    label: str
    reward: Callable[[Measurement, Measurement], float]
    needs_pedestrians: bool = False


MENU: dict[str, Objective] = {
    o.name: o
    for o in (
        Objective("vehicle_waiting", "vehicle waiting [s]", lambda p, c: p.vehicle_wait - c.vehicle_wait),
        Objective(
            "pedestrian_waiting",
            "pedestrian waiting [s]",
            lambda p, c: p.pedestrian_wait - c.pedestrian_wait,
            needs_pedestrians=True,
        ),
        Objective(
            "vehicle_delay",
            "vehicle waiting [s]",
            lambda p, c: p.vehicle_wait_episode - c.vehicle_wait_episode,
        ),
        Objective(
            "pedestrian_delay",
            "pedestrian waiting [s]",
            lambda p, c: p.pedestrian_wait_episode - c.pedestrian_wait_episode,
            needs_pedestrians=True,
        ),
        Objective("vehicle_queue", "halting vehicles", lambda p, c: -float(c.halting)),
        Objective("co2", "CO2 emitted [g]", lambda p, c: (p.co2_mg - c.co2_mg) / 1000.0),
    )
}
"""The objectives on offer, by name."""

DEFAULT_OBJECTIVES = ("vehicle_waiting", "pedestrian_waiting")
"""The paper's objectives (Sec. 5.2)."""


def select_objectives(names: Any) -> tuple[Objective, ...]:
    """The objectives named, in order.

    :param names: a sequence of at least one distinct name of :data:`MENU`.
    :return: the objectives.
    :raises ValueError: a name not on the menu, a repeated name, or no name at all.
    """
    if isinstance(names, str) or not isinstance(names, Sequence) or not names:
        raise ValueError(f"objectives must be a non-empty list of names from {list(MENU)}, got {names!r}")
    unknown = [n for n in names if n not in MENU]
    if unknown:
        raise ValueError(f"unknown objective {unknown[0]!r}; the menu: {', '.join(MENU)}")
    if len(set(names)) != len(names):
        raise ValueError(f"objectives must be distinct, got {list(names)}")
    return tuple(MENU[n] for n in names)


def reward_scales(scale: Any, names: Sequence[str]) -> np.ndarray:
    """One positive finite factor per objective.

    :param scale: one number for all, one per objective (in order), or a mapping name -> factor (objectives it
        does not name keep 1; names of the menu that are not selected are ignored).
    :param names: the selected objectives' names.
    :return: the factors, float64 of shape ``(len(names),)``.
    :raises ValueError: a factor that is not a positive finite number, a wrong length, an unknown name.
    """
    if isinstance(scale, Mapping):
        unknown = [k for k in scale if k not in MENU]
        if unknown:
            raise ValueError(f"reward_scale names an unknown objective {unknown[0]!r}; the menu: {', '.join(MENU)}")
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

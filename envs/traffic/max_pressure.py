"""Max-pressure signal control (``TrafficSignalEnv(signal_control="max-pressure")``), RESCO's definition.

At every decision each light asks for the green phase of largest *pressure*::

    pressure(phase) = sum over the phase's movements (l_in -> l_out) of  queue(l_in) - queue(l_out)

A *movement* is a pair (incoming lane, outgoing lane) of a link that is green (``G`` or ``g``) in the phase; a pair
served by several links counts once. ``queue`` is the number of halting vehicles on the lane (speed below 0.1 m/s,
SUMO's ``lane.getLastStepHaltingNumber``). Ties go to the green shown, then to the lowest index. Only vehicles
count, as in RESCO's max-pressure (Ault & Sharon 2021): links from pedestrian areas (crossings) are left out, so a
crossing is green only when the phase the vehicles' pressure chooses serves it.

The movements are read from the running simulation (``trafficlight.getControlledLinks``, one entry per link index of
the state strings) and the green phases of the light's static program, so any network the environment accepts runs.

The choice goes through the environment's own phase logic (:class:`~.signals.SignalController`), as an agent's
``action_mode="phase"`` request does: minimum green, ``early_change``, yellow and the transitions are the agents'.
Only the green that follows a green ended by ``max_green`` differs: the agents' controller takes the next one of the
cycle, max-pressure the other green of largest pressure (:meth:`MaxPressure.choose_other`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import partial
from typing import Any

from .signals import SignalController, SignalProgram
from .topology import IntersectionLayout

Movement = tuple[str, str]
"""(incoming lane, outgoing lane)."""


def phase_movements(
    links: Sequence[Sequence[Sequence[str]]], greens: Sequence[str], vehicle_lanes: Sequence[str]
) -> tuple[tuple[Movement, ...], ...]:
    """The vehicle movements each green phase serves.

    :param links: for each link index, its ``(incoming lane, outgoing lane, via lane)`` triples (SUMO's
        ``trafficlight.getControlledLinks``).
    :param greens: the state strings of the green phases (one character per link index).
    :param vehicle_lanes: the incoming vehicle lanes; links from other lanes (pedestrian areas) are left out.
    :return: per green phase, its movements without repetition, in link-index order.
    :raises ValueError: if a state string does not have one character per link.
    """
    vehicles = set(vehicle_lanes)
    result = []
    for state in greens:
        if len(state) != len(links):
            raise ValueError(f"phase state {state!r} has {len(state)} links, the light controls {len(links)}")
        moves = ((t[0], t[1]) for signal, triples in zip(state, links, strict=True) for t in triples if signal in "Gg")
        result.append(tuple(dict.fromkeys(m for m in moves if m[0] in vehicles)))
    return tuple(result)


def phase_pressures(movements: Sequence[Sequence[Movement]], queue: Mapping[str, int]) -> list[int]:
    """Pressure of each phase: the sum over its movements of the incoming lane's queue minus the outgoing lane's.

    :param movements: per phase, its movements (:func:`phase_movements`).
    :param queue: halting vehicles per lane (lanes absent count 0).
    :return: one pressure per phase.
    """
    return [sum(queue.get(src, 0) - queue.get(dst, 0) for src, dst in moves) for moves in movements]


def best_phase(pressures: Sequence[float], current: int, exclude_current: bool = False) -> int:
    """The phase of largest pressure: ties keep ``current``, then go to the lowest index.

    :param pressures: pressure per phase.
    :param current: index of the green shown.
    :param exclude_current: choose among the other phases only (after the maximum green).
    :return: the phase index.
    """
    candidates = [k for k in range(len(pressures)) if not (exclude_current and k == current)]
    best = max(pressures[k] for k in candidates)
    if not exclude_current and pressures[current] == best:
        return current
    return next(k for k in candidates if pressures[k] == best)


class MaxPressure:
    """Max-pressure choice of the green of every light of a running simulation.

    :param api: the libsumo module or TraCI connection.
    :param movements: per light (in agent order), per green phase, its movements (:func:`phase_movements`).
    """

    def __init__(self, api: Any, movements: Sequence[Sequence[Sequence[Movement]]]) -> None:
        self._halting = api.lane.getLastStepHaltingNumber
        self.movements = [tuple(tuple(m) for m in light) for light in movements]
        self._lanes = [sorted({lane for moves in light for m in moves for lane in m}) for light in self.movements]

    @classmethod
    def from_simulation(
        cls,
        api: Any,
        programs: Mapping[str, SignalProgram],
        layouts: Mapping[str, IntersectionLayout],
        controllers: Sequence[SignalController] = (),
    ) -> MaxPressure:
        """Read every light's movements from the simulation's controlled links.

        :param api: the libsumo module or TraCI connection of a loaded simulation.
        :param programs: the green phases of each light (agent order).
        :param layouts: each light's incoming vehicle lanes.
        :param controllers: the lights' controllers (agent order), to :meth:`attach` to.
        :return: the controller.
        """
        links = api.trafficlight.getControlledLinks
        movements = [phase_movements(links(t), prog.greens, layouts[t].vehicle_lanes) for t, prog in programs.items()]
        result = cls(api, movements)
        result.attach(controllers)
        return result

    def pressures(self, i: int) -> list[int]:
        """Pressure of each green phase of light ``i``, from the halting vehicles of the last simulation step."""
        queue = {lane: self._halting(lane) for lane in self._lanes[i]}
        return phase_pressures(self.movements[i], queue)

    def choose(self, i: int, current: int) -> int:
        """The green light ``i`` asks for at a decision (ties keep ``current``)."""
        return best_phase(self.pressures(i), current)

    def choose_other(self, i: int, current: int) -> int:
        """The green that follows green ``current`` of light ``i`` when the maximum green ends it."""
        return best_phase(self.pressures(i), current, exclude_current=True)

    def attach(self, controllers: Sequence[SignalController]) -> None:
        """Make each light's controller end a green at ``max_green`` towards :meth:`choose_other`."""
        for i, ctl in enumerate(controllers):
            ctl.after_max_green = partial(self.choose_other, i)

    def decide(self, controllers: Sequence[SignalController]) -> list[int]:
        """The green each light asks for now (what an agent's ``action_mode="phase"`` action says)."""
        return [self.choose(i, ctl.green) for i, ctl in enumerate(controllers)]

"""What a user's own reward or observation function sees of a traffic light, and sumo-rl's observation.

:class:`TrafficSignalEnv` hands every traffic light's state at a decision to the objectives and to an observation
function as one :class:`LightView`: the two :class:`~.monitor.Measurement` values the reward compares, the green
shown and its age, the lane features of the built-in observation, and the SUMO API for anything else. A user's
objective is an :class:`~.objectives.Objective` whose ``reward`` maps a view to a float; a user's observation
function is an object with ``space(layout, n_greens)`` and ``__call__(view)`` (:class:`ObservationFunction`), as
sumo-rl's ``observation_class``. Both must pickle (a module-level function or class, a ``functools.partial`` of
one): the evaluation workers and the env's copies are built in other processes. :class:`PaddedObservation` gives
lights that differ one layout, so that they share one policy set.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from gymnasium import spaces

from .monitor import Measurement
from .topology import IntersectionLayout


@dataclass(frozen=True)
class LightView:
    """One traffic light at a decision, as the objectives and the observation function see it.

    :param tls_id: the light's id (the agent's).
    :param layout: its incoming lanes, capacities and static program.
    :param previous: the measurement at the previous decision (at ``reset``: the current one).
    :param current: the measurement now.
    :param green: index of the green shown (during yellow: the one that comes next), among ``n_greens``.
    :param n_greens: the light's number of green phases.
    :param green_time: seconds the green has been shown (0 during yellow).
    :param min_green: the env's minimum green [s].
    :param max_green: the env's maximum green [s].
    :param densities: vehicles (persons) on each incoming lane (pedestrian edge) over its capacity, clipped to 1:
        vehicle lanes first, in ``layout.vehicle_lanes`` order, then ``layout.pedestrian_edges``.
    :param queues: the same for the halting vehicles (standing persons).
    :param time: simulation time [s].
    :param sumo: the ``libsumo`` module or the ``traci`` connection, for anything else (read, do not control).
    """

    tls_id: str
    layout: IntersectionLayout
    previous: Measurement
    current: Measurement
    green: int
    n_greens: int
    green_time: float
    min_green: int
    max_green: int
    densities: tuple[float, ...]
    queues: tuple[float, ...]
    time: int
    sumo: Any

    @property
    def tau(self) -> float:
        """The elapsed green over ``max_green``, at most 1."""
        return min(1.0, self.green_time / self.max_green)

    def green_one_hot(self, size: int) -> list[float]:
        """The green shown as a one-hot list of ``size`` (at least ``n_greens``) entries."""
        one_hot = [0.0] * size
        one_hot[self.green] = 1.0
        return one_hot

    def default_observation(self) -> np.ndarray:
        """The env's own observation (Eq. 22): green one-hot, elapsed green over ``max_green``, densities, queues."""
        vec = self.green_one_hot(self.n_greens) + [self.tau]
        return np.array(vec + list(self.densities) + list(self.queues), dtype=np.float32)


@runtime_checkable
class ObservationFunction(Protocol):
    """A user's observation of a traffic light (sumo-rl's ``observation_class``, as one picklable object)."""

    def space(self, layout: IntersectionLayout, n_greens: int) -> spaces.Box:
        """The observation space of a light with ``layout`` and ``n_greens`` green phases."""

    def __call__(self, light: LightView) -> np.ndarray:
        """The observation of ``light`` (an array of :meth:`space`'s shape and dtype)."""


class SumoRLObservation:
    """sumo-rl's default observation: green one-hot, "may change" flag, densities and queues of the vehicle lanes.

    ``[phase_0 .. phase_{G-1}, min_green_passed, density_1 .. density_V, queue_1 .. queue_V]`` over the ``V``
    controlled incoming vehicle lanes (no pedestrian edges), float32 in [0, 1]. The flag is 1 once the green has been
    shown for ``min_green`` seconds (sumo-rl: ``min_green + yellow_time`` since the last change, the same moment).
    """

    def space(self, layout: IntersectionLayout, n_greens: int) -> spaces.Box:
        return spaces.Box(0.0, 1.0, shape=(n_greens + 1 + 2 * len(layout.vehicle_lanes),), dtype=np.float32)

    def __call__(self, light: LightView) -> np.ndarray:
        n = len(light.layout.vehicle_lanes)
        may_change = [1.0 if light.green_time >= light.min_green else 0.0]
        lanes = list(light.densities[:n]) + list(light.queues[:n])
        return np.array(light.green_one_hot(light.n_greens) + may_change + lanes, dtype=np.float32)


def check_picklable(value: Any, what: str) -> None:
    """
    Refuse what cannot be sent to another process.

    :raises ValueError: naming ``what`` and how to make it picklable
    """
    try:
        pickle.dumps(value)
    except (pickle.PicklingError, AttributeError, TypeError) as error:
        raise ValueError(
            f"{what} must be picklable (a module-level function or class, or a functools.partial of one), "
            f"for the evaluation workers and the env's copies: {error}"
        ) from None


@dataclass(frozen=True)
class PaddedObservation:
    """One observation layout for lights that differ, each slot meaning the same thing at every light.

    Lights with different numbers of greens or lanes share one policy set only if an input means the same at all of
    them, so each feature group is padded to the largest light's size on its own (not zeros appended at the end)::

        [green one-hot (G), green exists (G), tau,
         vehicle density (V), vehicle queue (V), vehicle lane exists (V),
         pedestrian density (P), pedestrian queue (P), pedestrian edge exists (P)]

    ``G``, ``V``, ``P``: the most greens, controlled vehicle lanes and pedestrian approach edges of any light;
    absent slots are 0 and their "exists" flag says so. ``TrafficSignalEnv(observation_fn="padded")`` builds it for
    the network's lights (:meth:`covering`).

    :param max_greens: ``G``
    :param max_vehicle_lanes: ``V``
    :param max_pedestrian_edges: ``P``
    """

    max_greens: int
    max_vehicle_lanes: int
    max_pedestrian_edges: int

    @classmethod
    def covering(cls, lights: Sequence[tuple[IntersectionLayout, int]]) -> PaddedObservation:
        """The layout of the largest of ``lights``, given as ``(layout, number of greens)`` pairs."""
        return cls(
            max(n for _, n in lights),
            max(len(layout.vehicle_lanes) for layout, _ in lights),
            max(len(layout.pedestrian_edges) for layout, _ in lights),
        )

    def space(self, layout: IntersectionLayout, n_greens: int) -> spaces.Box:
        """The one space of every light; a light larger than the layout is refused (:class:`ValueError`)."""
        sizes = (n_greens, len(layout.vehicle_lanes), len(layout.pedestrian_edges))
        limits = (self.max_greens, self.max_vehicle_lanes, self.max_pedestrian_edges)
        if any(size > limit for size, limit in zip(sizes, limits, strict=True)):
            raise ValueError(f"light {layout.tls_id} (greens, vehicle lanes, pedestrian edges) {sizes} exceeds {self}")
        size = 2 * self.max_greens + 1 + 3 * self.max_vehicle_lanes + 3 * self.max_pedestrian_edges
        return spaces.Box(0.0, 1.0, shape=(size,), dtype=np.float32)

    def __call__(self, light: LightView) -> np.ndarray:
        n_vehicle = len(light.layout.vehicle_lanes)
        vehicles = _group(light.densities[:n_vehicle], light.queues[:n_vehicle], self.max_vehicle_lanes)
        pedestrians = _group(light.densities[n_vehicle:], light.queues[n_vehicle:], self.max_pedestrian_edges)
        exists = _padded([1.0] * light.n_greens, self.max_greens)
        green = light.green_one_hot(self.max_greens)
        return np.array(green + exists + [light.tau] + vehicles + pedestrians, dtype=np.float32)


def _padded(values: Sequence[float], size: int) -> list[float]:
    return list(values) + [0.0] * (size - len(values))


def _group(densities: Sequence[float], queues: Sequence[float], size: int) -> list[float]:
    """A lane group's densities, queues and "exists" flags, each padded to ``size``."""
    return _padded(densities, size) + _padded(queues, size) + _padded([1.0] * len(densities), size)

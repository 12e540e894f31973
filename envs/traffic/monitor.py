"""Waiting times, densities and queues at one signalised intersection (paper Eqs. 22-25).

:class:`IntersectionMonitor` is called once per simulated second (:meth:`~IntersectionMonitor.track`)
and once per decision (:meth:`~IntersectionMonitor.measure`).

Vehicles (Eq. 24)
    The waiting time of a vehicle at an intersection is SUMO's accumulated waiting time of the vehicle
    (time spent below 0.1 m/s; the simulation runs with a waiting-time memory as long as the episode)
    minus its value when the vehicle was first seen on an incoming lane of the intersection.
    ``W^v_t`` sums it over the vehicles on the incoming lanes at time ``t``.

Pedestrians (Eq. 25)
    SUMO only reports a person's *current* stop (``person.getWaitingTime`` restarts from zero when the
    person moves), so the monitor accumulates per person the seconds it spends waiting (waiting time
    > 0, i.e. standing) on the pedestrian approach of the intersection: the incoming sidewalk and the
    waiting area in front of the crossing. ``W^p_t`` sums it over the persons on that approach at ``t``.
    A person stops counting once it steps onto the crossing.

When a vehicle or person leaves the approach its waiting time moves to a "done" total, so
``done + W`` is the total waiting time spent at this intersection during the episode.

Queue and emissions
    The halting vehicles (below 0.1 m/s) on the incoming lanes at the decision; with ``emissions=True``
    the CO2 emitted on the incoming lanes (SUMO's ``lane.getCO2Emission``, mg per simulated second),
    summed over the seconds of the episode.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from .topology import IntersectionLayout


class Measurement(NamedTuple):
    """The state of one intersection at a decision (see :meth:`IntersectionMonitor.measure`)."""

    vehicle_wait: float
    """Total waiting time [s] of the vehicles on the incoming lanes (``W^v``)."""
    vehicles: int
    """Number of vehicles on the incoming lanes."""
    pedestrian_wait: float
    """Total waiting time [s] of the pedestrians on the approach (``W^p``)."""
    pedestrians: int
    """Number of pedestrians on the approach."""
    halting: int
    """Halting vehicles on the incoming lanes."""
    co2_mg: float
    """CO2 emitted on the incoming lanes since the episode began [mg] (0 without ``emissions``)."""
    vehicle_wait_episode: float
    """Waiting time [s] spent at this intersection by all vehicles since the episode began (gone ones included)."""
    pedestrian_wait_episode: float
    """Waiting time [s] spent at this intersection by all pedestrians since the episode began (gone ones included)."""


class IntersectionMonitor:
    """Per-intersection waiting-time bookkeeping and lane features.

    :param api: the ``libsumo`` module or a ``traci`` connection.
    :param layout: incoming lanes and capacities of the intersection.
    :param step_length: simulated seconds per :meth:`track` call.
    :param emissions: also sum the CO2 emitted on the incoming lanes (one more SUMO call per lane and second).
    """

    def __init__(
        self,
        api: Any,
        layout: IntersectionLayout,
        step_length: float = 1.0,
        emissions: bool = False,
    ) -> None:
        self.layout = layout
        self.step_length = step_length
        self._co2 = api.lane.getCO2Emission if emissions else None
        self._veh_ids = api.edge.getLastStepVehicleIDs
        self._person_ids = api.edge.getLastStepPersonIDs
        self._acc_wait = api.vehicle.getAccumulatedWaitingTime
        self._person_wait = api.person.getWaitingTime
        self._lane_count = api.lane.getLastStepVehicleNumber
        self._lane_halting = api.lane.getLastStepHaltingNumber
        self._veh_edges = layout.vehicle_edges
        self._ped_edges = layout.pedestrian_edges
        self._veh_lanes = tuple(zip(layout.vehicle_lanes, (1.0 / c for c in layout.vehicle_capacity), strict=True))
        self._ped_inv_cap = tuple(1.0 / c for c in layout.pedestrian_capacity)
        self.reset()

    def reset(self) -> None:
        """Forget everything (new episode)."""
        self._veh_offset: dict[str, float] = {}
        self._veh_on: set[str] = set()
        self._veh_last: dict[str, float] = {}
        self._ped_acc: dict[str, float] = {}
        self._ped_on: list[tuple[str, ...]] = [() for _ in self._ped_edges]
        self._ped_waiting: list[int] = [0 for _ in self._ped_edges]
        self.vehicle_done = 0.0
        """Waiting time [s] of vehicles that have already left the incoming lanes."""
        self.pedestrian_done = 0.0
        """Waiting time [s] of pedestrians that have already left the approach."""
        self.co2_mg = 0.0
        """CO2 emitted on the incoming lanes this episode [mg] (with ``emissions``)."""

    def track(self) -> None:
        """Record one simulated second: vehicles entering/leaving, pedestrians standing on the approach."""
        # vehicles: remember the accumulated waiting time at entry, settle it at exit
        cur: set[str] = set()
        for edge in self._veh_edges:
            cur.update(self._veh_ids(edge))
        prev = self._veh_on
        if cur != prev:
            acc = self._acc_wait
            offset = self._veh_offset
            for v in cur - prev:
                offset[v] = acc(v)
            for v in prev - cur:
                off = offset.pop(v)
                try:
                    self.vehicle_done += acc(v) - off
                except Exception:  # noqa: BLE001 - vehicle vanished (teleport/removal): last known value
                    self.vehicle_done += self._veh_last.get(v, 0.0)
                self._veh_last.pop(v, None)
            self._veh_on = cur
        # pedestrians: one more second for everyone standing on the approach
        wait = self._person_wait
        pacc = self._ped_acc
        dt = self.step_length
        for k, edge in enumerate(self._ped_edges):
            ids = self._person_ids(edge)
            self._ped_on[k] = ids
            n = 0
            for p in ids:
                if wait(p) > 0.0:
                    pacc[p] = pacc.get(p, 0.0) + dt
                    n += 1
            self._ped_waiting[k] = n
        if self._co2 is not None:
            co2 = self._co2
            self.co2_mg += dt * sum(co2(lane) for lane, _ in self._veh_lanes)

    def measure(self) -> Measurement:
        """The intersection now (call after :meth:`track` of the current second).

        :return: waiting times and numbers of the incoming vehicles and pedestrians, halting vehicles, CO2 so far.
        """
        acc = self._acc_wait
        offset = self._veh_offset
        last = self._veh_last
        w_v = 0.0
        for v in self._veh_on:
            w = acc(v) - offset[v]
            last[v] = w
            w_v += w
        on: set[str] = set()
        for ids in self._ped_on:
            on.update(ids)
        w_p = 0.0
        pacc = self._ped_acc
        gone = []
        for p, w in pacc.items():
            if p in on:
                w_p += w
            else:
                gone.append(p)
        for p in gone:
            self.pedestrian_done += pacc.pop(p)
        halting = sum(self._lane_halting(lane) for lane, _ in self._veh_lanes)
        vehicles, pedestrians = len(self._veh_on), len(on)
        spent_v, spent_p = self.vehicle_done + w_v, self.pedestrian_done + w_p
        return Measurement(w_v, vehicles, w_p, pedestrians, halting, self.co2_mg, spent_v, spent_p)

    def lane_features(self) -> tuple[list[float], list[float]]:
        """Density and queue of every incoming lane, each divided by the lane's capacity and clipped to 1.

        Vehicle lanes first (a vehicle is queued below 0.1 m/s), then the pedestrian approach edges
        (incoming sidewalks, waiting areas; a person is queued while standing).

        :return: ``(densities, queues)``.
        """
        dens: list[float] = []
        queue: list[float] = []
        for lane, inv in self._veh_lanes:
            dens.append(min(1.0, self._lane_count(lane) * inv))
            queue.append(min(1.0, self._lane_halting(lane) * inv))
        for ids, n_wait, inv in zip(self._ped_on, self._ped_waiting, self._ped_inv_cap, strict=True):
            dens.append(min(1.0, len(ids) * inv))
            queue.append(min(1.0, n_wait * inv))
        return dens, queue

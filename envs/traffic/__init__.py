"""SUMO traffic-signal control with pedestrians (paper Sec. 5.2) as a multi-objective PettingZoo env.

Public names:

* :class:`TrafficSignalEnv` -- the ``ParallelEnv`` on any SUMO network with traffic lights (one agent per light,
  rewards from :data:`OBJECTIVE_MENU`, by default ``[vehicle, pedestrian]`` waiting-time decrease);
* :func:`run_program_episode` -- fixed-time / actuated / max-pressure baselines with the same metrics;
* :class:`Objective`, :class:`LightView`, :class:`ObservationFunction` -- users' own rewards and observations;
  :class:`SumoRLObservation` and ``mdp="sumo-rl"`` -- sumo-rl's default MDP;
* :data:`NET_FILE`, :data:`ROUTE_FILE` -- the three-intersection scenario;
* :class:`SumoNotFoundError`, :class:`SumoLoadError` -- installation and loading errors.

The network is built from the XML sources in ``nets/`` by ``nets/build.py``.
"""

from .baselines import PROGRAMS, run_program_episode
from .env import (
    ACTION_MODES,
    EPISODE_METRIC_KEYS,
    MDP_DEFAULTS,
    PEDESTRIAN_METRIC_KEYS,
    SIGNAL_CONTROLS,
    TrafficSignalEnv,
)
from .hooks import LightView, ObservationFunction, SumoRLObservation
from .objectives import DEFAULT_OBJECTIVES, Objective
from .objectives import MENU as OBJECTIVE_MENU
from .scenario import NET_FILE, NETS_DIR, ROUTE_FILE, write_actuated_programs
from .signals import CHANGE, KEEP, SignalController, SignalProgram
from .sumo_backend import SumoLoadError, SumoNotFoundError, SumoSimulation
from .topology import IntersectionLayout, read_network

__all__ = [
    "ACTION_MODES",
    "CHANGE",
    "DEFAULT_OBJECTIVES",
    "EPISODE_METRIC_KEYS",
    "PEDESTRIAN_METRIC_KEYS",
    "KEEP",
    "NETS_DIR",
    "NET_FILE",
    "OBJECTIVE_MENU",
    "PROGRAMS",
    "ROUTE_FILE",
    "SIGNAL_CONTROLS",
    "IntersectionLayout",
    "LightView",
    "MDP_DEFAULTS",
    "ObservationFunction",
    "Objective",
    "SignalController",
    "SignalProgram",
    "SumoLoadError",
    "SumoNotFoundError",
    "SumoRLObservation",
    "SumoSimulation",
    "TrafficSignalEnv",
    "read_network",
    "run_program_episode",
    "write_actuated_programs",
]

"""SUMO traffic-signal control with pedestrians (paper Sec. 5.2) as a multi-objective PettingZoo env.

Public names:

* :class:`TrafficSignalEnv` -- the ``ParallelEnv`` (one keep/change agent per traffic light, rewards
  ``[vehicle, pedestrian]`` waiting-time decrease);
* :func:`run_program_episode` -- fixed-time / actuated baselines with the same metrics;
* :data:`NET_FILE`, :data:`ROUTE_FILE`, :data:`ACTUATED_FILE` -- the three-intersection scenario;
* :class:`SumoNotFoundError`, :class:`SumoLoadError` -- installation and loading errors.

The network is built from the XML sources in ``nets/`` by ``nets/build.py``.
"""

from .baselines import PROGRAMS, run_program_episode
from .env import EPISODE_METRIC_KEYS, OBJECTIVES, REWARD_DIM, SIGNAL_CONTROLS, TrafficSignalEnv
from .scenario import ACTUATED_FILE, NET_FILE, NETS_DIR, ROUTE_FILE
from .signals import CHANGE, KEEP, SignalController, SignalProgram
from .sumo_backend import SumoLoadError, SumoNotFoundError, SumoSimulation
from .topology import IntersectionLayout, read_network

__all__ = [
    "ACTUATED_FILE",
    "CHANGE",
    "EPISODE_METRIC_KEYS",
    "KEEP",
    "NETS_DIR",
    "NET_FILE",
    "OBJECTIVES",
    "PROGRAMS",
    "REWARD_DIM",
    "ROUTE_FILE",
    "SIGNAL_CONTROLS",
    "IntersectionLayout",
    "SignalController",
    "SignalProgram",
    "SumoLoadError",
    "SumoNotFoundError",
    "SumoSimulation",
    "TrafficSignalEnv",
    "read_network",
    "run_program_episode",
]

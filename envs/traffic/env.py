"""Multi-objective traffic-signal control with pedestrians as a PettingZoo ``ParallelEnv`` (paper Sec. 5.2).

One agent per traffic light (agent id = traffic-light id). Every ``delta_time`` simulated seconds each
agent observes its intersection (Eq. 22), chooses *keep* (0) or *change* (1) (or, with
``action_mode="phase"``, the green phase to show), and receives the vector reward (Eq. 23)::

    r_t = [W^v_t - W^v_{t+1},  W^p_t - W^p_{t+1}]

where ``W^v`` / ``W^p`` are the cumulative waiting times of the vehicles on its incoming lanes and of
the pedestrians waiting to cross (Eqs. 24-25, see :mod:`.monitor`). Other objectives (queue, CO2) come
from a menu (:mod:`.objectives`): ``objectives=[...]`` chooses them and their order.

Any SUMO network with traffic lights runs (``net_file``, ``route_file``): the lights, their incoming
lanes and their green phases are read from the network file.

SUMO runs in-process through libsumo (default), or through TraCI (``backend="traci"``; ``gui=True``
opens sumo-gui). The environment advances SUMO one second at a time and drives the lights itself
with ``setRedYellowGreenState``, so SUMO's static program never advances on its own. With
``signal_control="fixed-time"`` or ``"actuated"`` the lights follow SUMO's static or actuated program
instead, and with ``"max-pressure"`` the env's phase logic shows the green of largest vehicle pressure
(:mod:`.max_pressure`); actions are then ignored (the baselines, see :func:`.baselines.run_program_episode`).

Example::

    env = TrafficSignalEnv(num_seconds=500, seed=0)
    obs, infos = env.reset()
    while env.agents:
        obs, rewards, terms, truncs, infos = env.step({a: env.action_space(a).sample() for a in env.agents})
    print(env.episode_metrics())
    env.close()
"""

from __future__ import annotations

import os
import shutil
import tempfile
import weakref
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from .hooks import LightView, ObservationFunction, PaddedObservation, SumoRLObservation, check_picklable
from .max_pressure import MaxPressure
from .monitor import IntersectionMonitor, Measurement
from .objectives import DEFAULT_OBJECTIVES, Objective, reward_scales, select_objectives
from .scenario import NET_FILE, ROUTE_FILE, trim_demand, warn_if_no_demand, write_actuated_programs
from .signals import SignalController, SignalProgram, is_green
from .sumo_backend import SumoSimulation
from .topology import IntersectionLayout, read_network

SIGNAL_CONTROLS = ("agent", "fixed-time", "actuated", "max-pressure")
"""Who drives the lights: the agents, SUMO's static or actuated program, or max-pressure (:mod:`.max_pressure`)."""

ACTION_MODES = ("change", "phase")
"""What an action says: keep (0) / change to the next green (1), or the index of the green to show."""

MDP_DEFAULTS: dict[str, dict[str, Any]] = {
    "paper": {"yellow_time": 3, "min_green": 10, "action_mode": "change", "objectives": DEFAULT_OBJECTIVES},
    "sumo-rl": {
        "yellow_time": 2,
        "min_green": 5,
        "action_mode": "phase",
        "objectives": ("vehicle_waiting",),
        "observation_fn": SumoRLObservation(),
    },  # fmt: skip
}
"""The defaults ``mdp`` selects for the arguments left at None: the paper's, or sumo-rl's (its
``SumoEnvironment`` defaults: yellow 2 s, minimum green 5 s, phase actions, the waiting-time-decrease reward and
its observation, :class:`~.hooks.SumoRLObservation`). ``delta_time`` 5 s, ``max_green`` 50 s and ignoring early
changes are the same in both."""

EARLY_CHANGES = ("ignore", "defer")
"""What a change asked for before the minimum green does: nothing, or it is made when the minimum green is reached."""

EPISODE_METRIC_KEYS = (
    "vehicle_waiting_time_total",
    "vehicle_waiting_time_mean",
    "vehicles_departed",
    "vehicles_arrived",
    "sim_time",
)
"""Keys of :meth:`TrafficSignalEnv.episode_metrics` on every network."""

PEDESTRIAN_METRIC_KEYS = (
    "pedestrian_waiting_time_total",
    "pedestrian_waiting_time_mean",
    "pedestrians_departed",
    "pedestrians_arrived",
)
"""Keys :meth:`TrafficSignalEnv.episode_metrics` adds on a network with signalised pedestrian crossings."""


def _check_int(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low} (seconds), got {value!r}")
    return int(value)


def _check_choice(name: str, value: Any, choices: Sequence[Any]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")


def _observation_fn(given: Any, lights: Sequence[tuple[IntersectionLayout, int]]) -> ObservationFunction | None:
    """What ``observation_fn`` names: None (Eq. 22), ``"padded"`` for these lights, or the user's own."""
    if given is None:
        return None
    if given == "padded":
        return PaddedObservation.covering(lights)
    if isinstance(given, str) or not isinstance(given, ObservationFunction):
        raise ValueError(
            "observation_fn must be None, 'padded', or have space(layout, n_greens) -> Box and __call__(view) -> "
            f"array (see sfgpi_envs.traffic.hooks), got {given!r}"
        )
    check_picklable(given, "observation_fn")
    return given


class TrafficSignalEnv(ParallelEnv):
    """Traffic lights with vehicles and pedestrians, one agent per light, vector rewards.

    Observation of an agent (float32, all entries in [0, 1]), Eq. 22::

        [rho_0 .. rho_{G-1}, tau, density_1 .. density_L, queue_1 .. queue_L]

    * ``rho``: one-hot of the green phase shown (during yellow: the green that comes next), over the
      ``G`` green phases of the light's static program; in the default network phase 0 = N-S vehicles
      + pedestrians, phase 1 = W-E vehicles;
    * ``tau``: elapsed green time / ``max_green`` (0 during yellow);
    * for each incoming lane ``l`` -- the controlled vehicle lanes, then the incoming sidewalk and the
      waiting area in front of the crossing -- number of vehicles/persons (density) and of queued ones
      (vehicles below 0.1 m/s, persons standing) divided by the lane's capacity, clipped to 1.

    Actions (``action_mode="change"``, the paper's): ``Discrete(2)``, 0 keep, 1 change to the next green
    of the cycle; (``"phase"``, sumo-rl's): ``Discrete(G)``, the green to show. A change before
    ``min_green`` seconds of green is ignored (``early_change="ignore"``, sumo-rl's rule) or made when the green
    reaches ``min_green`` seconds unless a later decision keeps it (``"defer"``); a green is ended after
    ``max_green`` seconds whatever the action (the next green of the cycle follows); a change shows a yellow state
    for ``yellow_time`` seconds (the program's, or links green now and red next turn yellow), during which actions
    are ignored.

    Rewards: ``float32`` arrays of shape ``(d,)``, one component per objective of ``objectives``
    (default: vehicles, pedestrians, in seconds), times ``reward_scale`` (per objective).

    Infos (every step, per agent): ``vehicle_wait_total`` (``W^v``), ``vehicle_wait_mean`` (per
    incoming vehicle), ``pedestrian_wait_total`` (``W^p``), ``pedestrian_wait_mean`` (per person on
    the approach), ``vehicles_incoming``, ``pedestrians_incoming``, ``green_phase``, ``yellow`` and
    ``time``, ``vehicles_halting`` and, with the ``"co2"`` objective, ``co2_g`` (emitted on the incoming
    lanes so far). At the last step every agent's info also holds ``"episode"``: :meth:`episode_metrics`.

    The episode ends by truncation (time limit) after ``num_seconds`` simulated seconds (from ``begin_time``).

    :param net_file: SUMO network (default: the three-intersection scenario); every traffic light with at
        least two green phases in its static program becomes an agent (the others run their program).
    :param route_file: SUMO demand (flows are cut at ``num_seconds`` in a temporary copy, because
        SUMO creates every person of a ``personFlow`` when it loads the file).
    :param num_seconds: episode length [s].
    :param begin_time: simulation time the episode starts at [s] (networks whose demand starts later, as
        RESCO's, need it).
    :param mdp: whose defaults the arguments left at None take (:data:`MDP_DEFAULTS`): ``"paper"`` or
        ``"sumo-rl"`` (sumo-rl's ``SumoEnvironment``: yellow 2 s, minimum green 5 s, phase actions, its reward and
        observation).
    :param delta_time: simulated seconds between two decisions.
    :param yellow_time: duration of the yellow phase between two greens [s] (None: the ``mdp``'s).
    :param min_green: minimum green time [s] (None: the ``mdp``'s).
    :param max_green: maximum green time [s] (also the normaliser of ``tau``).
    :param early_change: what a change asked for before ``min_green`` seconds of green does: ``"ignore"``
        (nothing) or ``"defer"`` (it is made at ``min_green``, so that a green can last exactly ``min_green`` on a
        decision grid that does not fall on it).
    :param objectives: names from :data:`~.objectives.MENU` or users' :class:`~.objectives.Objective` objects, one
        reward component each, in order (``"pedestrian_waiting"`` needs a network with signalised crossings); None:
        the ``mdp``'s.
    :param action_mode: ``"change"`` (keep/change) or ``"phase"`` (choose the green); None: the ``mdp``'s.
    :param observation_fn: None (Eq. 22 above), ``"padded"`` (one layout for lights that differ, every slot meaning
        the same at every light: :class:`~.hooks.PaddedObservation`; with ``action_mode="phase"`` every light also
        gets ``Discrete(G)``, ``G`` the most greens of a light, and ``info["action_mask"]`` allows its own greens
        only), or a user's picklable object with
        ``space(layout, n_greens)`` and ``__call__(view)`` (:class:`~.hooks.ObservationFunction`).
    :param signal_control: ``"agent"`` (actions drive the lights), ``"fixed-time"`` (SUMO's static
        program in the network), ``"actuated"`` (SUMO's gap-based actuated program: the static
        program's phases, greens between ``min_green`` and ``max_green``, or ``actuated_file``) or
        ``"max-pressure"`` (every ``delta_time`` the green of largest vehicle pressure, through the agents'
        phase logic, :mod:`.max_pressure`); in the last three cases actions are ignored.
    :param backend: ``"libsumo"`` (in-process, fast; one live simulation per process) or ``"traci"``;
        default: libsumo, or traci when ``gui`` is set.
    :param gui: show the simulation in sumo-gui (TraCI backend).
    :param seed: seed of SUMO (``--seed``) for the first episode and of the seeds of the later ones;
        ``reset(seed=...)`` overrides it.
    :param actuated_file: additional file with the actuated programs (``signal_control="actuated"``),
        replacing the ones derived from the static programs.
    :param additional_files: further SUMO additional files.
    :param sumo_args: further SUMO command-line options.
    :param sumo_warnings: let SUMO print its warnings (e.g. jammed pedestrians).
    :param reward_scale: factor applied to the rewards: one number for all components, one per
        component, or a mapping objective name -> factor (others keep 1); default 1 (the units of
        :mod:`.objectives`). Learners with neural networks train
        better on rewards of order one (the per-step changes are tens of seconds), and per-objective factors
        set the units the preference weights trade (see the ``traffic`` domain preset). Infos and
        :meth:`episode_metrics` stay in seconds.
    :param render_mode: ``None`` or ``"human"`` (the latter implies ``gui=True``).
    :raises ValueError: for invalid arguments, or an invalid network file (message names the file).
    :raises FileNotFoundError: if the network or route file does not exist.
    :raises SumoNotFoundError: if SUMO / libsumo / traci is not installed (``ImportError`` subclass).
    """

    metadata = {"name": "sfgpi_traffic_v0", "render_modes": ["human"], "is_parallelizable": True}

    def __init__(
        self,
        net_file: str | os.PathLike[str] = NET_FILE,
        route_file: str | os.PathLike[str] = ROUTE_FILE,
        *,
        num_seconds: int = 500,
        begin_time: int = 0,
        mdp: str = "paper",
        delta_time: int = 5,
        yellow_time: int | None = None,
        min_green: int | None = None,
        max_green: int = 50,
        early_change: str = "ignore",
        objectives: Sequence[str | Objective] | None = None,
        action_mode: str | None = None,
        observation_fn: ObservationFunction | str | None = None,
        signal_control: str = "agent",
        backend: str | None = None,
        gui: bool = False,
        seed: int | None = None,
        actuated_file: str | os.PathLike[str] | None = None,
        additional_files: Sequence[str | os.PathLike[str]] = (),
        sumo_args: Sequence[str] = (),
        sumo_warnings: bool = False,
        reward_scale: float | Sequence[float] | Mapping[str, float] = 1.0,
        render_mode: str | None = None,
    ) -> None:
        super().__init__()
        _check_choice("mdp", mdp, tuple(MDP_DEFAULTS))
        defaults = MDP_DEFAULTS[mdp]
        yellow_time = defaults["yellow_time"] if yellow_time is None else yellow_time
        min_green = defaults["min_green"] if min_green is None else min_green
        action_mode = defaults["action_mode"] if action_mode is None else action_mode
        objectives = defaults["objectives"] if objectives is None else objectives
        self.mdp = mdp
        _check_choice("render_mode", render_mode, (None, "human"))
        _check_choice("signal_control", signal_control, SIGNAL_CONTROLS)
        _check_choice("early_change", early_change, EARLY_CHANGES)
        _check_choice("action_mode", action_mode, ACTION_MODES)
        self._set_timing(num_seconds, begin_time, delta_time, yellow_time, min_green, max_green)
        self.early_change = early_change
        self.objectives = select_objectives(objectives)
        self.objective_names = tuple(o.name for o in self.objectives)
        """The reward components' names, in order."""
        self.reward_scale = reward_scales(reward_scale, self.objective_names)
        self.action_mode = action_mode
        self.signal_control = signal_control
        self._drives = signal_control in ("agent", "max-pressure")  # the env's controllers set the lights
        self._max_pressure: MaxPressure | None = None
        self.render_mode = render_mode
        self.gui = gui or render_mode == "human"
        self.backend = backend if backend is not None else ("traci" if self.gui else "libsumo")
        # libsumo holds one live simulation per process: sb3-sfgpi builds no copy of this env beside it
        # (sb3_sfgpi.common.env_copies.ONE_PER_PROCESS)
        self.metadata = {**self.metadata, "one_per_process": self.backend == "libsumo"}
        self._set_files(net_file, route_file, actuated_file, additional_files)
        self.sumo_args = tuple(str(a) for a in sumo_args)
        self.sumo_warnings = sumo_warnings
        self._set_intersections(defaults.get("observation_fn") if observation_fn is None else observation_fn)
        self._sim = SumoSimulation(self.backend, self.gui)  # checks that SUMO is installed; starts nothing
        self._seed = seed
        self._rng = np.random.default_rng(seed)
        self._tmpdir: str | None = None
        self._finalizer: weakref.finalize | None = None
        self._route_for_episode: Path | None = None
        self._api: Any = None
        self._monitors: list[IntersectionMonitor] = []
        self._time = 0
        self._last: list[Measurement] = []
        self._counts = [0, 0, 0, 0]  # departed vehicles, arrived vehicles, departed persons, arrived persons
        self.sumo_seed: int | None = None
        """SUMO seed of the current episode."""

    def _set_timing(
        self, num_seconds: int, begin_time: int, delta_time: int, yellow_time: int, min_green: int, max_green: int
    ) -> None:
        self.num_seconds = _check_int("num_seconds", num_seconds, 1)
        self.begin_time = _check_int("begin_time", begin_time, 0)
        self._end = self.begin_time + self.num_seconds
        self.delta_time = _check_int("delta_time", delta_time, 1)
        self.yellow_time = _check_int("yellow_time", yellow_time, 1)
        self.min_green = _check_int("min_green", min_green, 0)
        self.max_green = _check_int("max_green", max_green, 1)
        if self.min_green > self.max_green:
            raise ValueError(f"min_green ({min_green}) must not exceed max_green ({max_green})")

    def _set_files(
        self,
        net_file: str | os.PathLike[str],
        route_file: str | os.PathLike[str],
        actuated_file: str | os.PathLike[str] | None,
        additional_files: Sequence[str | os.PathLike[str]],
    ) -> None:
        self.net_file = Path(net_file).resolve()
        self.route_file = Path(route_file).resolve()
        if not self.route_file.is_file():
            raise FileNotFoundError(f"route file {self.route_file} does not exist")
        warn_if_no_demand(self.route_file)
        extra = [Path(f).resolve() for f in additional_files]
        self.actuated_file = None if actuated_file is None else Path(actuated_file).resolve()
        if self.signal_control == "actuated" and self.actuated_file is not None:
            extra.insert(0, self.actuated_file)
        for f in extra:
            if not f.is_file():
                raise FileNotFoundError(f"additional file {f} does not exist")
        self.additional_files = tuple(extra)

    def _set_intersections(self, observation_fn: ObservationFunction | str | None) -> None:
        """The agents (traffic lights with two green phases or more), their programs, controllers and spaces."""
        self.layouts: dict[str, IntersectionLayout] = {
            tid: lay for tid, lay in read_network(self.net_file).items() if sum(map(is_green, dict(lay.phases))) > 1
        }
        if not self.layouts:
            raise ValueError(f"network file {self.net_file}: no traffic light has two green phases to choose from")
        self._programs = {
            tid: SignalProgram.from_phases([s for s, _ in lay.phases], tid) for tid, lay in self.layouts.items()
        }
        self._check_objectives()
        self.possible_agents: list[str] = list(self.layouts)
        self.agents: list[str] = []
        n_greens = {a: len(self._programs[a].greens) for a in self.possible_agents}
        self.observation_fn = _observation_fn(observation_fn, [(self.layouts[a], n_greens[a]) for a in n_greens])
        self.observation_spaces = {
            a: spaces.Box(0.0, 1.0, shape=(n_greens[a] + 1 + 2 * lay.n_lanes,), dtype=np.float32)
            if self.observation_fn is None
            else self.observation_fn.space(lay, n_greens[a])
            for a, lay in self.layouts.items()
        }
        most = max(n_greens.values())
        padded = self.action_mode == "phase" and isinstance(self.observation_fn, PaddedObservation)
        #: the greens a light has among the padded ``Discrete(G)`` (phase actions of padded lights), else None
        self._action_masks = {a: np.arange(most) < n for a, n in n_greens.items()} if padded else None
        change = self.action_mode == "change"  # keep/change; else the green: a light's own, or the most (masked)
        self.action_spaces = {a: spaces.Discrete(2 if change else most if padded else n) for a, n in n_greens.items()}
        d = len(self.objectives)
        self.reward_spaces = {
            a: spaces.Box(-np.inf, np.inf, shape=(d,), dtype=np.float32) for a in self.possible_agents
        }
        self._controllers = [
            SignalController(
                self._programs[a], self.min_green, self.max_green, self.yellow_time, self.early_change == "defer"
            )
            for a in self.possible_agents
        ]
        self._lookups = [self._programs[a].lookup() for a in self.possible_agents]

    def _has_crossings(self) -> bool:
        """Whether any light has a signalised pedestrian crossing."""
        return any(lay.waiting_areas for lay in self.layouts.values())

    def _check_objectives(self) -> None:
        if any(o.needs_pedestrians for o in self.objectives) and not self._has_crossings():
            raise ValueError(
                f"objective 'pedestrian_waiting' needs signalised pedestrian crossings; the network {self.net_file} "
                "has none at any traffic light"
            )

    # ------------------------------------------------------------------------------------- spaces
    def observation_space(self, agent: str) -> spaces.Box:
        """Observation space of ``agent`` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        """Action space of ``agent``: ``Discrete(2)`` (0 keep, 1 change) or ``Discrete(G)`` (the green to show)."""
        return self.action_spaces[agent]

    def reward_space(self, agent: str) -> spaces.Box:
        """Reward space of ``agent``: ``Box(-inf, inf, (d,), float32)``, one component per objective."""
        return self.reward_spaces[agent]

    @property
    def sim(self) -> SumoSimulation:
        """The SUMO simulation (its ``api`` is the libsumo module or the TraCI connection)."""
        return self._sim

    @property
    def sim_time(self) -> int:
        """Current simulation time [s]."""
        return self._time

    # -------------------------------------------------------------------------------------- reset
    def _workdir(self) -> str:
        if self._tmpdir is None:
            self._tmpdir = tempfile.mkdtemp(prefix="sfgpi_traffic_")
            self._finalizer = weakref.finalize(self, shutil.rmtree, self._tmpdir, True)
        return self._tmpdir

    def _episode_route_file(self) -> Path:
        if self._route_for_episode is None:
            self._route_for_episode = trim_demand(self.route_file, self._end, self._workdir())
        return self._route_for_episode

    def _additional_files(self) -> list[Path]:
        files = list(self.additional_files)
        if self.signal_control == "actuated" and self.actuated_file is None:
            path = Path(self._workdir()) / "actuated.add.xml"
            if not path.is_file():
                write_actuated_programs(self.layouts.values(), self.min_green, self.max_green, path)
            files.insert(0, path)
        return files

    def sumo_command(self, seed: int) -> list[str]:
        """SUMO options of an episode (without the executable).

        :param seed: SUMO's random seed.
        :return: the options.
        """
        args = [
            "--net-file", str(self.net_file),
            "--route-files", str(self._episode_route_file()),
            "--seed", str(int(seed)),
            "--begin", str(self.begin_time),
            "--step-length", "1",
            "--waiting-time-memory", str(max(self.num_seconds, 100)),
            "--no-step-log", "true",
            "--duration-log.disable", "true",
        ]  # fmt: skip
        additional = self._additional_files()
        if additional:
            args += ["--additional-files", ",".join(str(f) for f in additional)]
        if not self.sumo_warnings:
            args += ["--no-warnings", "true"]
        return args + list(self.sumo_args)

    def reset(
        self, seed: int | None = None, options: Mapping[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start a new episode: (re)load SUMO (``load`` in the running process when possible).

        :param seed: SUMO seed of this episode; also re-seeds the seeds of later episodes and the
            action spaces. Default: the constructor's seed for the first episode, then seeds drawn
            from it.
        :param options: unused.
        :return: observations and infos of all agents.
        :raises RuntimeError: if another libsumo simulation is live in this process.
        :raises SumoLoadError: if SUMO cannot load the scenario (message includes SUMO's complaint).
        """
        del options
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None
        if seed is not None:
            self._rng = np.random.default_rng(seed)
            for i, a in enumerate(self.possible_agents):
                self.action_spaces[a].seed(int(seed) + i)
            sumo_seed = int(seed)
        else:
            sumo_seed = int(self._rng.integers(0, 2**31 - 1))
        self.sumo_seed = sumo_seed
        self._sim.start(self.sumo_command(sumo_seed))
        api = self._sim.api
        try:
            if api is not self._api:
                self._bind(api)
            for mon in self._monitors:
                mon.reset()
            self._time = int(round(api.simulation.getTime()))
            if self._drives:
                for a, ctl in zip(self.possible_agents, self._controllers, strict=True):
                    self._set_state(a, ctl.reset(self._time))
            else:
                self._lookups = [self._active_program(a).lookup() for a in self.possible_agents]
            self._counts = [0, 0, 0, 0]
            self._last = [mon.measure() for mon in self._monitors]
            views = [self._view(i, last, last) for i, last in enumerate(self._last)]
        except self._sim.errors as exc:
            self._died(exc)
        self.agents = list(self.possible_agents)
        obs = {a: self._observe(view) for a, view in zip(self.agents, views, strict=True)}
        infos = {a: self._info(i) for i, a in enumerate(self.agents)}
        return obs, infos

    def _bind(self, api: Any) -> None:
        self._api = api
        self._set_state = api.trafficlight.setRedYellowGreenState
        self._simulation_step = api.simulationStep
        sim = api.simulation
        self._counters = (sim.getDepartedNumber, sim.getArrivedNumber, sim.getDepartedPersonNumber,
                          sim.getArrivedPersonNumber)  # fmt: skip
        emissions = "co2" in self.objective_names
        self._monitors = [IntersectionMonitor(api, self.layouts[a], emissions=emissions) for a in self.possible_agents]
        if self.signal_control == "max-pressure":
            self._max_pressure = MaxPressure.from_simulation(api, self._programs, self.layouts, self._controllers)

    def _active_program(self, tls: str) -> SignalProgram:
        tl = self._api.trafficlight
        current = tl.getProgram(tls)
        for logic in tl.getAllProgramLogics(tls):
            if logic.programID == current:
                return SignalProgram.from_phases([p.state for p in logic.phases], tls)
        return self._programs[tls]

    # --------------------------------------------------------------------------------------- step
    def step(
        self, actions: Mapping[str, Any]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, np.ndarray],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Apply the agents' actions and simulate ``delta_time`` seconds.

        :param actions: action per agent (0 keep / 1 change, or the green to show); missing agents keep.
        :return: observations, vector rewards, terminations, truncations, infos.
        :raises RuntimeError: if the episode is over or was never started, or SUMO died during the step.
        :raises ValueError: for an action outside the agent's action space.
        """
        if not self.agents:
            raise RuntimeError("no episode is running: call reset() first")
        agent_mode, drives = self.signal_control == "agent", self._drives
        acts = [self._checked_action(a, actions) for a in self.possible_agents] if agent_mode else []
        agents = self.possible_agents
        try:
            if self._max_pressure is not None:
                acts = self._max_pressure.decide(self._controllers)  # the greens it asks for, as phase actions
            if drives:
                self._apply_actions(acts)
            self._simulate(min(self.delta_time, self._end - self._time), self._controllers if drives else ())
            measures = [mon.measure() for mon in self._monitors]
            views = [self._view(i, prev, cur) for i, (prev, cur) in enumerate(zip(self._last, measures, strict=True))]
            obs = {a: self._observe(view) for a, view in zip(agents, views, strict=True)}
            rewards = {a: self._reward(view) for a, view in zip(agents, views, strict=True)}
        except self._sim.errors as exc:
            self._died(exc)
        self._last = measures
        done = self._time >= self._end
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, done)
        infos = {a: self._info(i) for i, a in enumerate(agents)}
        if done:
            metrics = self.episode_metrics()
            for a in agents:
                infos[a]["episode"] = dict(metrics)
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def _apply_actions(self, acts: list[int | None]) -> None:
        """Hand each agent's action (``None``: keep; max-pressure's: a green) to its controller, show what it asks."""
        phase = self.action_mode == "phase" or self._max_pressure is not None
        apply = SignalController.request if phase else SignalController.act
        for a, ctl, act in zip(self.possible_agents, self._controllers, acts, strict=True):
            state = None if act is None else apply(ctl, act, self._time)
            if state is not None:
                self._set_state(a, state)

    def _simulate(self, n: int, controllers: Sequence[SignalController]) -> None:
        """Advance SUMO ``n`` seconds, ticking the controllers and tracking the monitors and counters every second."""
        time, monitors, counters, counts = self._time, self._monitors, self._counters, self._counts
        sim_step = self._simulation_step
        for _ in range(n):
            for a, ctl in zip(self.possible_agents, controllers, strict=False):  # no controllers in program mode
                state = ctl.tick(time)
                if state is not None:
                    self._set_state(a, state)
            sim_step()
            time += 1
            self._time = time
            for mon in monitors:
                mon.track()
            for k in range(4):
                counts[k] += counters[k]()

    def _reward(self, view: LightView) -> np.ndarray:
        return (np.array([o.reward(view) for o in self.objectives]) * self.reward_scale).astype(np.float32)

    def _checked_action(self, agent: str, actions: Mapping[str, Any]) -> int | None:
        """``agent``'s action as an int (``None`` when it has none: it keeps its green)."""
        if agent not in actions:
            return None
        act, n = actions[agent], self.action_spaces[agent].n
        try:
            k = int(act)
        except (TypeError, ValueError):
            k = -1
        if k != act or not 0 <= k < n:
            meaning = "0 (keep) or 1 (change)" if self.action_mode == "change" else f"a green phase in 0..{n - 1}"
            raise ValueError(f"action of {agent} must be {meaning}, got {act!r}")
        if self._action_masks is not None and not self._action_masks[agent][k]:
            raise ValueError(
                f"action of {agent} is green {k}, which its action mask forbids: it has only "
                f"{self._action_masks[agent].sum()} greens (padded phase actions: act within info['action_mask'])"
            )
        return k

    def _died(self, exc: BaseException) -> NoReturn:
        time = self._time
        self.agents = []
        self._sim.close()
        self._api = None
        raise RuntimeError(
            f"the SUMO simulation stopped unexpectedly at t={time} s ({type(exc).__name__}: {exc}). "
            "Call reset() to start a new episode."
        ) from exc

    # -------------------------------------------------------------------------- observation / info
    def _view(self, i: int, previous: Measurement, current: Measurement) -> LightView:
        """Light ``i`` now, for the objectives and the observation."""
        tls = self.possible_agents[i]
        if self._drives:
            ctl = self._controllers[i]
            green, green_time = ctl.green, ctl.elapsed_green(self._time)
        else:
            tl = self._api.trafficlight
            green, yellow = self._lookups[i].get(tl.getRedYellowGreenState(tls), (0, False))
            green_time = 0.0 if yellow else tl.getSpentDuration(tls)
        dens, queue = self._monitors[i].lane_features()
        return LightView(
            tls, self.layouts[tls], previous, current, green, len(self._programs[tls].greens), green_time,
            self.min_green, self.max_green, tuple(dens), tuple(queue), self._time, self._api,
        )  # fmt: skip

    def _observe(self, view: LightView) -> np.ndarray:
        return view.default_observation() if self.observation_fn is None else self.observation_fn(view)

    def _info(self, i: int) -> dict[str, Any]:
        last = self._last[i]
        w_v, n_v, w_p, n_p = last.vehicle_wait, last.vehicles, last.pedestrian_wait, last.pedestrians
        if self._drives:
            green, yellow = self._controllers[i].green, self._controllers[i].in_yellow
        else:
            state = self._api.trafficlight.getRedYellowGreenState(self.possible_agents[i])
            green, yellow = self._lookups[i].get(state, (0, False))
        info = {
            "vehicle_wait_total": w_v,
            "vehicle_wait_mean": w_v / n_v if n_v else 0.0,
            "pedestrian_wait_total": w_p,
            "pedestrian_wait_mean": w_p / n_p if n_p else 0.0,
            "vehicles_incoming": n_v,
            "pedestrians_incoming": n_p,
            "vehicles_halting": last.halting,
            "green_phase": green,
            "yellow": yellow,
            "time": self._time,
        }
        if "co2" in self.objective_names:
            info["co2_g"] = last.co2_mg / 1000.0
        if self._action_masks is not None:
            info["action_mask"] = self._action_masks[self.possible_agents[i]].astype(np.int8)
        return info

    def episode_metrics(self) -> dict[str, float]:
        """System metrics of the current (or just finished) episode.

        * ``vehicle_waiting_time_total``: waiting time [s] of all vehicles on the incoming lanes of the
          intersections (where all waiting happens in this network), summed over vehicles;
        * ``vehicle_waiting_time_mean``: that total divided by ``vehicles_departed``;
        * ``vehicles_departed``, ``vehicles_arrived``; ``sim_time``: simulated seconds since ``begin_time``;
        * on a network with signalised pedestrian crossings only (elsewhere no pedestrian can wait at a light, and a
          mean of 0 s would read as a result): ``pedestrian_waiting_time_total`` / ``_mean``, the same for
          pedestrians (time standing on the approaches of the crossings) divided by ``pedestrians_departed``, and
          ``pedestrians_departed``, ``pedestrians_arrived``;
        * with the ``"co2"`` objective only: ``co2_emitted_kg``, the CO2 the vehicles on the incoming lanes emitted.

        :return: the metrics (keys :data:`EPISODE_METRIC_KEYS`, :data:`PEDESTRIAN_METRIC_KEYS` and ``co2_emitted_kg``
            as above).
        """
        veh = sum(last.vehicle_wait_episode for last in self._last)
        dep_v, arr_v, dep_p, arr_p = self._counts
        metrics = {
            "vehicle_waiting_time_total": float(veh),
            "vehicle_waiting_time_mean": float(veh / dep_v) if dep_v else 0.0,
            "vehicles_departed": float(dep_v),
            "vehicles_arrived": float(arr_v),
            "sim_time": float(self._time - self.begin_time),
        }
        if self._has_crossings():
            ped = sum(last.pedestrian_wait_episode for last in self._last)
            metrics["pedestrian_waiting_time_total"] = float(ped)
            metrics["pedestrian_waiting_time_mean"] = float(ped / dep_p) if dep_p else 0.0
            metrics["pedestrians_departed"], metrics["pedestrians_arrived"] = float(dep_p), float(arr_p)
        if "co2" in self.objective_names:
            metrics["co2_emitted_kg"] = sum(last.co2_mg for last in self._last) / 1e6
        return metrics

    # ------------------------------------------------------------------------------------- misc
    def render(self) -> None:
        """Nothing to draw: with ``gui=True`` (``render_mode="human"``) sumo-gui shows the simulation."""
        return None

    def close(self) -> None:
        """Stop SUMO (frees the process-wide libsumo slot) and delete temporary files."""
        self.agents = []
        self._sim.close()
        self._api = None
        self._route_for_episode = None
        if self._finalizer is not None:
            self._finalizer()
            self._finalizer = None
            self._tmpdir = None

    def __del__(self) -> None:
        try:
            self._sim.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

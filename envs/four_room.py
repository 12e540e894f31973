"""Two-agent Four-Room: a PettingZoo ``ParallelEnv`` with vector (multi-objective) rewards.

This is the multi-agent Four-Room of the paper (Section 5.1), built on the 13×13 layout of
MO-Gymnasium's ``four-room-v0`` (same walls, same 12 objects of 3 types, goal at the top right).
It is a re-implementation: MO-Gymnasium is not imported at run time.

Conventions
-----------
- **Coordinates** are MO-Gymnasium's: a cell is ``(row, col)``, row 0 at the top, col 0 at the left.
  The paper's observation ``[x, y]`` is this pair, in this order (MO-Gymnasium's observation also
  starts with ``[row, col]``).
- **Actions** (``Discrete(4)``) mean what they mean in MO-Gymnasium: ``0`` = left (col - 1),
  ``1`` = up (row - 1), ``2`` = right (col + 1), ``3`` = down (row + 1). A move into a wall or off
  the grid leaves the agent where it is. Both agents may share a cell; they never block each other.
- **Objects** are numbered column by column, then row by row (MO-Gymnasium's order), so the flags of
  the ``"full"`` observation line up with MO-Gymnasium's. Types: ``0`` blue square, ``1`` green
  triangle, ``2`` red circle (MO-Gymnasium's ``"1"``, ``"2"``, ``"3"``).
- **Rewards** are ``float32`` arrays of shape ``(3,)`` (MO-Gymnasium / MOMAland): the one-hot of the
  object type the agent collects this step, ``goal_reward`` when it enters the goal, else zeros.
- **Competition**: an object goes to the first agent that steps on it and then disappears for both.
  If both agents enter the cell of a present object in the same step, the agent with the lower
  index in ``possible_agents`` (``agent_0``) gets it; the other one gets zeros. The rule depends on
  the agent index only, never on the order of the keys of the ``actions`` dict.
- **Episode end**: an agent that enters the goal is terminated and removed from ``env.agents``
  (PettingZoo semantics; it stays drawn on the goal). The episode ends when both agents have
  reached the goal, or after ``max_steps`` calls to :meth:`FourRoomParallelEnv.step`, where every
  agent still in ``env.agents`` is truncated (``truncated=True``, ``terminated=False``). An agent
  that enters the goal on the last step is terminated, not truncated.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import logger, spaces
from pettingzoo import ParallelEnv

if TYPE_CHECKING:  # numba (and what it imports) loads with the first batch, not with the env
    from sfgpi_envs.four_room_dynamics import FourRoomEpisodes, PackedDynamics

__all__ = [
    "AGENT_IDS",
    "DEFAULT_STARTS",
    "DOWN",
    "GOAL",
    "LAYOUT",
    "LEFT",
    "MAZE",
    "OBJECT_TYPE_NAMES",
    "RIGHT",
    "UP",
    "FourRoomParallelEnv",
    "Layout",
    "parallel_env",
]

#: The layout, one string per row: ``X`` wall, ``G`` goal, ``1``/``2``/``3`` an object of type 0/1/2, ``.`` empty.
MAZE: tuple[str, ...] = (
    "1....2X.....G",
    "......X......",
    "......1......",
    ".............",
    "......X......",
    "2....3X......",
    "XX3.XXXXX.1XX",
    "......X2....3",
    "......X......",
    ".............",
    "......2......",
    "......X......",
    "......X3....1",
)
HEIGHT: int = len(MAZE)
WIDTH: int = len(MAZE[0])
#: Goal cell ``(row, col)``.
GOAL: tuple[int, int] = next((r, c) for r, row in enumerate(MAZE) for c, ch in enumerate(row) if ch == "G")
#: Names of the three objectives / object types, in reward order.
OBJECT_TYPE_NAMES: tuple[str, str, str] = ("blue square", "green triangle", "red circle")
N_OBJECTIVES: int = 3

LEFT, UP, RIGHT, DOWN = 0, 1, 2, 3
_MOVES: tuple[tuple[int, int], ...] = ((0, -1), (-1, 0), (0, 1), (1, 0))  # (d_row, d_col) per action

AGENT_IDS: tuple[str, str] = ("agent_0", "agent_1")
#: Default starts: agent_0 at MO-Gymnasium's single-agent start, agent_1 in the bottom-right room.
DEFAULT_STARTS: tuple[tuple[int, int], tuple[int, int]] = ((12, 0), (12, 11))

OBSERVATION_MODES: tuple[str, str, str] = ("xy", "own", "full")

# Rendering: pixels per cell and RGB colours.
_CELL_PX = 20
_WHITE = (255, 255, 255)
_GRID = (225, 225, 225)
_WALL = (0, 0, 0)
_GOAL_COLOUR = (255, 200, 0)
_OBJECT_COLOURS = ((0, 0, 255), (0, 128, 0), (255, 0, 0))  # blue square, green triangle, red circle
_AGENT_COLOURS = ((90, 90, 90), (200, 0, 200))  # agent_0 grey (left half), agent_1 magenta (right half)


def _layout() -> tuple[frozenset[tuple[int, int]], tuple[tuple[int, int], ...], tuple[int, ...]]:
    """Walls, object cells (MO-Gymnasium order: column-major) and object types, parsed from :data:`MAZE`."""
    walls = frozenset((r, c) for r, row in enumerate(MAZE) for c, ch in enumerate(row) if ch == "X")
    cells, types = [], []
    for c in range(WIDTH):
        for r in range(HEIGHT):
            if MAZE[r][c] in "123":
                cells.append((r, c))
                types.append(int(MAZE[r][c]) - 1)
    return walls, tuple(cells), tuple(types)


WALLS, OBJECT_CELLS, OBJECT_TYPES = _layout()
N_OBJECTS: int = len(OBJECT_CELLS)


@dataclass(frozen=True)
class Layout:
    """
    The grid as lookup tables; a cell is the integer ``row * width + col``.

    :param next_cell: shape ``(cells, 4)``: where each action leads from each cell (the cell itself into a wall)
    :param object_at: shape ``(cells,)``: the object on each cell, ``-1`` where none
    :param object_type: shape ``(objects,)``: each object's type, the objective it rewards
    :param goal_cell: the goal
    :param xy: shape ``(cells, 2)``: each cell's ``(row, col)``, int64
    """

    next_cell: np.ndarray
    object_at: np.ndarray
    object_type: np.ndarray
    goal_cell: int
    xy: np.ndarray


def _move(cell: int, action: int) -> int:
    """Where ``action`` leads from ``cell`` (``row * WIDTH + col``): the cell itself into a wall or off the grid."""
    row, col = divmod(cell, WIDTH)
    d_row, d_col = _MOVES[action]
    r, c = row + d_row, col + d_col
    if not (0 <= r < HEIGHT and 0 <= c < WIDTH) or (r, c) in WALLS:
        return cell
    return r * WIDTH + c


def _tables() -> Layout:
    """The grid's lookup tables (see :class:`Layout`)."""
    n_cells = HEIGHT * WIDTH
    object_at = np.full(n_cells, -1, dtype=np.int64)
    for k, (r, c) in enumerate(OBJECT_CELLS):
        object_at[r * WIDTH + c] = k
    next_cell = np.array([[_move(cell, action) for action in range(4)] for cell in range(n_cells)], dtype=np.int64)
    xy = np.array([divmod(cell, WIDTH) for cell in range(n_cells)], dtype=np.int64)
    object_type = np.array(OBJECT_TYPES, dtype=np.int64)
    for table in (next_cell, object_at, object_type, xy):
        table.flags.writeable = False
    return Layout(next_cell, object_at, object_type, GOAL[0] * WIDTH + GOAL[1], xy)


#: The grid's tables: the env's step reads them as tuples (one episode: Python indexes those faster), and
#: :meth:`FourRoomParallelEnv.batched_episodes` as arrays.
LAYOUT: Layout = _tables()


class FourRoomParallelEnv(ParallelEnv):
    """Two agents compete for 12 objects of 3 types in the Four-Room grid, then walk to the goal.

    :param starts: start cell ``(row, col)`` of each agent, either a sequence ordered like
        ``possible_agents`` or a mapping ``{agent: (row, col)}``. Defaults to :data:`DEFAULT_STARTS`.
        A start must be inside the grid and not on a wall, an object or the goal.
    :param goal_reward: reward vector (shape ``(3,)``, finite) given to an agent when it enters the goal.
    :param max_steps: number of steps after which every remaining agent is truncated.
    :param observation_mode: ``"xy"`` (the paper): the agent's own ``[row, col]``,
        ``MultiDiscrete([13, 13])``; ``"own"``: ``[row, col]`` followed by 12 flags, 1 when this agent has
        collected the object (what it knows of its own progress; the other agent stays unobserved);
        ``"full"``: ``[row, col]`` followed by 12 flags, 1 when the object is gone (collected by either agent).
        The last two are ``MultiDiscrete([13, 13] + [2] * 12)``. Observations are ``int64`` arrays.
    :param render_mode: ``None`` or ``"rgb_array"`` (:meth:`render` returns an ``(H, W, 3)`` ``uint8`` image).
    """

    metadata: dict[str, Any] = {
        "render_modes": ["rgb_array"],
        "name": "four_room_v0",
        "is_parallelizable": True,
        "render_fps": 4,
    }

    def __init__(
        self,
        starts: Sequence[tuple[int, int]] | Mapping[str, tuple[int, int]] | None = None,
        goal_reward: Sequence[float] | np.ndarray = (1.0, 1.0, 1.0),
        max_steps: int = 200,
        observation_mode: str = "xy",
        render_mode: str | None = None,
    ) -> None:
        self.possible_agents: list[str] = list(AGENT_IDS)
        self.agents: list[str] = []
        self._index: dict[str, int] = {agent: i for i, agent in enumerate(self.possible_agents)}

        self.starts: tuple[tuple[int, int], ...] = self._check_starts(starts)
        self.goal_reward: np.ndarray = self._check_goal_reward(goal_reward)
        if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        self.max_steps: int = int(max_steps)
        if observation_mode not in OBSERVATION_MODES:
            raise ValueError(f"unknown observation_mode {observation_mode!r}; expected one of {OBSERVATION_MODES}")
        self.observation_mode: str = observation_mode
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"unsupported render_mode {render_mode!r}; expected None or one of {self.metadata['render_modes']}"
            )
        self.render_mode: str | None = render_mode

        self._build_spaces()
        self._build_tables()

        # Episode state (reset() restores it).
        self._cells: list[int] = [r * WIDTH + c for r, c in self.starts]
        self._present: list[bool] = [True] * N_OBJECTS
        self._gone = np.zeros(N_OBJECTS, dtype=np.int64)  # the "full" observation's flags
        self._collected: list[np.ndarray] = [np.zeros(N_OBJECTS, dtype=bool) for _ in self.possible_agents]
        self._t: int = 0

        self._background: np.ndarray | None = None
        self._masks: dict[str, np.ndarray] | None = None

    # ------------------------------------------------------------------ validation / tables
    def _build_spaces(self) -> None:
        """The spaces, built once: the ``*_space(agent)`` methods return these same objects."""
        nvec = [HEIGHT, WIDTH] + ([2] * N_OBJECTS if self.observation_mode != "xy" else [])
        self.observation_spaces: dict[str, spaces.MultiDiscrete] = {
            agent: spaces.MultiDiscrete(nvec, dtype=np.int64) for agent in self.possible_agents
        }
        self.action_spaces: dict[str, spaces.Discrete] = {agent: spaces.Discrete(4) for agent in self.possible_agents}
        low = np.minimum(self.goal_reward, 0.0).astype(np.float32)
        high = np.maximum(self.goal_reward, 1.0).astype(np.float32)
        self.reward_spaces: dict[str, spaces.Box] = {
            agent: spaces.Box(low=low, high=high, shape=(N_OBJECTIVES,), dtype=np.float32)
            for agent in self.possible_agents
        }

    def _build_tables(self) -> None:
        """Flat tables for the hot loop (:data:`LAYOUT`'s): a cell is the int ``row * WIDTH + col``."""
        self._next: tuple[tuple[int, ...], ...] = tuple(tuple(moves) for moves in LAYOUT.next_cell.tolist())
        self._obj_at: tuple[int, ...] = tuple(LAYOUT.object_at.tolist())
        self._goal_cell: int = LAYOUT.goal_cell
        self._xy: tuple[np.ndarray, ...] = tuple(LAYOUT.xy)
        eye = np.eye(N_OBJECTIVES, dtype=np.float32)
        self._object_reward: tuple[np.ndarray, ...] = tuple(eye[t] for t in OBJECT_TYPES)
        self._zero_reward = np.zeros(N_OBJECTIVES, dtype=np.float32)

    def _check_starts(
        self, starts: Sequence[tuple[int, int]] | Mapping[str, tuple[int, int]] | None
    ) -> tuple[tuple[int, int], ...]:
        if starts is None:
            return DEFAULT_STARTS
        if isinstance(starts, Mapping):
            if set(starts) != set(self.possible_agents):
                raise ValueError(
                    f"starts must have one entry per agent {self.possible_agents}, got keys {sorted(starts)}"
                )
            starts = [starts[agent] for agent in self.possible_agents]
        starts = list(starts)
        if len(starts) != len(self.possible_agents):
            raise ValueError(f"starts must give {len(self.possible_agents)} cells (one per agent), got {len(starts)}")
        checked = []
        for agent, cell in zip(self.possible_agents, starts, strict=True):
            try:
                row, col = (int(v) for v in cell)
            except (TypeError, ValueError):
                raise ValueError(f"start of {agent} must be a (row, col) pair of ints, got {cell!r}") from None
            if not (0 <= row < HEIGHT and 0 <= col < WIDTH):
                raise ValueError(f"start of {agent} {(row, col)} is outside the {HEIGHT}x{WIDTH} grid")
            if (row, col) in WALLS:
                raise ValueError(f"start of {agent} {(row, col)} is on a wall")
            if (row, col) == GOAL:
                raise ValueError(f"start of {agent} {(row, col)} is the goal")
            if (row, col) in OBJECT_CELLS:
                raise ValueError(f"start of {agent} {(row, col)} holds an object")
            checked.append((row, col))
        return tuple(checked)

    @staticmethod
    def _check_goal_reward(goal_reward: Sequence[float] | np.ndarray) -> np.ndarray:
        try:
            arr = np.asarray(goal_reward, dtype=np.float32)
        except (TypeError, ValueError):
            raise ValueError(f"goal_reward must be a numeric vector of shape (3,), got {goal_reward!r}") from None
        if arr.shape != (N_OBJECTIVES,):
            raise ValueError(f"goal_reward must have shape ({N_OBJECTIVES},), got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"goal_reward must be finite, got {arr}")
        arr.flags.writeable = False
        return arr

    def batched_episodes(self, n: int) -> FourRoomEpisodes:
        """
        ``n`` episodes of this env as arrays, stepped together by one compiled call
        (:class:`~sb3_sfgpi.common.rollouts.BatchedEpisodes`): each is the episode this env runs from a reset.
        """
        from sfgpi_envs.four_room_dynamics import FourRoomEpisodes

        starts = [r * WIDTH + c for r, c in self.starts]
        return FourRoomEpisodes(
            LAYOUT, starts, self.goal_reward, self.max_steps, self.observation_mode, self.possible_agents, n
        )

    def packed_dynamics(self) -> PackedDynamics:
        """
        The env's step compiled over its state packed in integers, for compiled training loops
        (:class:`~sfgpi_envs.four_room_dynamics.PackedDynamics`): the step, the constant model and the current
        episode's state; :meth:`restore_packed_state` makes the env continue from a state the step advanced.
        """
        from sfgpi_envs.four_room_dynamics import (
            PackedDynamics,
            pack_model,
            pack_state,
            packed_episode_step,
            packed_step,
        )

        live = [agent in self.agents for agent in self.possible_agents]
        mode = OBSERVATION_MODES.index(self.observation_mode)
        model = pack_model(LAYOUT, len(self.possible_agents), self.max_steps, mode)
        state = pack_state(self._t, self._cells, live, self._present, self._collected)
        return PackedDynamics(packed_step, packed_episode_step, model, self.goal_reward.copy(), state)

    def restore_packed_state(self, state: np.ndarray) -> None:
        """Continue from a packed state of :meth:`packed_dynamics` (as the packed step left it)."""
        from sfgpi_envs.four_room_dynamics import unpack_state

        self._t, self._cells, live, self._present, collected = unpack_state(state, len(self.possible_agents), N_OBJECTS)
        self.agents = [agent for agent, is_live in zip(self.possible_agents, live, strict=True) if is_live]
        self._gone[:] = ~np.array(self._present)
        for mine, theirs in zip(self._collected, collected, strict=True):
            mine[:] = theirs

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.MultiDiscrete:
        """Observation space of ``agent`` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        """Action space of ``agent``: ``Discrete(4)``, left/up/right/down (the same object on every call)."""
        return self.action_spaces[agent]

    def reward_space(self, agent: str) -> spaces.Box:
        """Reward space of ``agent``: ``float32`` ``Box`` of shape ``(3,)`` holding the one-hots and ``goal_reward``."""
        return self.reward_spaces[agent]

    # ------------------------------------------------------------------ API
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Put the agents on their starts and all objects back.

        The dynamics are deterministic; ``seed`` seeds the action spaces (agent ``i`` with ``seed + i``)
        so that random-action rollouts are reproducible.

        :param seed: optional seed.
        :param options: unused.
        :return: observations and infos, keyed by agent.
        """
        if seed is not None:
            for i, agent in enumerate(self.possible_agents):
                self.action_spaces[agent].seed(seed + i)
        self.agents = list(self.possible_agents)
        self._cells = [r * WIDTH + c for r, c in self.starts]
        self._present = [True] * N_OBJECTS
        self._gone[:] = 0
        for collected in self._collected:
            collected[:] = False
        self._t = 0
        observations = {agent: self._observe(i) for i, agent in enumerate(self.possible_agents)}
        infos = {agent: {"collected": self._collected[i].copy()} for i, agent in enumerate(self.possible_agents)}
        return observations, infos

    def step(
        self, actions: Mapping[str, int]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, np.ndarray],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Move every live agent at once.

        Agents are processed in index order, which implements the tie rule (``agent_0`` wins an object
        both agents enter in the same step). Keys of ``actions`` for agents no longer in ``env.agents``
        are ignored.

        :param actions: an action in ``{0, 1, 2, 3}`` for every agent in ``env.agents``.
        :return: observations, rewards (``float32``, shape ``(3,)``), terminations, truncations and infos
            (``{"collected": bool array (12,)}``, the objects this agent has collected so far), keyed by the
            agents that were live before this step.
        """
        agents = self.agents
        if not agents:
            raise RuntimeError("no live agents: call reset() before step() (the episode is over or not started)")
        chosen = self._checked_actions(actions)  # every action is validated before any state changes
        self._t += 1
        truncate = self._t >= self.max_steps
        rewards: dict[str, np.ndarray] = {}
        terminations: dict[str, bool] = {}
        truncations: dict[str, bool] = {}
        survivors = []
        for agent, action in zip(agents, chosen, strict=True):
            rewards[agent], terminations[agent] = self._advance(self._index[agent], action)
            truncations[agent] = truncate and not terminations[agent]
            if not (terminations[agent] or truncate):
                survivors.append(agent)

        # Observations after every agent has moved, so the "full" flags show this step's collections.
        observations = {agent: self._observe(self._index[agent]) for agent in agents}
        infos = {agent: {"collected": self._collected[self._index[agent]].copy()} for agent in agents}
        self.agents = survivors
        return observations, rewards, terminations, truncations, infos

    def _checked_actions(self, actions: Mapping[str, int]) -> list[int]:
        chosen = []
        for agent in self.agents:
            try:
                action = actions[agent]
            except KeyError:
                raise ValueError(f"no action for live agent {agent!r}; got actions for {list(actions)}") from None
            if not 0 <= action < 4:
                raise ValueError(
                    f"invalid action {action!r} for {agent!r}; expected 0 (left), 1 (up), 2 (right), 3 (down)"
                )
            chosen.append(action)
        return chosen

    def _advance(self, i: int, action: int) -> tuple[np.ndarray, bool]:
        """Move agent ``i`` and collect the object it enters, if still there.

        :return: its reward and whether it reached the goal.
        """
        cell = self._next[self._cells[i]][action]
        self._cells[i] = cell
        if cell == self._goal_cell:
            return self.goal_reward.copy(), True
        k = self._obj_at[cell]
        if k >= 0 and self._present[k]:
            self._present[k] = False
            self._gone[k] = 1
            self._collected[i][k] = True
            return self._object_reward[k].copy(), False
        return self._zero_reward.copy(), False

    def _observe(self, agent: int) -> np.ndarray:
        cell = self._cells[agent]
        if self.observation_mode == "xy":
            return self._xy[cell].copy()
        flags = self._gone if self.observation_mode == "full" else self._collected[agent]
        return np.concatenate((self._xy[cell], flags), dtype=np.int64)

    @property
    def agent_positions(self) -> dict[str, tuple[int, int]]:
        """Current cell ``(row, col)`` of every agent, including agents that have already reached the goal."""
        return {agent: divmod(self._cells[i], WIDTH) for i, agent in enumerate(self.possible_agents)}

    @property
    def objects_present(self) -> np.ndarray:
        """Boolean array (12,): which objects are still on the grid (order of :data:`OBJECT_CELLS`)."""
        return np.array(self._present, dtype=bool)

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """Draw the grid: walls black, the goal gold, present objects (blue squares, green triangles, red
        circles), agent_0 as a grey disc in the left half of its cell, agent_1 as a magenta disc in the right half.

        :return: an ``(H, W, 3)`` ``uint8`` image (``H = W = 13 * 20``) when ``render_mode="rgb_array"``, else ``None``.
        """
        if self.render_mode is None:
            logger.warn("render() called without a render_mode; pass render_mode='rgb_array' to the constructor.")
            return None
        if self._background is None or self._masks is None:
            self._background, self._masks = self._draw_background()
        img = self._background.copy()
        px = _CELL_PX
        masks = self._masks
        for k, (r, c) in enumerate(OBJECT_CELLS):
            if self._present[k]:
                t = OBJECT_TYPES[k]
                img[r * px : (r + 1) * px, c * px : (c + 1) * px][masks[f"object{t}"]] = _OBJECT_COLOURS[t]
        for i, cell in enumerate(self._cells):
            r, c = divmod(cell, WIDTH)
            img[r * px : (r + 1) * px, c * px : (c + 1) * px][masks[f"agent{i}"]] = _AGENT_COLOURS[i]
        return img

    @staticmethod
    def _draw_background() -> tuple[np.ndarray, dict[str, np.ndarray]]:
        px = _CELL_PX
        v, u = np.mgrid[0:px, 0:px]
        v = (v + 0.5) / px  # vertical position in the cell, 0 (top) .. 1 (bottom)
        u = (u + 0.5) / px  # horizontal position in the cell, 0 (left) .. 1 (right)
        masks = {
            "object0": (np.abs(u - 0.5) <= 0.35) & (np.abs(v - 0.5) <= 0.35),
            "object1": (v >= 0.12) & (v <= 0.88) & (np.abs(u - 0.5) <= 0.4 * (v - 0.12) / 0.76),
            "object2": (u - 0.5) ** 2 + (v - 0.5) ** 2 <= 0.4**2,
            "agent0": (u - 0.26) ** 2 + (v - 0.5) ** 2 <= 0.25**2,
            "agent1": (u - 0.74) ** 2 + (v - 0.5) ** 2 <= 0.25**2,
        }
        img = np.empty((HEIGHT * px, WIDTH * px, 3), dtype=np.uint8)
        img[:] = _WHITE
        img[::px, :] = _GRID
        img[:, ::px] = _GRID
        for r, c in WALLS:
            img[r * px : (r + 1) * px, c * px : (c + 1) * px] = _WALL
        r, c = GOAL
        img[r * px : (r + 1) * px, c * px : (c + 1) * px] = _GOAL_COLOUR
        return img, masks

    def close(self) -> None:
        """Nothing to release (no window)."""


def parallel_env(**kwargs: Any) -> FourRoomParallelEnv:
    """PettingZoo-style constructor: ``parallel_env(**kwargs)`` is ``FourRoomParallelEnv(**kwargs)``."""
    return FourRoomParallelEnv(**kwargs)

"""Green/yellow phase logic of one traffic light under agent control.

:class:`SignalProgram` extracts the green phases (two or more) and their yellow transitions from a
static program; :class:`SignalController` is a small state machine that shows the green an agent asks
for (the next one of the cycle, or any one) and enforces the minimum and maximum green times and the
yellow time. It never touches SUMO: it returns the state string to show, and
the environment sends it with ``trafficlight.setRedYellowGreenState``. That call puts the light on
SUMO's single-phase "online" program, which never advances by itself.

Time is in whole simulated seconds (the environment steps SUMO one second at a time).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

KEEP = 0
"""Action: keep the current green phase."""

CHANGE = 1
"""Action: switch to the next green phase of the cycle (through a yellow phase)."""


def is_green(state: str) -> bool:
    """Whether a phase state is a green phase: some links green, none yellow."""
    return any(c in "Gg" for c in state) and not any(c in "yYuo" for c in state)


def _is_yellow(state: str) -> bool:
    return any(c in "yY" for c in state)


def _derive_yellow(green: str, following: str) -> str:
    """Yellow state between two greens: links green now and red next turn yellow."""
    return "".join("y" if a in "Gg" and b in "rs" else a for a, b in zip(green, following, strict=True))


@dataclass(frozen=True)
class SignalProgram:
    """The green phases of a traffic light and the yellow state shown after each.

    :param greens: state strings of the green phases, in program order.
    :param yellows: ``yellows[i]`` is the state shown between ``greens[i]`` and the next green.
    """

    greens: tuple[str, ...]
    yellows: tuple[str, ...]

    @classmethod
    def from_phases(cls, states: Sequence[str], tls_id: str = "?") -> SignalProgram:
        """Build from the phase states of a program.

        A green phase has green links and no yellow ones. The yellow after green ``i`` is the first
        yellow phase between it and the next green; if there is none it is derived (links that are
        green now and red in the next green turn yellow).

        :param states: phase state strings, in cycle order.
        :param tls_id: traffic-light id, for error messages.
        :return: the program.
        :raises ValueError: if the program has fewer than two green phases (nothing to choose).
        """
        states = list(states)
        green_idx = [i for i, s in enumerate(states) if is_green(s)]
        if len(green_idx) < 2:
            raise ValueError(
                f"traffic light {tls_id!r} needs at least 2 green phases to control, found {len(green_idx)} in {states}"
            )
        greens, yellows = [], []
        for k, i in enumerate(green_idx):
            j = green_idx[(k + 1) % len(green_idx)]
            between = [states[m % len(states)] for m in range(i + 1, j if j > i else j + len(states))]
            yellow = next((s for s in between if _is_yellow(s)), None)
            greens.append(states[i])
            yellows.append(yellow if yellow is not None else _derive_yellow(states[i], states[j]))
        return cls(tuple(greens), tuple(yellows))

    def transition(self, green: int, target: int) -> str:
        """Yellow state shown between green ``green`` and green ``target``.

        :param green: index of the green shown.
        :param target: index of the green that follows.
        :return: the program's yellow when ``target`` follows ``green`` in the cycle, else a derived one.
        """
        if target == (green + 1) % len(self.greens):
            return self.yellows[green]
        return _derive_yellow(self.greens[green], self.greens[target])

    def lookup(self) -> dict[str, tuple[int, bool]]:
        """Map each state string to ``(green index it shows or leads to, is_yellow)``.

        :return: the mapping (yellow ``i`` leads to green ``i + 1``).
        """
        table = {y: ((i + 1) % len(self.greens), True) for i, y in enumerate(self.yellows)}
        table.update({g: (i, False) for i, g in enumerate(self.greens)})
        return table


class SignalController:
    """Controller of one light: minimum/maximum green and a fixed yellow time.

    * a change (:meth:`act` with :data:`CHANGE`, or :meth:`request` of another green) before
      ``min_green`` seconds of green is ignored (the green is kept), or, with ``defer_early``, made by
      :meth:`tick` when the green reaches ``min_green`` seconds, unless a later decision asks otherwise;
    * a green that reaches ``max_green`` seconds is ended by :meth:`tick` whatever the agent wants
      (the next green of the cycle follows, or the one :attr:`after_max_green` chooses);
    * between two greens the yellow state is shown for exactly ``yellow_time`` seconds;
    * during yellow, actions are ignored.

    :param program: green and yellow states.
    :param min_green: minimum green time [s].
    :param max_green: maximum green time [s].
    :param yellow_time: yellow time [s] (at least 1).
    :param defer_early: make a change asked for too early when the minimum green is reached, instead of ignoring it.
    """

    __slots__ = (
        "program",
        "min_green",
        "max_green",
        "yellow_time",
        "defer_early",
        "green",
        "in_yellow",
        "green_start",
        "yellow_end",
        "deferred",
        "after_max_green",
    )

    def __init__(
        self, program: SignalProgram, min_green: int, max_green: int, yellow_time: int, defer_early: bool = False
    ) -> None:
        self.program = program
        self.min_green = min_green
        self.max_green = max_green
        self.yellow_time = yellow_time
        self.defer_early = defer_early
        self.deferred: int | None = None
        """The green asked for before the minimum green, made when it is reached (``defer_early`` only)."""
        self.green = 0
        """Index of the green phase shown, or (during yellow) the one coming next."""
        self.in_yellow = False
        self.green_start = 0
        """Time the current green started (during yellow: when it will start)."""
        self.yellow_end = 0
        self.after_max_green: Callable[[int], int] | None = None
        """Given the green ended by ``max_green``, the (other) green that follows; ``None``: the next of the cycle."""

    def reset(self, time: int, green: int = 0) -> str:
        """Start green phase ``green`` at ``time``.

        :param time: current simulation time [s].
        :param green: green phase index.
        :return: the state string to show.
        """
        self.green = green
        self.in_yellow = False
        self.deferred = None
        self.green_start = time
        return self.program.greens[green]

    def elapsed_green(self, time: int) -> int:
        """Seconds the current green has been shown (0 during yellow).

        :param time: current simulation time [s].
        :return: elapsed green time.
        """
        return 0 if self.in_yellow else time - self.green_start

    def act(self, action: int, time: int) -> str | None:
        """Apply a keep/change decision at ``time``.

        :param action: :data:`KEEP` or :data:`CHANGE` (to the next green of the cycle).
        :param time: current simulation time [s].
        :return: the new state string if the light changes now, else ``None``.
        """
        return self.request(self._next() if action == CHANGE else self.green, time)

    def request(self, green: int, time: int) -> str | None:
        """Ask for green phase ``green`` at ``time``: the current one is kept, another one follows a yellow.

        :param green: index of the green phase wanted.
        :param time: current simulation time [s].
        :return: the new state string if the light changes now, else ``None``.
        """
        if self.in_yellow:
            return None
        early = time - self.green_start < self.min_green
        self.deferred = green if early and self.defer_early and green != self.green else None
        if green != self.green and not early:
            return self._start_yellow(time, green)
        return None

    def tick(self, time: int) -> str | None:
        """Advance the phase logic to ``time`` (called before each simulated second).

        Ends a finished yellow, makes a deferred change once the green reached ``min_green`` and forces the change
        of a green that reached ``max_green``.

        :param time: current simulation time [s].
        :return: the new state string if the light changes now, else ``None``.
        """
        if self.in_yellow:
            if time >= self.yellow_end:
                self.in_yellow = False
                self.green_start = time
                return self.program.greens[self.green]
            return None
        if self.deferred is not None and time - self.green_start >= self.min_green:
            return self._start_yellow(time, self.deferred)
        if time - self.green_start >= self.max_green:
            after = self.after_max_green
            return self._start_yellow(time, self._next() if after is None else after(self.green))
        return None

    def _next(self) -> int:
        return (self.green + 1) % len(self.program.greens)

    def _start_yellow(self, time: int, target: int) -> str:
        state = self.program.transition(self.green, target)
        self.green = target
        self.deferred = None
        self.in_yellow = True
        self.yellow_end = time + self.yellow_time
        self.green_start = self.yellow_end
        return state

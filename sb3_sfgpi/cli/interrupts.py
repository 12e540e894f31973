"""Ctrl-C and SIGTERM stop a training at once, and are reported as themselves wherever they land."""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback


class Interrupts(BaseCallback):
    """
    Ctrl-C (SIGINT) and SIGTERM (``kill``, a batch scheduler) stop training in one way while :meth:`caught` is open: a
    ``KeyboardInterrupt`` raised at once (``"SIGTERM"`` its message for SIGTERM), and kept in :attr:`received`.

    An interrupt can land where it does not propagate or changes shape: in a finalizer (Python prints it as an
    ignored exception and goes on) or while numba unboxes a compiled call's arguments (it comes out as a ``TypeError``,
    and a compilation it cut short fails later with a ``RuntimeError``). So once a signal came, its ignored report is
    not printed, the training stops at its next joint step (this is a runner-level callback: pass it to ``learn``),
    and whatever the training raises is the interrupt in :attr:`received`.
    """

    #: its ``on_step`` reads nothing of the steps: the runner may show it compiled steps in batches
    takes_steps_in_batches = True

    def __init__(self) -> None:
        super().__init__()
        self.received: KeyboardInterrupt | None = None

    def _on_step(self) -> bool:
        return self.received is None

    @contextmanager
    def caught(self) -> Iterator[Interrupts]:
        """
        SIGTERM and SIGINT handled as above in the ``with`` block; off the main thread, signals stay as they are, and
        so does a SIGINT that was ignored (a job a shell script started in the background).
        """

        def interrupt(signum: int, frame: Any) -> None:
            self.received = KeyboardInterrupt("SIGTERM") if signum == signal.SIGTERM else KeyboardInterrupt()
            raise self.received

        def unraisable(report: Any) -> None:
            if self.received is None or report.exc_value is not self.received:
                previous_hook(report)

        numbers = [signal.SIGTERM]
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where it is ignored (a background job)
            numbers.append(signal.SIGINT)
        try:
            previous = {number: signal.signal(number, interrupt) for number in numbers}
        except ValueError:  # not the main thread
            yield self
            return
        previous_hook, sys.unraisablehook = sys.unraisablehook, unraisable
        try:
            yield self
        finally:
            sys.unraisablehook = previous_hook
            for number, handler in previous.items():
                signal.signal(number, handler)

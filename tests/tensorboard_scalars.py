"""Reading back the TensorBoard scalars a run wrote (every event file of a folder, as TensorBoard shows them)."""

from __future__ import annotations

from pathlib import Path

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator


def scalar_steps(folder: Path, tag: str) -> list[int]:
    """The steps at which ``tag`` was logged in ``folder``, over all its event files, in the order written."""
    steps = []
    for events in sorted(folder.glob("events.out.tfevents.*"), key=lambda path: path.stat().st_mtime_ns):
        accumulator = EventAccumulator(str(events))
        accumulator.Reload()
        if tag in accumulator.Tags()["scalars"]:
            steps += [event.step for event in accumulator.Scalars(tag)]
    return steps

"""The two ways a command fails: a user mistake (exit code 2) and a run stopped by an error (exit code 1)."""

from __future__ import annotations

import os
import threading


class UsageError(Exception):
    """A user mistake: reported as one line on stderr with exit code 2."""


class TrainingStopped(Exception):
    """
    Training stopped by an error (the simulator died, the disk is full, Ctrl-C or SIGTERM): reported as one line
    with exit code 1, as an ``OSError`` outside training is.
    """


def report_writer_errors_once() -> None:
    """
    Leave a failed TensorBoard write (a full disk) to the one line of the command's error.

    TensorBoard writes event files from a thread of its own: where a write fails, the thread prints its traceback,
    then the training loop gets the same ``OSError`` at its next write, which names no file (the write that failed
    was to an open file). Here the thread's error gets the event file's name and no traceback of its own; every other
    thread's error goes to the hook that was there before.
    """
    previous = threading.excepthook
    if getattr(previous, "reports_writer_errors", False):
        return

    def hook(args: threading.ExceptHookArgs) -> None:
        if type(args.thread).__name__ == "_AsyncWriterThread" and isinstance(args.exc_value, OSError):
            if args.exc_value.filename is None:
                writer = getattr(getattr(args.thread, "_record_writer", None), "_writer", None)
                name = getattr(writer, "filename", None)  # bytes in TensorBoard's file layer
                args.exc_value.filename = os.fsdecode(name) if name is not None else None
            return
        previous(args)

    hook.reports_writer_errors = True  # type: ignore[attr-defined]
    threading.excepthook = hook

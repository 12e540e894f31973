"""The two ways a command fails: a user mistake (exit code 2) and a run stopped by an error (exit code 1)."""


class UsageError(Exception):
    """A user mistake: reported as one line on stderr with exit code 2."""


class TrainingStopped(Exception):
    """
    Training stopped by an error (the simulator died, the disk is full, Ctrl-C or SIGTERM): reported as one line
    with exit code 1, as an ``OSError`` outside training is.
    """

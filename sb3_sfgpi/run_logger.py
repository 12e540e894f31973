"""The runner's Stable-Baselines3 logger on a run directory's ``logs/``, continued where the checkpoint left it.

Apart from :mod:`sb3_sfgpi.run_directory` (plain data) so that reading a run needs neither torch nor SB3.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from stable_baselines3.common.logger import CSVOutputFormat, Logger, TensorBoardOutputFormat

from sb3_sfgpi.common.serialization import atomic_write_bytes
from sb3_sfgpi.run_directory import RunDirectory, summary_scalars


def run_logger(run_dir: RunDirectory) -> Logger:
    """
    The runner's SB3 logger on ``logs/``: ``progress.csv`` (one row per finished iteration) and TensorBoard.
    An existing ``progress.csv`` is continued, not truncated: it keeps its header and the rows of the
    iterations the checkpoint counts (those of an iteration killed before its checkpoint are dropped). The
    TensorBoard scalars are written anew from ``evaluation.json``, so that they too hold each iteration the
    checkpoint counts exactly once.
    """
    logs_dir = run_dir.logs_dir
    logs_dir.mkdir(parents=True, exist_ok=True)
    done = run_dir.read_checkpoint()["iteration"] if run_dir.has_checkpoint() else 0
    progress = _ContinuedCSV(str(logs_dir / "progress.csv"), keep_rows=done)
    for events in logs_dir.glob("events.out.tfevents.*"):
        events.unlink()
    tensorboard = TensorBoardOutputFormat(str(logs_dir))
    for row in run_dir.read_history(done) if done else []:
        scalars = summary_scalars(row)
        tensorboard.write(scalars, dict.fromkeys(scalars, ()), step=row["iteration"])
    return Logger(str(logs_dir), [progress, tensorboard])


class _ContinuedCSV(CSVOutputFormat):
    """SB3's CSV output, continuing an existing file from its header and its first ``keep_rows`` rows."""

    def __init__(self, filename: str, keep_rows: int):
        path = Path(filename)
        lines = path.read_text().splitlines(keepends=True) if path.exists() else []
        kept = lines[: 1 + keep_rows]
        if kept != lines:
            atomic_write_bytes(path, "".join(kept).encode())
        # Not SB3's __init__, which opens the file with "w+" and so truncates it; SB3 closes the file.
        self.file = open(filename, "r+" if path.exists() else "w+")
        self.file.seek(0, io.SEEK_END)
        self.keys: list[str] = next(csv.reader(kept[:1]), [])
        self.separator = ","
        self.quotechar = '"'

"""Command line: ``sb3-sfgpi train | evaluate | compare | plot | sweep`` (one module per command).

Domains (``four-room``, ``traffic``, ...) are found through the entry-point group ``sb3_sfgpi.domains``
(:mod:`sb3_sfgpi.cli.presets`). A user mistake is one line on stderr and exit code 2; training stopped by an error
(e.g. the simulator died, or Ctrl-C) is one line naming the intact checkpoint and exit code 1.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from sb3_sfgpi.cli import compare, evaluate, plot, sweep, train
from sb3_sfgpi.cli.errors import TrainingStopped, UsageError, report_writer_errors_once
from sb3_sfgpi.cli.presets import DomainPreset, available_domains, load_domain

COMMANDS = {"train": train, "evaluate": evaluate, "compare": compare, "plot": plot, "sweep": sweep}

__all__ = ["DomainPreset", "TrainingStopped", "UsageError", "available_domains", "load_domain", "main"]


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line's arguments (argparse exits with code 2 and one usage line on a malformed one)."""
    parser = argparse.ArgumentParser(prog="sb3-sfgpi", description="MA-SFOLS + GPI with Stable-Baselines3")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS.values():
        command.add_parser(sub)
    for command_parser in sub.choices.values():
        command_parser.allow_abbrev = False  # --se is not --seed: a sweep's reserved options cannot be abbreviated
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-sfgpi`` console script."""
    args = parse_args(argv)
    report_writer_errors_once()
    try:
        return COMMANDS[args.command].run(args)
    except (UsageError, ValueError) as error:
        print(f"sb3-sfgpi {args.command}: error: {error}", file=sys.stderr)
        return 2
    except (TrainingStopped, OSError) as error:  # OSError: a full disk, a file that cannot be written
        print(f"sb3-sfgpi {args.command}: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C before a command's own handling starts (train and sweep report theirs)
        print(f"sb3-sfgpi {args.command}: error: interrupted", file=sys.stderr)
        return 1

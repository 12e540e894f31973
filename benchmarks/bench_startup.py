"""Start-up of the command line: ``sb3-sfgpi --help`` and ``sb3-sfgpi plot --help`` in fresh interpreters.

Candidate: this source tree. Baseline: the source tree of the commit before the lazy imports (``git archive`` of
:data:`BASELINE_COMMIT` into a temporary folder, or of ``$SB3_SFGPI_STARTUP_BASELINE``), where ``import sb3_sfgpi``
imported every public name (torch, SB3, scipy) and the commands imported what training needs to build their parsers.
Where that commit cannot be read (no git, a shallow clone), the baseline is this tree with the same imports forced
first (``import sb3_sfgpi.masfols, sb3_sfgpi.gpi, ...``). Each side runs ``python -m sb3_sfgpi.cli ARGS`` (what the
console script runs) with ``PYTHONPATH`` on its tree, alternately, 5 times; medians, and the ratio of each round's
pair. The modules each side imports are counted once.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from benchmarks._common import ROOT, Row, baseline_tree, fmt_time, interleaved_samples, paired_ratio

#: The last commit whose ``import sb3_sfgpi`` imported everything (issue 48, item 4: start-up).
BASELINE_COMMIT = "f9373af"
#: What ``sb3_sfgpi/__init__.py`` imported eagerly before: forced first in the fallback baseline.
EAGER = (
    "import sb3_sfgpi.admission, sb3_sfgpi.callbacks, sb3_sfgpi.common.mo_callbacks, sb3_sfgpi.evaluation, "
    "sb3_sfgpi.gpi, sb3_sfgpi.masfols, sb3_sfgpi.multiagent, sb3_sfgpi.ols, sb3_sfgpi.schedules, sb3_sfgpi.sfdqn"
)
CLI = "import sys; from sb3_sfgpi.cli import main; sys.argv[0] = 'sb3-sfgpi'; sys.exit(main({argv!r}))"
COUNT = "import sys; from sb3_sfgpi.cli import parse_args\ntry: parse_args({argv!r})\nexcept SystemExit: pass\n"
COUNT += "print(len(sys.modules), file=sys.stderr)"


def _command(tree: Path, code: str, prefix: str = "") -> Callable[[], None]:
    env = {**os.environ, "PYTHONPATH": str(tree)}

    def run() -> None:
        subprocess.run([sys.executable, "-c", prefix + code], env=env, cwd=tree, capture_output=True, check=False)

    return run


def _modules(tree: Path, argv: list[str], prefix: str = "") -> int:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    code = prefix + COUNT.format(argv=argv)
    result = subprocess.run([sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True)
    return int(result.stderr.strip().splitlines()[-1])


def run(quick: bool = False) -> list[Row]:
    """Seconds of ``sb3-sfgpi --help`` and ``sb3-sfgpi plot --help``, this tree against the baseline."""
    repeats = 3 if quick else 5
    rows = []
    commit = os.environ.get("SB3_SFGPI_STARTUP_BASELINE", BASELINE_COMMIT)
    with tempfile.TemporaryDirectory(prefix="sfgpi_startup_") as folder:
        from_git = baseline_tree(Path(folder), commit)
        base, prefix = (Path(folder), "") if from_git else (ROOT, EAGER + "\n")
        what = f"commit {commit}" if from_git else "this tree with the former eager imports forced"
        for argv in (["--help"], ["plot", "--help"]):
            code = CLI.format(argv=argv)
            samples = interleaved_samples(
                {"candidate": _command(ROOT, code), "baseline": _command(base, code, prefix)}, repeats
            )
            ratio = paired_ratio(samples, "baseline", "candidate")[0]
            medians = {name: statistics.median(values) for name, values in samples.items()}
            modules = _modules(ROOT, argv), _modules(base, argv, prefix)
            rows.append(
                Row(
                    "start-up",
                    f"sb3-sfgpi {' '.join(argv)} (fresh interpreter)",
                    fmt_time(medians["candidate"]),
                    fmt_time(medians["baseline"]),
                    ratio,
                    "≥ 3×",
                    ratio >= 3,
                    f"baseline: {what}; modules imported {modules[0]} vs {modules[1]}; median of {repeats}",
                )
            )
    return rows

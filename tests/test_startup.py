"""Start-up (issue 48): a command that does not train imports neither torch nor SB3, SUMO, Ray, scipy, matplotlib
before it needs them. Each check runs in a fresh interpreter, since this one has imported them all."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import sb3_sfgpi
from sb3_sfgpi.cli import main

HEAVY = ("torch", "stable_baselines3", "libsumo", "traci", "sumolib", "ray", "scipy", "matplotlib")
TRAIN = ["train", "four-room", "--iterations", "1", "--steps-per-iteration", "100", "--no-progress"]
#: A run in seconds: few test weights and episodes, no validation, one planning sweep.
TINY = ["--set", "n_test_weights=2", "--set", "eval_episodes=1", "--set", "value_episodes=1"]
TINY += ["--set", "validation_weights=0", "--learner", "planning_sweeps=1"]

PROBE = """
import contextlib, io, json, sys
from sb3_sfgpi.cli import main, parse_args

heavy = {heavy!r}
seen = {{}}
for name, argv in {steps!r}:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            if name.startswith("main "):
                code = main(argv)
            else:
                parse_args(argv)
                code = 0
        except SystemExit as error:
            code = error.code
    seen[name] = [code, sorted(m for m in heavy if m in sys.modules)]
print(json.dumps(seen))
"""


def probe(steps: list[tuple[str, list[str]]], heavy: tuple[str, ...] = HEAVY) -> dict[str, list]:
    """Run each step in one fresh interpreter: name -> [exit code, the heavy modules imported by then]."""
    code = PROBE.format(heavy=heavy, steps=steps)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.splitlines()[-1])


def test_the_package_imports_lazily_and_keeps_its_public_names():
    code = (
        "import sys, sb3_sfgpi; v = sb3_sfgpi.__version__; names = dir(sb3_sfgpi); "
        f"print(sorted(m for m in {HEAVY!r} if m in sys.modules), v, set(sb3_sfgpi.__all__) <= set(names))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.stdout.split() == ["[]", sb3_sfgpi.__version__, "True"], result.stderr
    for name in sb3_sfgpi.__all__:
        assert getattr(sb3_sfgpi, name) is not None
    from sb3_sfgpi import SFDQN
    from sb3_sfgpi.sfdqn.sfdqn import SFDQN as defined

    assert SFDQN is defined
    with pytest.raises(AttributeError, match="no attribute 'SFDQNN'"):
        sb3_sfgpi.SFDQNN  # noqa: B018


def test_the_process_of_an_env_copy_imports_neither_torch_nor_sb3():
    """A copy's spawned process (``n_envs > 1``) imports the worker's module: 0.4 s, not torch's and SB3's 3 s."""
    code = f"import sys, sb3_sfgpi.common.env_copies; print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.stdout.split() == ["[]"], result.stderr


def test_help_and_parsing_import_nothing_heavy():
    steps = [("--help", ["--help"])]
    steps += [
        (f"{command} --help", [command, "--help"]) for command in ("train", "evaluate", "compare", "plot", "sweep")
    ]
    steps += [("train", [*TRAIN, "--seed", "3", "--set", "prune=false"]), ("usage error", ["train", "--seed", "x"])]
    seen = probe(steps)
    assert seen == {name: [0 if name != "usage error" else 2, []] for name, _ in steps}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "tiny"
    assert main([*TRAIN, *TINY, "--out", str(out)]) == 0
    return out


def test_plot_imports_neither_torch_nor_sb3_nor_sumo(run, tmp_path):
    png = tmp_path / "returns.png"
    seen = probe([("main plot", ["plot", str(run), "-o", str(png)])], tuple(m for m in HEAVY if m != "matplotlib"))
    assert seen == {"main plot": [0, []]} and png.stat().st_size > 0


def test_evaluate_and_compare_refuse_bad_input_before_importing_torch(run, tmp_path):
    missing = str(tmp_path / "missing")
    steps = [
        ("main evaluate: no run", ["evaluate", missing, "--w", "1", "0", "0"]),
        ("main evaluate: --episodes 0", ["evaluate", str(run), "--w", "1", "0", "0", "--episodes", "0"]),
        ("main compare: no run", ["compare", missing]),
        ("main compare: --episodes 0", ["compare", str(run), "--episodes", "0"]),
    ]
    assert probe(steps) == {name: [2, []] for name, _ in steps}


def test_a_tabular_run_imports_neither_torch_dynamo_nor_sympy(tmp_path):
    """A table's learning rate lives in :class:`~sb3_sfgpi.sfdqn.tabular_policy.StepSize`: a torch optimizer would
    import ``torch._dynamo`` and SymPy (68 MB of the main job's peak, 1.5 s) for a placeholder never stepped."""
    steps = [("main train", [*TRAIN, *TINY, "--out", str(tmp_path / "run")])]
    assert probe(steps, ("torch._dynamo", "sympy")) == {"main train": [0, []]}

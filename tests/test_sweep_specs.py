"""Regressions of issue 45, sweep specs: names stay inside --out and are unique, options are a list of strings that
cannot set (or abbreviate) what the sweep sets, Ctrl-C prints the table so far. Each failed on the code before."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.sweep_runner import RunSpec, read_spec, run_sweep

TINY = [
    "--env",
    "max_steps=30",
    "--steps-per-iteration",
    "600",
    "--set",
    "n_test_weights=2",
    "--set",
    "validation_weights=0",
]


@pytest.mark.parametrize("name", ["/abs/path", "../x", "a/b", "./r", ".", "..", "a\\b", "x\0y", "tab\there", "é" * 101])
def test_a_run_name_is_one_path_component(name):
    with pytest.raises(ValueError, match="a run name must be one printable path component"):
        RunSpec("four-room", name=name)


def test_a_domain_cannot_smuggle_a_path_into_the_default_name():
    with pytest.raises(ValueError, match="one printable path component"):
        RunSpec("../four-room")


@pytest.mark.parametrize(
    "names", [("r", "r"), ("R", "r"), ("\u00e9", "e\u0301")], ids=["same", "case", "unicode-normalisation"]
)
def test_run_names_must_differ_after_normalisation(tmp_path, names):
    specs = [RunSpec("four-room", seed=i, name=name) for i, name in enumerate(names)]
    with pytest.raises(ValueError, match="two runs of the sweep have the same name"):
        run_sweep(specs, tmp_path, progress_bar=False)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "options",
    [
        ["--se", "7", "--ou", "/elsewhere"],
        ["--see", "7"],
        ["--ou=/elsewhere"],
        ["--resu"],
        ["--al", "random"],
    ],
)
def test_options_cannot_abbreviate_what_the_sweep_sets(options):
    with pytest.raises(ValueError, match=r"may not set .* \(nor abbreviate them\)"):
        RunSpec("four-room", options=options)


def test_train_itself_takes_no_abbreviated_option(tmp_path, capsys):
    with pytest.raises(SystemExit) as exited:
        main(["train", "four-room", "--se", "7", "--ou", str(tmp_path / "elsewhere")])
    assert exited.value.code == 2 and not (tmp_path / "elsewhere").exists()
    assert "unrecognized arguments: --se 7 --ou" in capsys.readouterr().err


def test_a_run_whose_options_train_refuses_fails_at_once_and_is_not_retried(tmp_path):
    from sb3_sfgpi.cli.sweep_runner import train_run

    with pytest.raises(ValueError, match="train refused its arguments"):
        train_run(RunSpec("four-room", options=["--no-such-option"]), tmp_path / "run")
    assert "unrecognized arguments: --no-such-option" in (tmp_path / "run" / "train.log").read_text()


@pytest.mark.parametrize("options", ["--iterations 1", [1, 2], ["--iterations", 3], {"--iterations": "1"}])
def test_options_must_be_a_list_of_strings(tmp_path, options):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"runs": [{"domain": "four-room", "options": options}]}))
    with pytest.raises(ValueError, match="options must be a list of strings"):
        read_spec(spec)
    spec.write_text(json.dumps({"domains": ["four-room"], "algos": ["random"], "seeds": [0], "options": options}))
    with pytest.raises(ValueError, match="options must be a list of strings"):
        read_spec(spec)


@pytest.mark.parametrize(
    "run", [{"domain": "four-room", "name": "/abs/path"}, {"domain": "four-room", "options": "--iterations 1"}]
)
def test_the_sweep_command_refuses_a_bad_spec_in_one_line(tmp_path, capsys, run):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"runs": [run]}))
    assert main(["sweep", "--spec", str(spec), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    error = capsys.readouterr().err
    assert len(error.strip().splitlines()) == 1 and "Traceback" not in error
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("moment", ["run-started", "checkpoint.json"])
def test_ctrl_c_prints_one_line_and_the_table_so_far(tmp_path, moment):
    """Ctrl-C as the run starts (no checkpoint yet) and after its first iteration: one line, the table, exit 1."""
    pytest.importorskip("ray")
    spec = tmp_path / "spec.json"
    long = [*TINY, "--iterations", "1000"]
    spec.write_text(json.dumps({"runs": [{"domain": "four-room", "name": "long", "options": long}]}))
    command = [sys.executable, "-m", "sb3_sfgpi.cli", "sweep", "--spec", str(spec), "--out", str(tmp_path / "out")]
    sweep = subprocess.Popen(
        [*command, "--num-cpus", "1", "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    sign = tmp_path / "out" / "long" / ("" if moment == "run-started" else moment)
    deadline = time.monotonic() + 180
    while not sign.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    sweep.send_signal(signal.SIGINT)
    stdout, stderr = sweep.communicate(timeout=120)
    assert sweep.returncode == 1 and "Traceback" not in stderr and "Unhandled error" not in stderr
    assert stderr.strip().splitlines()[-1].startswith("sb3-sfgpi sweep: error: interrupted: 1 run(s) did not end")
    assert "| long | interrupted |" in stdout

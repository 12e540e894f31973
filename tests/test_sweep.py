"""Sweeps: run specs, spec files, the CLI's errors, and on a local Ray a run killed mid-way that ends as if it had not
been."""

from __future__ import annotations

import importlib.metadata
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
from packaging.version import Version

from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.sweep_runner import RunSpec, grid, read_spec, run_sweep, train_run

#: Four-room runs of a few seconds: short episodes, small iterations, few test weights, no validation.
TINY = (
    "--env", "max_steps=30", "--steps-per-iteration", "600",
    "--set", "n_test_weights=2", "--set", "validation_weights=0",
)  # fmt: skip


def test_grid_makes_every_combination_and_names_each_run():
    specs = grid(["four-room"], ["ma-sfols", "fixed"], [0, 1], weights=[[0.5, 0.5, 0], [1, 0, 0]])
    assert [spec.run_name for spec in specs] == [
        "four-room-ma-sfols-s0",
        "four-room-ma-sfols-s1",
        "four-room-fixed-w0.5-0.5-0-s0",
        "four-room-fixed-w0.5-0.5-0-s1",
        "four-room-fixed-w1-0-0-s0",
        "four-room-fixed-w1-0-0-s1",
    ]
    assert specs[2].train_argv(tmp := __import__("pathlib").Path("x"), resume=True) == [
        "train", "four-room", "--algo", "fixed", "--seed", "0", "--w", "0.5", "0.5", "0.0", "--out", str(tmp),
        "--no-progress", "--resume",
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(algo="ppo"), "algo must be one of"),
        (dict(seed=-1), "seed must be an integer >= 0"),
        (dict(algo="fixed"), "weights w are for algo 'fixed'"),
        (dict(w=(1.0, 0.0)), "weights w are for algo 'fixed'"),
        (dict(options=("--seed", "3")), "may not set"),
        (dict(options=("--out=x",)), "may not set"),
    ],
)
def test_bad_run_specs_are_refused_by_name(kwargs, message):
    with pytest.raises(ValueError, match=message):
        RunSpec("four-room", **kwargs)


def test_spec_files_hold_runs_or_a_grid_and_bad_ones_are_refused(tmp_path):
    runs = tmp_path / "runs.json"
    runs.write_text(json.dumps({"runs": [{"domain": "four-room", "algo": "fixed", "w": [1, 0, 0], "options": TINY}]}))
    (spec,) = read_spec(runs)
    assert spec.w == (1.0, 0.0, 0.0) and spec.options == TINY
    grid_file = tmp_path / "grid.json"
    grid_file.write_text(json.dumps({"domains": ["four-room"], "algos": ["random"], "seeds": [0, 1, 2]}))
    assert [s.seed for s in read_spec(grid_file)] == [0, 1, 2]
    for content, message in (
        ("[1, 2]", "a JSON object"),
        ("{", "Expecting"),
        ('{"domains": ["x"], "sedes": [1]}', "unknown"),
    ):
        grid_file.write_text(content)
        with pytest.raises(ValueError, match=message):
            read_spec(grid_file)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--out", "OUT"], "give --domains"),
        (["--domains", "four-room", "--algos", "fixed", "--out", "OUT"], "'fixed' needs weights"),
        (["--domains", "four-room", "--num-cpus", "0", "--out", "OUT"], "--num-cpus must be at least 1"),
        (["--spec", "SPEC", "--domains", "four-room", "--out", "OUT"], "no --domains"),
    ],
)
def test_the_sweep_command_refuses_bad_arguments_in_one_line(tmp_path, capsys, argv, message):
    argv = [str(tmp_path / a) if a in ("OUT", "SPEC") else a for a in argv]
    assert main(["sweep", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray instance of 2 CPUs for the module's sweeps (starting one takes about 5 s)."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


#: A sweep whose first run is killed: its second iteration of 60,000 steps takes about three seconds, longer than the
#: up to ``SHIP_SECONDS`` (2 s) its first checkpoint may take to reach home without a shared filesystem (20,000 steps,
#: about a second, often ended before the kill could land; Four-Room's compiled joint steps run 3,000 in a few
#: hundredths of a second); the other run, never killed, stays tiny.
KILLED_SWEEP = grid(
    ["four-room"], ["ma-sfols"], [0], options=[*TINY, "--iterations", "2", "--steps-per-iteration", "60000"]
)
KILLED_SWEEP += grid(["four-room"], ["random"], [0], options=TINY)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The killed sweep's first run trained in this process, never killed (what the killed one must end as)."""
    return train_run(KILLED_SWEEP[0], tmp_path_factory.mktemp("uninterrupted") / "run")


def _sweep_into(outcomes: list, specs: list[RunSpec], out: Path, shared_filesystem: bool) -> None:
    outcomes.extend(run_sweep(specs, out, progress_bar=False, shared_filesystem=shared_filesystem))


def _killed_in_its_second_iteration(sweep: threading.Thread, run_dir: Path) -> dict | None:
    """
    Kill the run once its first checkpoint is in ``run_dir`` (sent home, without a shared filesystem: up to
    ``SHIP_SECONDS`` after it was written) while it is still in its second iteration where it works; its attempt, or
    None where it had gone past that (the kill would have missed it).
    """
    while not (run_dir / "checkpoint.json").is_file():
        assert sweep.is_alive(), "the sweep ended before the run could be killed"
        time.sleep(0.02)
    attempt = json.loads((run_dir / "sweep.json").read_text())["attempts"][-1]
    try:
        iterations = len(json.loads((Path(attempt["dir"]) / "evaluation.json").read_text()))
    except FileNotFoundError:  # its folder on the node is gone: the run ended
        return None
    if iterations != 1:
        return None
    os.kill(attempt["pid"], signal.SIGKILL)
    return attempt


@pytest.mark.parametrize("shared_filesystem", [True, False])
def test_a_killed_run_is_retried_and_ends_as_if_it_had_not_been_killed(
    tmp_path, local_ray, uninterrupted, shared_filesystem
):
    specs, target = KILLED_SWEEP, KILLED_SWEEP[0]
    for tries in range(3):  # a run that ended before the kill could land is swept again
        out, outcomes = tmp_path / f"sweep{tries}", []
        sweep = threading.Thread(target=_sweep_into, args=(outcomes, specs, out, shared_filesystem))
        sweep.start()
        run_dir = out / target.run_name
        attempt = _killed_in_its_second_iteration(sweep, run_dir)
        if attempt is not None:
            break
        sweep.join(timeout=600)
    else:
        pytest.fail("the run ended before it could be killed, three times")
    if not shared_filesystem:  # the run worked in a folder of its node: the node is lost with it
        assert out not in Path(attempt["dir"]).parents
        shutil.rmtree(Path(attempt["dir"]).parent)
    sweep.join(timeout=600)
    assert [o.status for o in outcomes] == ["finished"] * 2
    assert [o.attempts for o in outcomes] == [2, 1]
    assert [o.run_dir for o in outcomes] == [out / spec.run_name for spec in specs]
    if not shared_filesystem:  # the nodes' folders are gone once their runs came home
        assert not any(
            Path(a["dir"]).exists()
            for o in outcomes
            for a in json.loads((o.run_dir / "sweep.json").read_text())["attempts"]
        )
    killed = json.loads((run_dir / "evaluation.json").read_text())
    reference = json.loads((uninterrupted.run_dir / "evaluation.json").read_text())
    strip = [
        [{k: v for k, v in row.items() if k not in ("wall_time", "eval_time")} for row in rows]
        for rows in (killed, reference)
    ]
    assert len(killed) == 2 and strip[0] == strip[1]
    again = run_sweep(specs, out, progress_bar=False)  # a sweep run again skips what finished
    assert [o.status for o in again] == ["skipped"] * 2 and [o.attempts for o in again] == [2, 1]


def test_runs_asking_more_cpus_than_the_cluster_has_still_run(tmp_path, local_ray):
    specs = grid(["four-room"], ["ma-sfols"], [0], options=[*TINY, "--iterations", "1"])
    outcomes: list = []
    sweep = threading.Thread(
        target=lambda: outcomes.extend(run_sweep(specs, tmp_path, cpus_per_run=3, progress_bar=False)), daemon=True
    )
    sweep.start()
    sweep.join(timeout=120)  # the run takes seconds
    assert not sweep.is_alive(), "a run asking 3 CPUs of a 2-CPU cluster was never scheduled"
    assert [o.status for o in outcomes] == ["finished"]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def ray_head(tmp_path):
    """
    A Ray head node started as a user starts one (``ray start --head``) with token authentication (its token in the
    ``~/.ray/auth_token`` of a home of its own, where Ray ≥ 2.59 keeps it), stopped afterwards (its process group
    only: other tests' local Ray instances stay).
    """
    pytest.importorskip("ray")
    home = tmp_path / "home"
    (home / ".ray").mkdir(parents=True)
    (home / ".ray" / "auth_token").write_text(secrets.token_hex(32))
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")} | {"HOME": str(home)}
    temp = tempfile.mkdtemp(prefix="r", dir="/tmp")  # short: Ray's socket paths have a length limit
    port = _free_port()
    log = tmp_path / "head.log"
    command = [
        "ray", "start", "--head", "--block", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
        "--disable-usage-stats", f"--temp-dir={temp}", f"--ray-client-server-port={_free_port()}",
    ]  # fmt: skip
    with log.open("w") as output:
        head = subprocess.Popen(command, env=env, stdout=output, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in log.read_text():
            assert head.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.2)
        yield f"127.0.0.1:{port}", env
    finally:
        os.killpg(head.pid, signal.SIGKILL)
        head.wait()
        shutil.rmtree(temp, ignore_errors=True)


def test_a_sweep_joins_a_cluster_started_with_ray_start_and_says_what_to_do_without_its_token(tmp_path, ray_head):
    address, env = ray_head

    def sweep(out: str, home: dict) -> subprocess.CompletedProcess:
        command = [
            sys.executable, "-m", "sb3_sfgpi.cli", "sweep", "--domains", "four-room", "--algos", "random",
            "--seeds", "0", "--out", str(tmp_path / out), "--address", address, "--no-progress", "--", *TINY,
            "--iterations", "1",
        ]  # fmt: skip
        return subprocess.run(command, env=home, capture_output=True, text=True, timeout=300)

    joined = sweep("a", env)
    assert joined.returncode == 0, joined.stderr[-2000:]
    assert "| four-room-random-s0 | finished | 1 | 1 |" in joined.stdout
    # no token in this home; Ray retries the refused connection for 20 s unless told to try once
    stranger = sweep("b", {**env, "HOME": str(tmp_path), "RAY_gcs_server_port_wait_time_s": "1"})
    if Version(importlib.metadata.version("ray")) < Version("2.59"):  # no token authentication before Ray 2.59
        assert stranger.returncode == 0, stranger.stderr[-2000:]
        return
    assert stranger.returncode == 2
    assert "asks for its token" in stranger.stderr.strip().splitlines()[-1]

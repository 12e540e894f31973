"""Regressions of issue 12 (no silent wrong answers on bad input): each of these failed on the code before the fix."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch as th
from conftest import FEW_VALIDATION, FIG1_TABULAR_KWARGS, train_tiny_run
from momdp import Fig1MOMDP
from stable_baselines3.common.callbacks import BaseCallback
from tensorboard_scalars import scalar_steps

from sb3_sfgpi.cli import main, parse_args
from sb3_sfgpi.cli.interrupts import Interrupts
from sb3_sfgpi.cli.train import _stopped_message
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_settings import RunSettings
from sb3_sfgpi.sfdqn import SFDQN


def test_huge_weights_are_normalised_without_overflow():
    np.testing.assert_array_equal(validate_weights([1e308, 1e308, 0.0], 3), [0.5, 0.5, 0.0])
    np.testing.assert_allclose(validate_weights([5e-324, 0.0], 2), [1.0, 0.0])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"gamma": 2.0}, "gamma must be a number in"),
        ({"gamma": -0.1}, "gamma must be a number in"),
        ({"gamma": float("nan")}, "gamma must be a number in"),
        ({"batch_size": 0}, "batch_size must be a positive integer"),
        ({"batch_size": 2.5}, "batch_size must be a positive integer"),
        ({"learning_rate": "abc"}, "learning_rate must be a number >= 0 or a schedule"),
        ({"learning_rate": "lin_-1"}, "learning_rate must be a number >= 0 or a schedule"),
        ({"learning_rate": "lin_nan"}, "learning_rate must be a number >= 0 or a schedule"),
        ({"learning_rate": -0.1}, "learning_rate must be a number >= 0 or a schedule"),
        ({"learning_rate": float("nan")}, "learning_rate must be a number >= 0 or a schedule"),
    ],
)
def test_out_of_range_learner_options_are_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        SFDQN("TabularPolicy", Fig1MOMDP(), **{**FIG1_TABULAR_KWARGS, **overrides})


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--iterations", "0"], "--iterations must be positive, got 0"),
        (["--seed", "-1"], "--seed must be an integer in [0, 2**32), got -1"),
        (["--set", "n_test_weights=100000000000"], "--set n_test_weights must be an integer in [1, 1000000]"),
        (["--out", "x" * 300], "is longer than 255 bytes"),
        (["--seed", str(2**32)], "--seed must be an integer in [0, 2**32), got 4294967296"),
        (["--steps-per-iteration", "0"], "--steps-per-iteration must be positive, got 0"),
        (["--learner", "gamma=2"], "'gamma' must be a number in [0, 1], got 2"),
        (["--learner", "batch_size=0"], "batch_size must be a positive integer, got 0"),
        (["--set", "validation_weights=-1"], "--set validation_weights must be an integer in [0, 1000000], got -1"),
        (["--env", "nosuchkey=1"], "the four-room env refuses"),
        (["--env", "observation_mode=bogus"], "unknown observation_mode 'bogus'"),
        (["--learner", "nosuchkwarg=1"], "learner argument 'nosuchkwarg' is not taken from a run file"),
        (
            ["--learner", "learning_rate=abc"],
            "learning_rate must be a number >= 0 or a schedule ('lin_X', X >= 0), got 'abc'",
        ),
        (["--algo", "fixed", "--w", "1", "0", "0", "--set", "validation_weights=3"], "not for --algo fixed"),
        (
            ["--set", "validation_weights=0", "--set", "prune=true"],
            "--set prune=true needs validation weights (--set validation_weights=N",
        ),
        (["--set", "validation_weights=0", "--set", "admit_together=true"], "admit_together=true needs validation"),
        (["--algo", "random", "--set", "ols_batch=top"], "--set ols_batch is only for --algo ma-sfols"),
        (["--set", "pool_replay=true"], "pool_replay needs a single-agent env, not 2 agents"),
    ],
)
def test_train_refuses_zero_budgets_and_bad_learner_options(tmp_path, cli_exit, argv, message):
    code, stderr = cli_exit(["train", "four-room", "--out", str(tmp_path / "run"), *argv])
    assert code == 2
    assert message in stderr and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1


def test_train_refuses_a_run_directory_it_cannot_create(tmp_path):
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "run"
    result = subprocess.run(
        [sys.executable, "-m", "sb3_sfgpi.cli", "train", "four-room", "--out", str(out)], capture_output=True, text=True
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"--out {out}: cannot create the run directory (Not a directory)" in result.stderr


def test_a_diverging_tabular_update_stops_in_one_clear_error_without_numpy_warnings():
    """α = 1 with batches of 32 on the Fig. 1 chain: the first update moves a lone transition 32 times its TD error; the
    TD errors overflow float32 within 40 steps. It stops there, not at a later save, and numpy warns of nothing."""
    settings = {**FIG1_TABULAR_KWARGS, "batch_size": 32, "seed": 0}  # seeds 0-11: it diverges within 21-50 steps
    model = SFDQN("TabularPolicy", Fig1MOMDP(), **{**settings, "learning_rate": 1.0})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow warning would fail here
        with pytest.raises(ValueError, match=r"the tabular TD update diverged .* learning_rate 1 and batch_size 32"):
            model.learn(3_000)
    assert model.num_timesteps < 100
    fine = SFDQN("TabularPolicy", Fig1MOMDP(), **{**settings, "learning_rate": 0.2})
    assert np.isfinite(fine.learn(3_000).successor_features(np.arange(5))).all()  # a smaller α on the same batches


def test_the_cli_stops_a_diverging_run_in_one_line(tmp_path, cli_exit):
    code, stderr = cli_exit(
        ["train", "four-room", "--iterations", "1", "--steps-per-iteration", "2000", "--no-progress", "--out",
         str(tmp_path / "run"), "--learner", "learning_rate=1"]
    )  # fmt: skip
    assert code == 2 and len(stderr.strip().splitlines()) == 1 and "the tabular TD update diverged" in stderr


def test_numpy_scalars_are_accepted_as_options():
    model = SFDQN("TabularPolicy", Fig1MOMDP(), gamma=np.float32(0.9), batch_size=np.int64(4), learning_starts=0)
    assert model.gamma == pytest.approx(0.9) and model.batch_size == 4


@pytest.fixture(scope="module")
def one_iteration_run(tmp_path_factory) -> Path:
    """A finished one-iteration run of 150 steps (tests resume copies of it)."""
    return train_tiny_run(tmp_path_factory.mktemp("trained") / "run", steps=150)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["--steps-per-iteration", "200"],
            "--steps-per-iteration 200 would change the run's steps_per_iteration (150)",
        ),
        (["--set", "n_test_weights=5"], "--set n_test_weights=5 would change the run's n_test_weights (2)"),
        (["--set", "validation_weights=0"], "--set validation_weights=0 would change the run's validation_weights (4)"),
        (["--set", "prune=false"], "--set prune=False would change the run's prune (True)"),
        (["--set", "admit_together=false"], "--set admit_together=False would change the run's admit_together (True)"),
        (["--set", "ols_batch=top"], "--set ols_batch=top would change the run's ols_batch (same-after-extrema)"),
        (["--set", "value_mode=shared"], "--set value_mode=shared would change the run's value_mode (joint)"),
        (["--set", "gpi_set=ccs"], "--set gpi_set=ccs would change the run's gpi_set (all)"),
        (["--set", "eval_episodes=2"], "--set eval_episodes=2 would change the run's eval_episodes (1)"),
    ],
)
def test_resume_refuses_options_that_would_change_the_run(one_iteration_run, tmp_path, argv, message, capsys):
    out = str(tmp_path / "run")
    shutil.copytree(one_iteration_run, out)
    resume = ["train", "four-room", "--iterations", "2", "--no-progress", "--out", out, "--resume"]
    assert main([*resume, *argv]) == 2
    assert message in capsys.readouterr().err
    assert main(resume) == 0  # the options not given keep the run's


def test_sigterm_stops_training_as_ctrl_c_does(tmp_path):
    out = tmp_path / "run"
    command = [sys.executable, "-m", "sb3_sfgpi.cli", "train", "four-room", "--out", str(out), "--no-progress"]
    budget = ["--iterations", "1000", "--steps-per-iteration", "200", "--set", "n_test_weights=2", *FEW_VALIDATION]
    process = subprocess.Popen([*command, *budget], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / "checkpoint.json").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 1 and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert "(interrupted by SIGTERM)" in stderr and "is intact: continue with" in stderr
    assert f"--out {out} --resume --iterations 1000`" in stderr


class _Finalized:
    """An object whose finalizer receives a signal: Python reports an exception raised there as ignored, and goes on."""

    def __init__(self, signal_number: int) -> None:
        self.signal_number = signal_number

    def __del__(self) -> None:
        os.kill(os.getpid(), self.signal_number)


class _SignalInAFinalizerAt(BaseCallback):
    def __init__(self, step: int, signal_number: int) -> None:
        super().__init__()
        self.step, self.signal_number = step, signal_number

    def _on_step(self) -> bool:
        if self.num_timesteps == self.step:
            _Finalized(self.signal_number)  # collected at once
        return True


def _four_room(out: Path) -> list[str]:
    budget = ["--iterations", "5", "--steps-per-iteration", "200", "--set", "n_test_weights=2", *FEW_VALIDATION]
    return ["train", "four-room", "--out", str(out), "--no-progress", *budget]


@contextmanager
def _sigint_handled_by(handler: Any) -> Iterator[None]:
    """SIGINT's handler set to ``handler`` in the block, the previous one back after it."""
    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.fixture
def live_ctrl_c() -> Iterator[None]:
    """Ctrl-C delivered as in a terminal, also where pytest runs as a background job of a script (SIGINT ignored)."""
    with _sigint_handled_by(signal.default_int_handler):
        yield


@pytest.mark.parametrize(
    ("signal_number", "reason"), [(signal.SIGTERM, "(interrupted by SIGTERM)"), (signal.SIGINT, "(interrupted)")]
)
def test_an_interrupt_lost_in_a_finalizer_stops_training_at_the_next_step(
    tmp_path, monkeypatch, capfd, live_ctrl_c, signal_number, reason
):
    learn = MASFOLS.learn
    at = _SignalInAFinalizerAt(250, signal_number)
    monkeypatch.setattr(MASFOLS, "learn", lambda self, n, callback, **kw: learn(self, n, [callback, at], **kw))
    assert main(_four_room(tmp_path / "run")) == 1
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and "Exception ignored" not in err and "Traceback" not in err
    assert f"training stopped in iteration 2 {reason}" in err
    assert RunDirectory(tmp_path / "run").read_checkpoint()["iteration"] == 1


def test_an_error_an_interrupt_turned_into_is_reported_as_the_interrupt(tmp_path, monkeypatch, capsys):
    """numba turns an interrupt that lands while it unboxes a compiled call's arguments into a TypeError (CI of 89)."""

    def learn(self, *args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
        except KeyboardInterrupt:
            raise TypeError("_get_wrapper_address() missing 1 required positional argument: 'sig'") from None

    monkeypatch.setattr(MASFOLS, "learn", learn)
    assert main(_four_room(tmp_path / "run")) == 1
    assert "training stopped in iteration 1 (interrupted by SIGTERM)" in capsys.readouterr().err


def test_a_sigint_that_a_background_job_ignores_stays_ignored_in_training():
    with _sigint_handled_by(signal.SIG_IGN):
        with Interrupts().caught():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, signal.SIG_IGN)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_sigkill_at_random_moments_then_resume_loses_and_repeats_nothing(tmp_path):
    run = ["train", "four-room", "--iterations", "3", "--steps-per-iteration", "300", "--set", "n_test_weights=2"]
    run += [*FEW_VALIDATION, "--no-progress"]

    def train(out, kill_after=None):
        argv = [*run, "--out", str(out), *(["--resume"] if (out / "run.json").exists() else [])]
        command = [sys.executable, "-m", "sb3_sfgpi.cli", *argv]
        with subprocess.Popen(command, stdout=subprocess.PIPE, text=True) as process:
            process.stdout.readline()  # the header: the run is built, training starts
            try:
                return process.wait(kill_after)
            except subprocess.TimeoutExpired:
                process.kill()  # SIGKILL: no handler runs
                return process.wait()

    start = time.monotonic()
    assert main([*run, "--out", str(tmp_path / "whole")]) == 0  # in this process: never killed
    seconds = time.monotonic() - start  # the whole run's length (a fixed delay let a fast machine finish unkilled)
    cut, kills = tmp_path / "cut", 0
    for fraction in np.random.default_rng(12).uniform(0.05, 0.6, size=3):  # the first attempt is always killed
        kills += train(cut, kill_after=fraction * seconds) != 0
        if (cut / "checkpoint.json").exists() and json.loads((cut / "checkpoint.json").read_text())["iteration"] == 3:
            break
    assert kills >= 1 and train(cut) == 0
    whole = json.loads((tmp_path / "whole" / "evaluation.json").read_text())
    assert [row["mean_return"] for row in json.loads((cut / "evaluation.json").read_text())] == [
        row["mean_return"] for row in whole
    ]
    progress = (cut / "logs" / "progress.csv").read_text().splitlines()
    column = progress[0].split(",").index("ols/iteration")
    assert [int(row.split(",")[column]) for row in progress[1:]] == [1, 2, 3]
    assert scalar_steps(cut / "logs", "ols/mean_return") == [1, 2, 3]
    folders = sorted(folder.name for folder in (cut / "tensorboard").iterdir())
    assert folders == [f"{agent}_iter{i:03d}_1" for agent in ("agent_0", "agent_1") for i in (1, 2, 3)]


def test_the_stop_message_repeats_the_iteration_cap(tmp_path):
    args = parse_args(["train", "four-room", "--iterations", "3", "--out", str(tmp_path)])
    model = SimpleNamespace(settings=RunSettings(), callback=SimpleNamespace(iteration=1))
    message = _stopped_message(args, RunDirectory(tmp_path), model, KeyboardInterrupt())
    assert message.endswith(
        f"`sb3-sfgpi train four-room --algo ma-sfols --seed 0 --out {tmp_path} --resume --iterations 3`"
    )


def four_room_tabular_model() -> SFDQN:
    from sfgpi_envs.four_room import FourRoomParallelEnv

    from sb3_sfgpi.learners import default_learner_factory
    from sb3_sfgpi.multiagent import MultiAgentRunner

    runner = MultiAgentRunner(
        FourRoomParallelEnv(observation_mode="own"), default_learner_factory(policy="TabularPolicy")
    )
    runner.start_iteration({agent: np.ones(3) / 3 for agent in runner.agents}, iteration=0, total_timesteps=1)
    return runner.learners["agent_0"]


@pytest.mark.parametrize(
    "observation",
    [[12, 0, 2] + [0] * 11, [13, 0] + [0] * 12, [-1, 0] + [0] * 12, [12.7, 0] + [0] * 12],
    ids=["flag-2", "row-13", "row-minus-1", "row-12.7"],
)
def test_tabular_predict_refuses_observations_outside_the_space(observation):
    model = four_room_tabular_model()
    policy_set = GPIPolicy()
    policy_set.add(model)
    for predict in (lambda obs: model.predict(obs, deterministic=True), lambda obs: policy_set.predict(obs, [1, 0, 0])):
        with pytest.raises(ValueError, match=r"observation \[.*\] is outside the observation space MultiDiscrete"):
            predict(np.array(observation))
    assert model.predict(np.array([12, 0] + [0] * 12), deterministic=True)[0] in range(4)


def test_predict_takes_a_tensor_that_requires_grad_and_refuses_strings():
    model = four_room_tabular_model()
    policy_set = GPIPolicy()
    policy_set.add(model)
    observation = [12, 0] + [0] * 12
    tensor = th.tensor(observation, dtype=th.float32, requires_grad=True)
    for predict in (lambda obs: model.predict(obs, deterministic=True), lambda obs: policy_set.predict(obs, [1, 0, 0])):
        assert predict(tensor)[0] == predict(np.array(observation))[0]
        for bad, dtype in ((np.array(["12"] + ["0"] * 13), "<U2"), (np.array(observation, dtype=object), "object")):
            with pytest.raises(ValueError, match=f"observations must be numbers .*, got an array of dtype {dtype}"):
                predict(bad)


@pytest.fixture
def small_disk(tmp_path):
    """A real 8 MB file system (tmpfs), where mounting is allowed (root on Linux); skipped elsewhere."""
    mount_point = tmp_path / "disk"
    mount_point.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8M", "tmpfs", str(mount_point)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip("cannot mount a small file system here (needs root)")
    yield mount_point
    subprocess.run(["umount", "-l", str(mount_point)], check=True)


def test_a_full_disk_stops_training_in_one_line_and_the_checkpoint_survives(small_disk, cli_exit):
    out = small_disk / "run"
    # the disk is what is tested, not policy validation (off: its 100 weights' rollouts are most of a short run)
    train = ["train", "four-room", "--out", str(out), "--no-progress", "--set", "validation_weights=0",
             "--set", "prune=false"]  # fmt: skip
    budget = ["--steps-per-iteration", "150", "--set", "n_test_weights=2"]
    assert cli_exit([*train, *budget, "--iterations", "1"])[0] == 0
    filler = small_disk / "filler"
    subprocess.run(["dd", "if=/dev/zero", f"of={filler}", "bs=64k"], capture_output=True)  # ends at ENOSPC
    code, stderr = cli_exit([*train, "--iterations", "2", "--resume"])
    assert code == 1 and "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1
    assert "No space left on device" in stderr
    assert f"cannot write {out / 'run.json'}" in stderr and "it is as it was" in stderr  # the first write
    filler.unlink()
    assert cli_exit([*train, "--iterations", "2", "--resume"])[0] == 0
    assert json.loads((out / "checkpoint.json").read_text())["iteration"] == 2


def test_a_full_disk_under_tensorboards_writer_thread_is_one_error_naming_the_event_file(small_disk, capsys):
    """TensorBoard's writer thread printed its traceback, then the training loop got an error naming no file."""
    from torch.utils.tensorboard import SummaryWriter

    from sb3_sfgpi.cli.errors import report_writer_errors_once

    report_writer_errors_once()
    writer = SummaryWriter(str(small_disk / "tensorboard"), flush_secs=0)
    subprocess.run(["dd", "if=/dev/zero", f"of={small_disk / 'filler'}", "bs=64k"], capture_output=True)  # ENOSPC
    with pytest.raises(OSError, match="No space left") as error:
        for step in range(10_000):  # the thread fails on a flush; a later write raises its error here
            writer.add_scalar("x", float(step), step)
            writer.flush()
    (event_file,) = (small_disk / "tensorboard").glob("events.out.tfevents.*")
    assert error.value.filename == str(event_file)
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("link", [".lock", "logs", "logs/progress.csv", "policy_set", "tensorboard"])
def test_a_link_inside_a_run_directory_is_refused_before_anything_is_written(tmp_path, cli_exit, link):
    """A symbolic link inside a run made `--resume` write (or delete) where it pointed: now nothing is written."""
    from conftest import FEW_VALIDATION, tiny_four_room, train_tiny_run

    run = train_tiny_run(tmp_path / "run")
    victim = tmp_path / "victim"
    victim.mkdir() if (run / link).is_dir() else victim.write_text("mine")
    before = sorted(p.name for p in victim.iterdir()) if victim.is_dir() else victim.read_text()
    target = run / link
    shutil.rmtree(target) if target.is_dir() else target.unlink(missing_ok=True)
    target.symlink_to(victim, target_is_directory=victim.is_dir())
    resume = [*tiny_four_room(), *FEW_VALIDATION, "--iterations", "2", "--out", str(run), "--resume", "--no-progress"]
    code, stderr = cli_exit(resume)
    assert code == 2 and f"{target} is a symbolic link" in stderr and len(stderr.strip().splitlines()) == 1
    assert (sorted(p.name for p in victim.iterdir()) if victim.is_dir() else victim.read_text()) == before

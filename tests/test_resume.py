"""Checkpoints and resume: stopped or killed runs continue where their checkpoint left them, every
iteration's TensorBoard points exactly once and the killed run's points before the checkpoint untouched;
bad checkpoints and changed arguments are refused by name."""

import builtins
import contextlib
import errno
import fcntl
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT, assert_refusal, hyperparameters, scalars

SCRIPTS = {"ppo": ppo, "p3o": p3o}
BATCH, ITERATIONS, UPDATES = 4 * 32, 10, 2  # UPDATES: minibatches x epochs per iteration
FLAGS = ["--env-id", "Breakout-v5", "--num-envs", "4", "--num-steps", "32", "--num-minibatches", "2"]
FLAGS += ["--update-epochs", "1", "--total-timesteps", str(BATCH * ITERATIONS), "--seed", "5"]
PER_ITERATION = ["losses/value_loss", "losses/entropy", "charts/learning_rate", "charts/SPS"]


def command(algo, *extra):
    return [sys.executable, os.path.join(ROOT, f"{algo}_atari_envpool.py"), *FLAGS, *extra]


def run(algo, cwd, *extra):
    return subprocess.run(command(algo, *extra), cwd=cwd, capture_output=True, text=True, timeout=600)


def start_and_signal(algo, cwd, sig, at_iteration, *extra):
    """Start a run and send `sig` once it has printed iteration `at_iteration`."""
    proc = subprocess.Popen(command(algo, *extra), cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if line.startswith(f"iteration {at_iteration}/"):
            proc.send_signal(sig)
            break
    out, err = proc.communicate(timeout=300)
    return proc.returncode, "".join(lines) + out, err


def check_resumed(algo, tmp_path, run_dir, before, checkpoint_iteration, how):
    """Resume the run; then the points up to the checkpoint are the killed run's, and every later
    iteration has its points exactly once."""
    resumed = run(algo, tmp_path, *how)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resuming {run_dir} after iteration {checkpoint_iteration}" in resumed.stdout
    assert f"iteration {ITERATIONS}/{ITERATIONS} global_step={BATCH * ITERATIONS} " in resumed.stdout
    assert f"iteration {checkpoint_iteration}/" not in resumed.stdout
    after = scalars(str(tmp_path / run_dir))
    cut = checkpoint_iteration * BATCH
    for tag in PER_ITERATION + ["charts/episodic_return", "charts/episodic_length"]:
        kept = [p for p in before.get(tag, []) if p[0] <= cut]
        assert [p for p in after[tag] if p[0] <= cut] == kept, tag
    for tag in PER_ITERATION:
        assert [s for s, _ in after[tag]] == [BATCH * i for i in range(1, ITERATIONS + 1)], tag
    # the learning-rate schedule (the default 1e-3, annealed) continues where it was
    lrs = [v for _, v in after["charts/learning_rate"]]
    np.testing.assert_allclose(lrs, [1e-3 * (1 - i / ITERATIONS) for i in range(ITERATIONS)], rtol=1e-6)
    final = torch.load(tmp_path / run_dir / "checkpoint.pt", weights_only=True)
    assert final["finished"] and final["iteration"] == ITERATIONS and final["global_step"] == BATCH * ITERATIONS
    # Adam's step count went on from the checkpoint's: the optimizer state was restored, not started afresh
    assert final["optimizer_state_dict"]["state"][0]["step"].item() == ITERATIONS * UPDATES
    again = run(algo, tmp_path, "--resume", run_dir)
    assert again.returncode == 0 and "already finished (1280 steps); nothing to do." in again.stdout


@pytest.mark.parametrize(
    "algo,sig",
    [("ppo", signal.SIGTERM), ("p3o", signal.SIGTERM), ("p3o", signal.SIGINT)],
    ids=["ppo-TERM", "p3o-TERM", "p3o-INT"],
)
def test_signal_checkpoints_the_iteration_it_ends_and_the_run_resumes(algo, sig, tmp_path):
    # no periodic checkpoints: the only checkpoint is the one the signal makes
    rc, out, err = start_and_signal(algo, tmp_path, sig, 3, "--run-name", "r", "--checkpoint-every", "0")
    run_dir = os.path.join("runs", "r")
    assert rc == 128 + sig, err
    assert "Traceback" not in err
    stopped = re.search(rf"stopped by signal {int(sig)} after iteration (\d+); continue with --resume {run_dir}\n", out)
    assert stopped, out
    iteration = int(stopped.group(1))
    assert 3 <= iteration < ITERATIONS and f"iteration {iteration + 1}/" not in out
    saved = torch.load(tmp_path / run_dir / "checkpoint.pt", weights_only=True)
    assert saved["iteration"] == iteration and not saved["finished"]
    assert not (tmp_path / run_dir / "checkpoint.pt.tmp").exists()
    before = scalars(str(tmp_path / run_dir))
    assert max(s for s, _ in before["losses/value_loss"]) == iteration * BATCH  # logged up to the checkpoint
    # SIGINT's run goes on as a sweep continues it: the same command again, with --auto-resume
    how = ("--run-name", "r", "--auto-resume") if sig == signal.SIGINT else ("--resume", run_dir)
    check_resumed(algo, tmp_path, run_dir, before, iteration, how)


@pytest.mark.parametrize("algo", SCRIPTS)
def test_killed_run_resumes_from_its_last_periodic_checkpoint(algo, tmp_path):
    rc, _, _ = start_and_signal(algo, tmp_path, signal.SIGKILL, 5, "--run-name", "k", "--checkpoint-every", "3")
    run_dir = os.path.join("runs", "k")
    assert rc == -signal.SIGKILL
    assert not (tmp_path / run_dir / "checkpoint.pt.tmp").exists()
    before = scalars(str(tmp_path / run_dir))
    logged = max(s for s, _ in before["losses/value_loss"]) // BATCH  # the last iteration the killed run logged
    saved = torch.load(tmp_path / run_dir / "checkpoint.pt", weights_only=True)["iteration"]
    # the checkpoint after the last multiple of 3 it logged (or the one before, when killed between the two)
    assert saved % 3 == 0 and logged - 3 <= saved <= logged and saved >= 3, (saved, logged)
    if logged > saved:  # points after the checkpoint exist now and must be purged by the resume
        assert any(s > saved * BATCH for s, _ in before["losses/value_loss"])
    check_resumed(algo, tmp_path, run_dir, before, saved, ("--resume", run_dir))


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory):
    """A PPO run stopped by SIGTERM after a few iterations: (cwd, run folder, checkpoint iteration)."""
    cwd = tmp_path_factory.mktemp("stopped")
    rc, out, err = start_and_signal("ppo", cwd, signal.SIGTERM, 3, "--run-name", "s", "--checkpoint-every", "0")
    assert rc == 128 + signal.SIGTERM, err
    iteration = int(re.search(r"after iteration (\d+);", out).group(1))
    return cwd, str(cwd / "runs" / "s"), iteration


def test_resume_restores_the_model_and_optimizer_exactly(stopped_run, tmp_path):
    # a checkpoint taken after the last iteration (a signal in the final iteration): resuming it trains
    # nothing, so the finished checkpoint must hold exactly the model and optimizer it was given
    _, run_dir, _ = stopped_run
    saved = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
    saved["iteration"], saved["global_step"] = ITERATIONS, ITERATIONS * BATCH
    os.makedirs(tmp_path / "runs" / "last")
    torch.save(saved, tmp_path / "runs" / "last" / "checkpoint.pt")
    proc = run("ppo", tmp_path, "--resume", "runs/last")
    assert proc.returncode == 0, proc.stderr[-3000:]
    final = torch.load(tmp_path / "runs" / "last" / "checkpoint.pt", weights_only=True)
    assert final["finished"]
    for name, tensor in saved["model_state_dict"].items():
        assert torch.equal(final["model_state_dict"][name], tensor), name
    for key, state in saved["optimizer_state_dict"]["state"].items():
        for field in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(final["optimizer_state_dict"]["state"][key][field], state[field])
    assert (
        final["optimizer_state_dict"]["param_groups"][0]["lr"] == saved["optimizer_state_dict"]["param_groups"][0]["lr"]
    )


def test_two_resumes_of_one_checkpoint_give_the_same_numbers(stopped_run, tmp_path):
    _, run_dir, _ = stopped_run
    results = []
    for copy in ("a", "b"):
        shutil.copytree(run_dir, tmp_path / "runs" / copy)
        proc = run("ppo", tmp_path, "--resume", f"runs/{copy}")
        assert proc.returncode == 0, proc.stderr[-3000:]
        results.append(
            {tag: scalars(str(tmp_path / "runs" / copy))[tag] for tag in ("losses/value_loss", "losses/entropy")}
        )
    assert results[0] == results[1]


def args_for(module, **overrides):
    """The Args of FLAGS, for calling a script's main in-process (the refusals come before any env)."""
    flags = dict(zip(FLAGS[::2], FLAGS[1::2], strict=True))
    kwargs = {flag[2:].replace("-", "_"): value for flag, value in flags.items()}
    defaults = module.Args()
    kwargs = {k: type(getattr(defaults, k))(v) for k, v in kwargs.items()}
    return module.Args(**(kwargs | overrides))


def refusal(module, cwd, monkeypatch, args):
    monkeypatch.chdir(cwd)
    with pytest.raises(SystemExit) as excinfo:
        module.main(args)
    return str(excinfo.value.code)


def test_changed_arguments_are_refused(stopped_run, monkeypatch):
    cwd, run_dir, _ = stopped_run
    message = refusal(ppo, cwd, monkeypatch, args_for(ppo, num_envs=8, resume=run_dir, run_name="s"))
    assert_refusal(message, f"--resume {run_dir}/checkpoint.pt", "--num-envs 4 (now 8)")
    assert "--seed" not in message  # only what differs
    message = refusal(ppo, cwd, monkeypatch, args_for(ppo, learning_rate=3e-4, seed=6, resume=run_dir))
    assert "--seed 5 (now 6), --learning-rate 0.001 (now 0.0003)" in message  # the folder's name is a run flag
    message = refusal(p3o, cwd, monkeypatch, args_for(p3o, resume=run_dir))
    assert_refusal(message, f"--resume {run_dir}/checkpoint.pt", "a ppo run's checkpoint", "its own script")


def test_a_bare_resume_takes_the_saved_arguments(stopped_run, monkeypatch):
    # `--resume DIR` alone: every experiment flag not given takes the checkpoint's value
    cwd, run_dir, iteration = stopped_run
    cli = ["--resume", run_dir, "--save-model"]
    monkeypatch.chdir(cwd)
    with contextlib.ExitStack() as held:
        args, opened, checkpoint, _ = ppo.open_run(held, ppo.Args(resume=run_dir, save_model=True), cli)
        assert opened == run_dir and checkpoint["iteration"] == iteration
    assert (args.num_envs, args.num_steps, args.seed, args.total_timesteps) == (4, 32, 5, BATCH * ITERATIONS)
    assert args.save_model and args.run_name == "s" and args.resume is None


def test_an_in_process_resume_keeps_every_value_it_is_given(stopped_run, monkeypatch):
    """In-process there is no command line to tell a given value from a default: every value of the Args counts
    as given, so a run flag given at its default (--checkpoint-every 10; the run used 0) is kept, not replaced
    by the run's, and the resume goes the one way a command line's does (the same checks, the same refusals)."""
    cwd, run_dir, iteration = stopped_run
    monkeypatch.chdir(cwd)
    given = args_for(ppo, resume=run_dir, run_name="s", checkpoint_every=10)
    with contextlib.ExitStack() as held:
        args, _, checkpoint, _ = ppo.open_run(held, given, None)
        assert checkpoint["iteration"] == iteration and checkpoint["args"]["checkpoint_every"] == 0
    assert args.checkpoint_every == 10 and (args.batch_size, args.num_iterations) == (BATCH, ITERATIONS)
    cli = ["--resume", run_dir]  # the command line: what it leaves out keeps the run's value
    with contextlib.ExitStack() as held:
        args, _, _, _ = ppo.open_run(held, ppo.Args(resume=run_dir), cli)
        assert args.checkpoint_every == 0


@pytest.mark.parametrize("algo", SCRIPTS)
def test_a_failure_before_training_lets_the_run_folder_go(algo, tmp_path, monkeypatch):
    """The run folder's lock, the writer and the environments are released together however the run ends: an
    exception after the lock is taken (here the environments fail to start, in-process) leaves no lock held, so
    the same process (a sweep, a notebook) can start the run again at once."""
    module = SCRIPTS[algo]
    monkeypatch.chdir(tmp_path)

    def failing_make_env(*args, **kwargs):
        raise RuntimeError("no emulator today")

    monkeypatch.setattr(module, "make_env", failing_make_env)
    before = signal.getsignal(signal.SIGINT)  # Python's default_int_handler; SIG_IGN in a pytest-xdist worker
    with pytest.raises(RuntimeError, match="no emulator today"):
        module.main(args_for(module, run_name="r"))
    assert open(tmp_path / "runs" / "r" / ".lock").read() == f"process {os.getpid()} on {socket.gethostname()}"
    with open(tmp_path / "runs" / "r" / ".lock") as lock:  # raises BlockingIOError if the failed run still held it
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    # and its signal handlers are gone with it: SIGINT's is what it was before the run
    assert signal.getsignal(signal.SIGINT) == before


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_damaged_checkpoints_are_refused_by_name(damage, stopped_run, tmp_path, monkeypatch):
    _, run_dir, _ = stopped_run
    data = open(os.path.join(run_dir, "checkpoint.pt"), "rb").read()
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"not a checkpoint" * 100, "empty": b""}[damage])
    message = refusal(ppo, tmp_path, monkeypatch, args_for(ppo, resume=str(bad)))
    assert_refusal(message, f"--resume {bad}", "is not a checkpoint these scripts can read")


def test_a_model_file_is_not_a_checkpoint(stopped_run, tmp_path, monkeypatch):
    _, run_dir, _ = stopped_run
    saved = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
    model = {k: saved[k] for k in ("format", "algorithm", "args", "model_state_dict")}
    torch.save(model, tmp_path / "model.cleanrl_model")
    message = refusal(ppo, tmp_path, monkeypatch, args_for(ppo, resume=str(tmp_path / "model.cleanrl_model")))
    assert_refusal(message, f"--resume {tmp_path}/model.cleanrl_model", "is not a checkpoint these scripts can read")


def test_a_run_name_in_use_is_not_overwritten(stopped_run, monkeypatch):
    cwd, _, _ = stopped_run
    message = refusal(ppo, cwd, monkeypatch, args_for(ppo, run_name="s"))
    assert_refusal(message, "runs/s holds a run already", "continue it with --resume", "--run-name")


def test_auto_resume_needs_a_run_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:  # where the arguments are made (Args.__post_init__), before main
        args_for(ppo, auto_resume=True)
    assert_refusal(str(excinfo.value.code), "--auto-resume", "--run-name")
    assert not (tmp_path / "runs").exists()


def test_resume_of_a_missing_checkpoint_is_refused(tmp_path, monkeypatch):
    message = refusal(p3o, tmp_path, monkeypatch, args_for(p3o, resume="runs/nothing-here"))
    assert_refusal(message, "--resume runs/nothing-here", "no checkpoint")


def test_refusals_on_the_command_line_exit_1_with_one_sentence(stopped_run):
    cwd, run_dir, _ = stopped_run
    proc = run("p3o", cwd, "--resume", run_dir)
    assert proc.returncode == 1
    assert_refusal(proc.stderr, f"--resume {run_dir}/checkpoint.pt", "a ppo run's checkpoint", "its own script")


def test_points_logged_after_the_checkpoint_are_purged_on_resume(stopped_run, tmp_path):
    # a killed run has logged iterations past its last checkpoint; made deterministic: the stopped run's
    # checkpoint is kept aside, the run finished, and the old checkpoint put back in front of all its points
    _, stopped_dir, iteration = stopped_run
    shutil.copytree(stopped_dir, tmp_path / "runs" / "p")
    old = (tmp_path / "runs" / "p" / "checkpoint.pt").read_bytes()
    assert run("ppo", tmp_path, "--resume", "runs/p").returncode == 0
    (tmp_path / "runs" / "p" / "checkpoint.pt").write_bytes(old)
    before = scalars(str(tmp_path / "runs" / "p"))
    assert max(s for s, _ in before["losses/value_loss"]) == ITERATIONS * BATCH > iteration * BATCH
    check_resumed("ppo", tmp_path, "runs/p", before, iteration, ("--resume", "runs/p"))


def test_checkpoints_of_earlier_versions_still_resume(stopped_run, tmp_path):
    # a checkpoint as the scripts wrote them before evaluation moved to evaluate.py (commit 0dbe53f): the evaluation
    # flags among its arguments, an "ablation" key, no random state, environment or action count
    rc, _, err = start_and_signal("p3o", tmp_path, signal.SIGTERM, 2, "--run-name", "old", "--checkpoint-every", "0")
    assert rc == 128 + signal.SIGTERM, err
    path = tmp_path / "runs" / "old" / "checkpoint.pt"
    saved = torch.load(path, weights_only=True)
    for key in ("rng_state", "env_id", "num_actions"):
        del saved[key]
    saved["ablation"] = None
    saved["args"] |= {"eval_episodes": 10, "eval_greedy": False, "capture_video": False}
    torch.save(saved, path)
    proc = run("p3o", tmp_path, "--resume", "runs/old")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert torch.load(path, weights_only=True)["finished"]


@pytest.mark.parametrize("algo", SCRIPTS)
def test_one_run_folder_takes_one_process(algo, tmp_path):
    """A second process given a folder in use is refused, whether it starts or resumes; once the first dies
    (even by SIGKILL) its lock is gone and the run resumes."""
    proc = subprocess.Popen(
        command(algo, "--run-name", "busy", "--checkpoint-every", "1"), cwd=tmp_path, stdout=subprocess.PIPE, text=True
    )
    for line in proc.stdout:
        if line.startswith("iteration 2/"):  # a checkpoint exists: the second process would resume it
            proc.send_signal(signal.SIGSTOP)  # paused, not finished, while the others try
            break
    try:
        for how in (("--run-name", "busy"), ("--run-name", "busy", "--auto-resume"), ("--resume", "runs/busy")):
            second = run(algo, tmp_path, *how)
            assert second.returncode == 1, second.stdout
            assert second.stderr == (
                f"error: runs/busy is in use by process {proc.pid} on {socket.gethostname()}; one run folder takes"
                " one process (wait, or choose another --run-name).\n"
            ), how
        assert proc.poll() is None  # the first run was not disturbed
    finally:
        proc.kill()
        proc.communicate(timeout=60)
    resumed = run(algo, tmp_path, "--run-name", "busy", "--auto-resume")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resuming runs/busy after iteration " in resumed.stdout


def test_a_resume_keeps_the_runs_own_flags(tmp_path):
    # started with run flags, stopped, resumed exactly as the stop message says: the flags still hold
    flags = ("--run-name", "f", "--save-model", "--checkpoint-every", "0")
    rc, out, err = start_and_signal("p3o", tmp_path, signal.SIGTERM, 2, *flags)
    assert rc == 128 + signal.SIGTERM, err
    again = re.search(r"continue with (--resume \S+)\n", out).group(1).split()
    script = os.path.join(ROOT, "p3o_atari_envpool.py")
    proc = subprocess.run([sys.executable, script, *again], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run_dir = tmp_path / "runs" / "f"
    assert (run_dir / "p3o_atari_envpool.cleanrl_model").is_file()
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["args"]["checkpoint_every"] == 0
    # a flag given again on the resume command line wins over the run's
    rc, out, err = start_and_signal("p3o", tmp_path, signal.SIGTERM, 2, "--run-name", "g", "--checkpoint-every", "0")
    assert rc == 128 + signal.SIGTERM, err
    proc = subprocess.run(
        [sys.executable, script, "--resume", "runs/g", "--checkpoint-every", "4", "--save-model"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert torch.load(tmp_path / "runs" / "g" / "checkpoint.pt", weights_only=True)["args"]["checkpoint_every"] == 4
    assert (tmp_path / "runs" / "g" / "p3o_atari_envpool.cleanrl_model").is_file()


def test_a_start_killed_before_its_first_periodic_checkpoint_resumes_from_its_start(tmp_path):
    """A new run writes a checkpoint before it logs anything, so a start killed at any point is resumed (from
    iteration 0, as the same run: the same seed, the same initial weights) and every point is logged once."""
    rc, _, _ = start_and_signal("ppo", tmp_path, signal.SIGKILL, 3, "--run-name", "c", "--checkpoint-every", "0")
    assert rc == -signal.SIGKILL
    run_dir = tmp_path / "runs" / "c"
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["iteration"] == 0
    proc = run("ppo", tmp_path, "--run-name", "c", "--auto-resume")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resuming runs/c after iteration 0 (0 steps)" in proc.stdout
    after = scalars(str(run_dir))
    for tag in PER_ITERATION:
        assert [s for s, _ in after[tag]] == [BATCH * i for i in range(1, ITERATIONS + 1)], tag
    assert hyperparameters(str(run_dir)).count("|param|value|") == 1
    # resumed from its start, it is the run an uninterrupted start makes: the same numbers
    whole = run("ppo", tmp_path, "--run-name", "whole")
    assert whole.returncode == 0, whole.stderr[-3000:]
    assert scalars(str(tmp_path / "runs" / "whole"))["losses/value_loss"] == after["losses/value_loss"]


@pytest.mark.parametrize("algo", SCRIPTS)
def test_a_non_finite_loss_stops_the_run_and_keeps_the_last_finite_checkpoint(algo, tmp_path, monkeypatch):
    module = SCRIPTS[algo]
    calls = []

    def value_loss_that_turns_nan(*args):  # finite for two iterations (UPDATES calls each), then nan
        calls.append(1)
        loss = original(*args)
        return loss * float("nan") if len(calls) > 2 * UPDATES else loss

    original = module.value_loss
    monkeypatch.setattr(module, "value_loss", value_loss_that_turns_nan)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:
        module.main(args_for(module, run_name="nan", checkpoint_every=1, cuda=False))
    assert excinfo.value.code == (
        "error: the loss or the policy became non-finite (nan or inf) in iteration 3, so the run stopped and"
        " runs/nan/checkpoint.pt keeps the last weights it could act with (a lower --learning-rate or"
        " --max-grad-norm may help)."
    )
    saved = torch.load(tmp_path / "runs" / "nan" / "checkpoint.pt", weights_only=True)
    assert saved["iteration"] == 2 and not saved["finished"]
    assert all(torch.isfinite(w).all() for w in saved["model_state_dict"].values())
    assert max(s for s, _ in scalars(str(tmp_path / "runs" / "nan"))["losses/value_loss"]) == 2 * BATCH


def test_a_failed_checkpoint_write_leaves_the_previous_checkpoint_whole(stopped_run, tmp_path, monkeypatch):
    # a full disk half-way through writing over a good checkpoint: the old one still loads, no .tmp is left
    _, stopped_dir, iteration = stopped_run
    shutil.copytree(stopped_dir, tmp_path / "runs" / "d")
    path = str(tmp_path / "runs" / "d" / "checkpoint.pt")
    good = torch.load(path, weights_only=True)
    real_open = builtins.open

    class HalfWritten:  # writes half of what it is given, then the disk is full
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            self.f.write(bytes(data)[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def full_disk_open(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        return HalfWritten(f) if str(file).endswith(".tmp") and "w" in mode else f

    monkeypatch.setattr(builtins, "open", full_disk_open)
    agent = ppo.Agent(4)
    args = ppo.Args(num_envs=4, num_steps=32, num_minibatches=2, total_timesteps=BATCH * ITERATIONS)
    assert args.batch_size == BATCH
    optimizer = torch.optim.Adam(agent.parameters())
    with pytest.raises(SystemExit) as excinfo:
        ppo.save(path, agent, args, optimizer, iteration + 1)
    monkeypatch.undo()
    assert excinfo.value.code == (
        f"error: writing {path} failed (No space left on device), so it is as it was; make room and continue with"
        f" --resume {os.path.dirname(path)}."
    )
    assert not os.path.exists(f"{path}.tmp")
    again = torch.load(path, weights_only=True)
    assert again["iteration"] == good["iteration"] == iteration
    for name, tensor in good["model_state_dict"].items():
        assert torch.equal(again["model_state_dict"][name], tensor), name


@pytest.mark.parametrize("algo", SCRIPTS)
def test_a_failed_model_file_keeps_the_checkpoint_to_redo_the_last_stage(algo, tmp_path, monkeypatch):
    """The model file fails to be written after training (a full disk): the last iteration's checkpoint is kept, not
    marked finished, and the resume the sentence names writes the model and the finished checkpoint, trains nothing."""
    module = SCRIPTS[algo]
    save = module.save

    def full_disk_at_the_model(path, *args, **kwargs):
        if path.endswith(".cleanrl_model"):
            sys.exit(f"error: writing {path} failed (No space left on device)")
        return save(path, *args, **kwargs)

    monkeypatch.setattr(module, "save", full_disk_at_the_model)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit, match="No space left on device"):
        module.main(args_for(module, run_name="last", save_model=True, cuda=False))
    saved = torch.load(tmp_path / "runs" / "last" / "checkpoint.pt", weights_only=True)
    assert saved["iteration"] == ITERATIONS and not saved["finished"]
    monkeypatch.undo()
    script = os.path.join(ROOT, f"{algo}_atari_envpool.py")
    proc = subprocess.run(
        [sys.executable, script, "--resume", "runs/last"], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"resuming runs/last after iteration {ITERATIONS}" in proc.stdout and "iteration 1/" not in proc.stdout
    assert (tmp_path / "runs" / "last" / f"{algo}_atari_envpool.cleanrl_model").is_file()
    assert torch.load(tmp_path / "runs" / "last" / "checkpoint.pt", weights_only=True)["finished"]


def full_disk(tmp_path, megabytes):
    """runs/ as a tmpfs of this size (a real full disk), unmounted when the `with` ends."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    (tmp_path / "runs").mkdir()
    mount = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={megabytes}M", "tmpfs", str(tmp_path / "runs")], capture_output=True
    )
    if mount.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mount.stderr.decode().strip()}")
    mounted = contextlib.ExitStack()
    mounted.callback(subprocess.run, ["umount", str(tmp_path / "runs")], check=True)
    return mounted


def test_a_full_disk_stops_the_run_with_a_sentence_and_keeps_its_checkpoint(tmp_path):
    # runs/ is a 30 MB tmpfs: room for the first checkpoint (7 MB: the network, and Adam with no state yet) and the
    # next (20 MB: Adam's moments too) beside it, and not for a third while the second is there
    with full_disk(tmp_path, 30):
        proc = run("ppo", tmp_path, "--run-name", "full", "--checkpoint-every", "1")
        assert proc.returncode == 1, proc.stdout
        (line,) = [x for x in proc.stderr.splitlines() if x.startswith("error: ")]
        assert line == (
            "error: writing runs/full/checkpoint.pt failed (No space left on device), so it is as it was; make room"
            " and continue with --resume runs/full."
        )
        assert "Traceback" not in proc.stderr and "iteration 2/" in proc.stdout and "iteration 3/" not in proc.stdout
        saved = torch.load(tmp_path / "runs" / "full" / "checkpoint.pt", weights_only=True)
        assert saved["iteration"] == 1 and not (tmp_path / "runs" / "full" / "checkpoint.pt.tmp").exists()


def test_a_full_disk_at_the_first_checkpoint_leaves_a_run_that_starts_again(tmp_path):
    # runs/ is a 4 MB tmpfs: not even the first checkpoint (7 MB) fits. Nothing was logged, so the advice is to run the
    # same command again (there is nothing to resume), which then works once there is room
    with full_disk(tmp_path, 4):
        proc = run("ppo", tmp_path, "--run-name", "first")
        assert proc.returncode == 1
        assert proc.stderr.splitlines()[-1] + "\n" == (
            "error: writing runs/first/checkpoint.pt failed (No space left on device), so it is as it was; make room"
            " and run it again.\n"
        )
        assert os.listdir(tmp_path / "runs" / "first") == [".lock"]
    again = run("ppo", tmp_path, "--run-name", "first", "--total-timesteps", str(BATCH))
    assert again.returncode == 0, again.stderr[-3000:]


def test_a_resume_may_restate_the_runs_own_values(tmp_path):
    """`--resume runs/x --total-timesteps 256` on a run of 256 steps is that run, not a refusal for the default
    sizes the other flags would have; another value is refused by name."""
    proc = run("ppo", tmp_path, "--run-name", "r", "--total-timesteps", str(2 * BATCH))
    assert proc.returncode == 0, proc.stderr[-3000:]
    script = os.path.join(ROOT, "ppo_atari_envpool.py")
    for restated in (["--total-timesteps", str(2 * BATCH)], ["--total-timesteps", str(2 * BATCH), "--num-envs", "4"]):
        again = subprocess.run(
            [sys.executable, script, "--resume", "runs/r", *restated], cwd=tmp_path, capture_output=True, text=True
        )
        assert again.returncode == 0 and again.stderr == "", again.stderr
        assert f"runs/r already finished ({2 * BATCH} steps); nothing to do." in again.stdout
    other = subprocess.run(
        [sys.executable, script, "--resume", "runs/r", "--total-timesteps", str(4 * BATCH)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert other.returncode == 1
    assert_refusal(other.stderr, "--resume runs/r/checkpoint.pt", f"--total-timesteps {2 * BATCH} (now {4 * BATCH})")


def test_a_finished_run_without_its_checkpoint_keeps_its_logs(tmp_path):
    """A finished run whose checkpoint was deleted (every run writes a checkpoint before it logs anything, so its event
    files without one are a run's that is done with): --auto-resume refuses in one sentence and deletes nothing."""
    proc = run("ppo", tmp_path, "--run-name", "done", "--total-timesteps", str(2 * BATCH), "--checkpoint-every", "0")
    assert proc.returncode == 0, proc.stderr[-3000:]
    run_dir = tmp_path / "runs" / "done"
    (run_dir / "checkpoint.pt").unlink()
    files = {p.name: p.read_bytes() for p in run_dir.glob("events.out.tfevents.*")}
    again = run("ppo", tmp_path, "--run-name", "done", "--total-timesteps", str(2 * BATCH), "--auto-resume")
    assert again.returncode == 1
    assert_refusal(again.stderr, "runs/done holds a run already", "--run-name")
    assert {p.name: p.read_bytes() for p in run_dir.glob("events.out.tfevents.*")} == files and files
    assert "iteration 1/" not in again.stdout


@pytest.mark.parametrize("algo", SCRIPTS)
def test_weights_blown_up_without_a_non_finite_loss_stop_the_run_before_a_checkpoint_takes_them(
    algo, tmp_path, monkeypatch
):
    """The last update of iteration 3 scales the weights by 1e20: still finite, and every loss was, but the network
    now overflows, so the next rollout could not sample. The run stops there with one sentence, and its
    checkpoint is iteration 2's, which plays."""
    module = SCRIPTS[algo]
    steps, step = [], torch.optim.Adam.step

    def blowing_up(self, *args, **kwargs):
        out = step(self, *args, **kwargs)
        steps.append(1)
        if len(steps) == 3 * UPDATES:
            with torch.no_grad():
                for group in self.param_groups:
                    for w in group["params"]:
                        w.mul_(1e20)
        return out

    monkeypatch.setattr(torch.optim.Adam, "step", blowing_up)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:
        module.main(args_for(module, run_name="big", checkpoint_every=1, cuda=False))
    assert excinfo.value.code == (
        "error: the loss or the policy became non-finite (nan or inf) in iteration 3, so the run stopped and"
        " runs/big/checkpoint.pt keeps the last weights it could act with (a lower --learning-rate or"
        " --max-grad-norm may help)."
    )
    monkeypatch.undo()
    saved = torch.load(tmp_path / "runs" / "big" / "checkpoint.pt", weights_only=True)
    assert saved["iteration"] == 2 and not saved["finished"]
    agent = module.Agent(4)
    agent.load_state_dict(saved["model_state_dict"])
    with torch.no_grad():
        logits = agent.actor(agent.hidden(torch.randint(0, 256, (8, 4, 84, 84), dtype=torch.uint8)))
    assert torch.isfinite(logits).all()


EVALUATE = os.path.join(ROOT, "benchmark", "evaluate.py")


def eval_points(run_dir) -> list[tuple[int, float]]:
    return scalars(str(run_dir)).get("eval/episodic_return", [])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished P3O run, not yet evaluated: (cwd, run folder)."""
    cwd = tmp_path_factory.mktemp("trained")
    proc = run("p3o", cwd, "--run-name", "t", "--total-timesteps", str(2 * BATCH))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return cwd, cwd / "runs" / "t"


def test_an_evaluation_that_fails_before_its_record_is_redone_once(trained, tmp_path, monkeypatch):
    """eval.json is the record that a run was evaluated, written last: an evaluation that fails after logging its points
    but before eval.json (a full disk) leaves no record, and the redo the README gives logs its points once."""
    from benchmark import evaluate

    shutil.copytree(trained[1], tmp_path / "t")
    run_dir = tmp_path / "t"
    real_replace = os.replace

    def full_disk_at_the_record(src, dst):
        if str(dst).endswith("eval.json"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", full_disk_at_the_record)
    with pytest.raises(OSError):
        evaluate.main(evaluate.Args(run=str(run_dir), episodes=2, cuda=False))
    monkeypatch.undo()
    assert not (run_dir / "eval.json").exists() and [s for s, _ in eval_points(run_dir)] == [0, 1]
    proc = subprocess.run(
        [sys.executable, EVALUATE, "--run", str(run_dir), "--episodes", "2"], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    first = eval_points(run_dir)
    assert [s for s, _ in first] == [0, 1]  # once, as eval.json
    assert json.loads((run_dir / "eval.json").read_text())["returns"] == [v for _, v in first]
    again = subprocess.run([sys.executable, EVALUATE, "--run", str(run_dir)], capture_output=True, text=True)
    assert again.returncode == 0 and "not played again" in again.stdout and eval_points(run_dir) == first


def test_a_signal_during_the_evaluation_stops_it_and_writes_nothing(trained, tmp_path):
    shutil.copytree(trained[1], tmp_path / "t")
    run_dir = tmp_path / "t"
    before = sorted(os.listdir(run_dir))
    cmd = [sys.executable, EVALUATE, "--run", str(run_dir), "--episodes", "8", "--video"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if line.startswith("device: "):  # the games start now: 8 full games with videos of an untrained agent
            proc.send_signal(signal.SIGTERM)
            break
    out, err = proc.communicate(timeout=300)
    out = "".join(lines) + out
    assert proc.returncode == 128 + signal.SIGTERM, (out, err)
    assert "stopped by signal 15: nothing was written" in out and "Traceback" not in err
    assert sorted(os.listdir(run_dir)) == before and not [p for p in os.listdir(tmp_path) if p.startswith(".")]
    resumed = subprocess.run([*cmd[:-1]], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert [step for step, _ in eval_points(run_dir)] == list(range(8))


def test_a_run_whose_output_pipe_closes_goes_on_to_its_checkpoint(tmp_path):
    """`... | tee log` ended by Ctrl-C: the reader of the run's output is gone before the run has stopped. The run's
    next print must not kill it before its checkpoint: it checkpoints the iteration the signal ended and exits
    128 + signal, as with its output intact."""
    cmd = command("ppo", "--run-name", "p", "--checkpoint-every", "0")
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("iteration 2/"):
            break
    proc.stdout.close()  # the reader goes away (tee died with the Ctrl-C) ...
    proc.send_signal(signal.SIGINT)  # ... and the run gets the Ctrl-C too
    err = proc.stderr.read()
    assert proc.wait(timeout=300) == 128 + signal.SIGINT, err
    assert "Traceback" not in err and "BrokenPipeError" not in err
    saved = torch.load(tmp_path / "runs" / "p" / "checkpoint.pt", weights_only=True)
    assert saved["iteration"] >= 2 and not saved["finished"]


def test_a_signal_while_the_last_checkpoint_is_written_is_one_sentence_and_128_plus_signal(tmp_path, monkeypatch):
    """The one handler only notes a signal: one that comes while the last iteration's checkpoint is being written
    interrupts nothing (no `.tmp` left, no traceback); the run says how to continue and exits 128 + signal."""
    save = ppo.save

    def signalled_while_saving(path, agent, args, optimizer=None, iteration=0, **kwargs):
        if iteration == ITERATIONS:
            os.kill(os.getpid(), signal.SIGINT)
        return save(path, agent, args, optimizer, iteration, **kwargs)

    monkeypatch.setattr(ppo, "save", signalled_while_saving)
    monkeypatch.chdir(tmp_path)
    before = signal.getsignal(signal.SIGINT)  # Python's default_int_handler; SIG_IGN in a pytest-xdist worker
    with pytest.raises(SystemExit) as excinfo:
        ppo.main(args_for(ppo, run_name="last", cuda=False))
    assert excinfo.value.code == 128 + signal.SIGINT
    assert not (tmp_path / "runs" / "last" / "checkpoint.pt.tmp").exists()
    saved = torch.load(tmp_path / "runs" / "last" / "checkpoint.pt", weights_only=True)
    assert saved["iteration"] == ITERATIONS and not saved["finished"]
    assert signal.getsignal(signal.SIGINT) == before  # the run's handler went with it
    monkeypatch.undo()
    proc = run("ppo", tmp_path, "--resume", "runs/last")
    assert proc.returncode == 0 and torch.load(tmp_path / "runs" / "last" / "checkpoint.pt")["finished"]


def test_auto_resume_of_a_copied_run_folder_continues_the_copy(stopped_run, tmp_path):
    """A run folder copied (or renamed) and continued under its new name is that folder's run: the name is a run
    flag, and the advice the run gives names the folder it is in, not the one it was started in."""
    _, stopped_dir, iteration = stopped_run
    shutil.copytree(stopped_dir, tmp_path / "runs" / "copy")
    proc = subprocess.Popen(
        command("ppo", "--run-name", "copy", "--auto-resume"), cwd=tmp_path, stdout=subprocess.PIPE, text=True
    )
    out = []
    for line in proc.stdout:
        out.append(line)
        if line.startswith(f"iteration {iteration + 1}/"):
            proc.send_signal(signal.SIGTERM)
            break
    out = "".join(out) + proc.communicate(timeout=300)[0]
    assert proc.returncode == 128 + signal.SIGTERM, out
    assert f"resuming runs/copy after iteration {iteration}" in out
    assert "continue with --resume runs/copy\n" in out and "runs/s" not in out
    assert not os.path.exists(tmp_path / "runs" / "s")


def test_an_unreadable_checkpoint_is_named_with_the_flag_that_was_given(tmp_path):
    (tmp_path / "runs" / "bad").mkdir(parents=True)
    (tmp_path / "runs" / "bad" / "checkpoint.pt").write_bytes(b"not a checkpoint" * 100)
    proc = run("ppo", tmp_path, "--run-name", "bad", "--auto-resume")
    assert proc.returncode == 1
    assert proc.stderr == (
        "error: --auto-resume runs/bad/checkpoint.pt is not a checkpoint these scripts can read (damaged, or another"
        " kind of file).\n"
    )


def test_ctrl_c_in_a_filmed_evaluation_into_a_new_folder_leaves_nothing_and_no_noise(trained, tmp_path):
    """Ctrl-C in a terminal signals the whole foreground group, evaluate.py and its ffmpeg encoders alike: the
    evaluation stops with 128 + 2 and one line, no traceback or encoder output, and no hidden half-written folder."""
    cmd = [sys.executable, EVALUATE, "--model-path", str(trained[1] / "checkpoint.pt"), "--episodes", "8"]
    cmd += ["--run-dir", str(tmp_path / "clip"), "--video", "--no-cuda"]
    proc = subprocess.Popen(
        cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if line.startswith("device: "):
            time.sleep(2)  # the games and their encoders under way
            os.killpg(proc.pid, signal.SIGINT)
            break
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGINT, (lines, out, err)
    assert err == "" and "stopped by signal 2: nothing was written" in out, err
    assert os.listdir(tmp_path) == []


def filmed_evaluation(trained, tmp_path):
    from benchmark import evaluate

    model = str(trained[1] / "checkpoint.pt")
    return evaluate.Args(model_path=model, run_dir=str(tmp_path / "clip"), video=True, episodes=2, cuda=False)


def test_a_stop_signal_is_noted_and_ends_the_games_at_their_next_step_with_the_encoders_killed(
    trained, tmp_path, capfd, caplog, monkeypatch
):
    """The handler only notes a signal: an exit raised in it could land in Python's at-fork hooks as an encoder
    starts, which print it and play on (the evaluation was written, exit 0). A stop that comes before the first
    frame ends the games at their first step and kills the encoders: none is left to finish an empty video aloud."""
    from benchmark import evaluate

    monkeypatch.setattr(evaluate, "STOPS", [])
    before = signal.signal(signal.SIGINT, evaluate.note_stop)
    try:
        os.kill(os.getpid(), signal.SIGINT)
        noted = list(evaluate.STOPS)  # the handler has run, and raised nothing
    finally:
        signal.signal(signal.SIGINT, before)
    assert noted == [signal.SIGINT]
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        evaluate.main(filmed_evaluation(trained, tmp_path))
    out, err = capfd.readouterr()
    assert stopped.value.code == 128 + signal.SIGINT and "stopped by signal 2: nothing was written" in out
    assert err == "" and caplog.messages == [] and os.listdir(tmp_path) == []  # imageio-ffmpeg's warnings log


def test_an_error_after_a_stop_signal_is_the_stop(trained, tmp_path, capfd, monkeypatch):
    """Ctrl-C reaches the helpers ffmpeg's wrapper runs in our process group (its encoder probe, whose empty answer
    it then fails to parse): the evaluation exits as stopped, in one line, not with the error's traceback."""
    import imageio_ffmpeg

    from benchmark import evaluate

    def probe_killed_by_the_ctrl_c(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        raise IndexError("list index out of range")

    monkeypatch.setattr(evaluate, "STOPS", [])
    monkeypatch.setattr(imageio_ffmpeg, "write_frames", probe_killed_by_the_ctrl_c)
    monkeypatch.chdir(tmp_path)
    before = signal.signal(signal.SIGINT, evaluate.note_stop)
    try:
        with pytest.raises(SystemExit) as stopped:
            evaluate.main(filmed_evaluation(trained, tmp_path))
    finally:
        signal.signal(signal.SIGINT, before)
    out, err = capfd.readouterr()
    assert stopped.value.code == 128 + signal.SIGINT and "stopped by signal 2: nothing was written" in out
    assert err == "" and os.listdir(tmp_path) == []

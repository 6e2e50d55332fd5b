"""Checkpoints and resume: stopped or killed runs continue where their checkpoint left them, every
iteration's TensorBoard points exactly once and the killed run's points before the checkpoint untouched;
bad checkpoints and changed arguments are refused by name."""

import os
import re
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT, scalars

SCRIPTS = {"ppo": ppo, "p3o": p3o}
BATCH, ITERATIONS, UPDATES = 4 * 32, 10, 2  # UPDATES: minibatches x epochs per iteration
FLAGS = ["--env-id", "Breakout-v5", "--num-envs", "4", "--num-steps", "32", "--num-minibatches", "2"]
FLAGS += ["--update-epochs", "1", "--total-timesteps", str(BATCH * ITERATIONS), "--eval-episodes", "0", "--seed", "5"]
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
    message = refusal(ppo, cwd, monkeypatch, args_for(ppo, num_envs=8, resume=run_dir))
    assert message == (
        f"error: --resume {run_dir}/checkpoint.pt was started with --num-envs 4 (now 8); "
        "resume it with the same arguments."
    )
    message = refusal(ppo, cwd, monkeypatch, args_for(ppo, learning_rate=3e-4, seed=6, resume=run_dir))
    assert "--seed 5 (now 6), --learning-rate 0.001 (now 0.0003)" in message
    message = refusal(p3o, cwd, monkeypatch, args_for(p3o, resume=run_dir))
    assert (
        message == f"error: --resume {run_dir}/checkpoint.pt is a ppo checkpoint; resume it with ppo_atari_envpool.py."
    )


def test_a_bare_resume_takes_the_saved_arguments(stopped_run, monkeypatch):
    # `--resume DIR` alone: every experiment flag left at its default takes the checkpoint's value
    cwd, run_dir, iteration = stopped_run
    args = ppo.Args(resume=run_dir, eval_episodes=0)
    monkeypatch.chdir(cwd)
    opened, checkpoint = ppo.open_run(args)
    assert opened == run_dir and checkpoint["iteration"] == iteration
    assert (args.num_envs, args.num_steps, args.seed, args.total_timesteps) == (4, 32, 5, BATCH * ITERATIONS)
    assert args.eval_episodes == 0 and args.run_name == "s"


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_damaged_checkpoints_are_refused_by_name(damage, stopped_run, tmp_path, monkeypatch):
    _, run_dir, _ = stopped_run
    data = open(os.path.join(run_dir, "checkpoint.pt"), "rb").read()
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"not a checkpoint" * 100, "empty": b""}[damage])
    message = refusal(ppo, tmp_path, monkeypatch, args_for(ppo, resume=str(bad)))
    assert message.startswith(f"error: --resume {bad} is not a readable checkpoint; it may be truncated or corrupt")


def test_a_model_file_is_not_a_checkpoint(stopped_run, tmp_path, monkeypatch):
    _, run_dir, _ = stopped_run
    saved = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
    model = {k: saved[k] for k in ("format", "algorithm", "args", "model_state_dict")}
    torch.save(model, tmp_path / "model.cleanrl_model")
    message = refusal(ppo, tmp_path, monkeypatch, args_for(ppo, resume=str(tmp_path / "model.cleanrl_model")))
    assert message == f"error: --resume {tmp_path}/model.cleanrl_model is not a checkpoint written by these scripts."


def test_a_run_name_in_use_is_not_overwritten(stopped_run, monkeypatch):
    cwd, _, _ = stopped_run
    message = refusal(ppo, cwd, monkeypatch, args_for(ppo, run_name="s"))
    assert message == "error: runs/s already holds a run; continue it with --resume runs/s."


def test_auto_resume_needs_a_run_name(tmp_path, monkeypatch):
    message = refusal(ppo, tmp_path, monkeypatch, args_for(ppo, auto_resume=True))
    assert message == "error: --auto-resume needs --run-name, the run folder it continues."


def test_resume_of_a_missing_checkpoint_is_refused(tmp_path, monkeypatch):
    message = refusal(p3o, tmp_path, monkeypatch, args_for(p3o, resume="runs/nothing-here"))
    assert message == "error: --resume runs/nothing-here: there is no checkpoint there."


def test_refusals_on_the_command_line_exit_1_with_one_sentence(stopped_run):
    cwd, run_dir, _ = stopped_run
    proc = run("p3o", cwd, "--resume", run_dir)
    assert proc.returncode == 1
    assert (
        proc.stderr
        == f"error: --resume {run_dir}/checkpoint.pt is a ppo checkpoint; resume it with ppo_atari_envpool.py.\n"
    )

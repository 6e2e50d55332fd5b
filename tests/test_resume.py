"""Checkpoints and resume: killed runs continue where their checkpoint left them, with nothing
duplicated or missing in TensorBoard; bad checkpoints and changed arguments are refused by name."""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BATCH = 4 * 32
ITERATIONS = 10
FLAGS = ["--env-id", "Breakout-v5", "--num-envs", "4", "--num-steps", "32", "--num-minibatches", "2"]
FLAGS += ["--update-epochs", "1", "--total-timesteps", str(BATCH * ITERATIONS), "--eval-episodes", "0"]
FLAGS += ["--checkpoint-every", "3", "--seed", "5"]


def command(algo, *extra):
    return [sys.executable, os.path.join(ROOT, f"{algo}_atari_envpool.py"), *FLAGS, *extra]


def run(algo, cwd, *extra):
    return subprocess.run(command(algo, *extra), cwd=cwd, capture_output=True, text=True, timeout=600)


def start_and_kill(algo, cwd, sig, at_iteration, *extra):
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


def steps(run_dir, tag):
    acc = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    acc.Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)]


@pytest.mark.parametrize(
    "algo,sig,at_iteration,last_checkpoint",
    [("ppo", signal.SIGTERM, 3, None), ("p3o", signal.SIGKILL, 5, 3)],
    ids=["ppo-SIGTERM", "p3o-SIGKILL"],
)
def test_killed_run_resumes_to_the_same_end_with_every_iteration_once(
    algo, sig, at_iteration, last_checkpoint, tmp_path
):
    rc, out, err = start_and_kill(algo, tmp_path, sig, at_iteration, "--run-name", "r")
    run_dir = str(tmp_path / "runs" / "r")
    if sig == signal.SIGTERM:
        # a clean stop: the checkpoint holds the last finished iteration (at least the one printed)
        assert rc == 128 + signal.SIGTERM, err
        assert "Traceback" not in err
        assert "stopped by signal 15: checkpoint after iteration" in out
        saved = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
        assert saved["iteration"] >= at_iteration and not saved["finished"]
    else:
        assert rc == -signal.SIGKILL
        saved = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
        assert saved["iteration"] == last_checkpoint  # the periodic checkpoint; later points get purged
    assert not os.path.exists(os.path.join(run_dir, "checkpoint.pt.tmp"))

    resumed = run(algo, tmp_path, "--resume", run_dir)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resuming {run_dir} after iteration {saved['iteration']}" in resumed.stdout
    assert f"iteration {ITERATIONS}/{ITERATIONS} global_step={BATCH * ITERATIONS} " in resumed.stdout

    expected_steps = [BATCH * i for i in range(1, ITERATIONS + 1)]
    for tag in ("losses/value_loss", "charts/learning_rate", "charts/SPS"):
        assert [s for s, _ in steps(run_dir, tag)] == expected_steps, tag
    # the learning-rate schedule (the default 1e-3, annealed) continues where it was
    lrs = [v for _, v in steps(run_dir, "charts/learning_rate")]
    np.testing.assert_allclose(lrs, [1e-3 * (1 - i / ITERATIONS) for i in range(ITERATIONS)], rtol=1e-6)
    episode_steps = [s for s, _ in steps(run_dir, "charts/episodic_return")]
    assert episode_steps == sorted(episode_steps)

    final = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
    assert final["finished"] and final["global_step"] == BATCH * ITERATIONS
    again = run(algo, tmp_path, "--resume", run_dir)
    assert again.returncode == 0 and "already finished" in again.stdout


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory):
    """A PPO run stopped by SIGTERM after a few iterations: (cwd, run folder)."""
    cwd = tmp_path_factory.mktemp("stopped")
    rc, out, err = start_and_kill("ppo", cwd, signal.SIGTERM, 3, "--run-name", "s")
    assert rc == 128 + signal.SIGTERM, err
    return cwd, str(cwd / "runs" / "s")


@pytest.mark.parametrize("module", [ppo], ids=["ppo"])
def test_restore_gives_back_model_optimizer_lr_and_rng_states(module, stopped_run):
    _, run_dir = stopped_run
    path, saved = module.load_checkpoint(run_dir)
    agent = module.Agent(4)
    optimizer = torch.optim.Adam(agent.parameters(), lr=123.0, eps=1e-5)
    torch.manual_seed(999)
    np.random.seed(999)
    module.restore(saved, agent, optimizer)
    for name, tensor in agent.state_dict().items():
        assert torch.equal(tensor, saved["model_state_dict"][name]), name
    restored_opt = optimizer.state_dict()
    assert restored_opt["param_groups"][0]["lr"] == saved["optimizer_state_dict"]["param_groups"][0]["lr"]
    for key, state in restored_opt["state"].items():
        for field in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(state[field], saved["optimizer_state_dict"]["state"][key][field])
    now = module.rng_state()
    assert now["python"] == saved["rng_state"]["python"]
    assert (
        torch.equal(now["numpy"][1], saved["rng_state"]["numpy"][1])
        and now["numpy"][2] == saved["rng_state"]["numpy"][2]
    )
    assert torch.equal(now["torch"], saved["rng_state"]["torch"])
    # and the generators continue as the saved states say
    draws = (np.random.rand(), torch.rand(1).item())
    module.set_rng_state(saved["rng_state"])
    assert (np.random.rand(), torch.rand(1).item()) == draws


def args_for(module, **overrides):
    """The Args of FLAGS, for calling a script's main in-process (the refusals come before any env)."""
    flags = dict(zip(FLAGS[::2], FLAGS[1::2], strict=True))
    kwargs = {flag[2:].replace("-", "_"): value for flag, value in flags.items()}
    defaults = module.Args()
    kwargs = {k: type(getattr(defaults, k))(v) for k, v in kwargs.items()}
    return module.Args(**(kwargs | overrides))


def refusal(module, cwd, monkeypatch, **overrides):
    monkeypatch.chdir(cwd)
    with pytest.raises(SystemExit) as excinfo:
        module.main(args_for(module, **overrides))
    return str(excinfo.value.code)


def test_changed_arguments_are_refused(stopped_run, monkeypatch):
    cwd, run_dir = stopped_run
    message = refusal(ppo, cwd, monkeypatch, num_envs=8, resume=run_dir)
    assert f"--resume {run_dir}/checkpoint.pt was started with --num-envs 4 (now 8)" in message
    message = refusal(ppo, cwd, monkeypatch, learning_rate=3e-4, seed=6, resume=run_dir)
    assert "--seed 5 (now 6), --learning-rate 0.001 (now 0.0003)" in message
    assert "is a ppo checkpoint; resume it with ppo_atari_envpool.py" in refusal(p3o, cwd, monkeypatch, resume=run_dir)


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_damaged_checkpoints_are_refused_by_name(damage, stopped_run, tmp_path, monkeypatch):
    _, run_dir = stopped_run
    data = open(os.path.join(run_dir, "checkpoint.pt"), "rb").read()
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"not a checkpoint" * 100, "empty": b""}[damage])
    message = refusal(ppo, tmp_path, monkeypatch, resume=str(bad))
    assert message.startswith(f"error: --resume {bad} is not a readable checkpoint; it may be truncated or corrupt")


def test_a_run_name_in_use_is_not_overwritten(stopped_run, monkeypatch):
    cwd, _ = stopped_run
    message = refusal(ppo, cwd, monkeypatch, run_name="s")
    assert "runs/s already holds a run; continue it with --resume runs/s" in message


def test_auto_resume_needs_a_run_name(tmp_path, monkeypatch):
    assert "--auto-resume needs --run-name" in refusal(ppo, tmp_path, monkeypatch, auto_resume=True)


def test_resume_of_a_missing_checkpoint_is_refused(tmp_path, monkeypatch):
    message = refusal(p3o, tmp_path, monkeypatch, resume="runs/nothing-here")
    assert "--resume runs/nothing-here: there is no checkpoint there." in message


def test_refusals_on_the_command_line_exit_nonzero_without_traceback(stopped_run):
    cwd, run_dir = stopped_run
    proc = run("p3o", cwd, "--resume", run_dir)
    assert proc.returncode == 1
    assert "is a ppo checkpoint" in proc.stderr and "Traceback" not in proc.stderr

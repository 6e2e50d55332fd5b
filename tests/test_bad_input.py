"""Bad input fails fast: one sentence on stderr, exit status 1, no environment started, nothing written."""

import os
import subprocess
import sys

import pytest

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT

CASES = [
    ({"env_id": "Breakout-v55"}, "--env-id Breakout-v55 is not an envpool environment. Did you mean Breakout-v5, "),
    ({"env_id": "Brekout-v5"}, "--env-id Brekout-v5 is not an envpool environment. Did you mean Breakout-v5, "),
    ({"env_id": "NoSuchGame"}, "--env-id NoSuchGame is not an envpool environment. Atari ids look like Breakout-v5."),
    (
        {"env_id": "CartPole-v1"},
        "--env-id CartPole-v1 is an envpool environment but not an Atari game. Atari ids look like Breakout-v5.",
    ),
    (
        {"num_envs": 4, "num_steps": 10, "num_minibatches": 3, "total_timesteps": 400},
        "the batch (--num-envs * --num-steps = 40) does not divide into 3 minibatches.",
    ),
    (
        {"num_envs": 4, "num_steps": 32, "num_minibatches": 2, "total_timesteps": 100},
        "--total-timesteps 100 is less than one batch (128): no update would run.",
    ),
    ({"num_envs": 0}, "--num-envs must be positive, got 0."),
    ({"num_steps": -1}, "--num-steps must be positive, got -1."),
    ({"num_minibatches": 0}, "--num-minibatches must be positive, got 0."),
    ({"update_epochs": 0}, "--update-epochs must be positive, got 0."),
    ({"total_timesteps": 0}, "--total-timesteps must be positive, got 0."),
    ({"learning_rate": 0.0}, "--learning-rate must be positive, got 0.0."),
    ({"learning_rate": float("nan")}, "--learning-rate must be positive, got nan."),
    ({"gamma": 1.5}, "--gamma must lie in [0, 1], got 1.5."),
    ({"gae_lambda": -0.1}, "--gae-lambda must lie in [0, 1], got -0.1."),
    ({"checkpoint_every": -1}, "--checkpoint-every must be 0 or more, got -1."),
    ({"eval_episodes": -2}, "--eval-episodes must be 0 or more, got -2."),
    ({"auto_resume": True}, "--auto-resume needs --run-name, the run folder it continues."),
]
P3O_CASES = [
    ({"ewma_alpha": 0.0}, "--ewma-alpha must lie in (0, 1], got 0.0."),
    ({"ewma_alpha": 1.01}, "--ewma-alpha must lie in (0, 1], got 1.01."),
    ({"ewma_alpha": -0.5}, "--ewma-alpha must lie in (0, 1], got -0.5."),
]


@pytest.fixture
def no_envs(monkeypatch):
    import envpool

    def forbidden(*args, **kwargs):
        raise AssertionError("an environment was created before the arguments were checked")

    monkeypatch.setattr(envpool, "make", forbidden)


def refusal(module, overrides, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:
        module.main(module.Args(**overrides))
    assert not (tmp_path / "runs").exists()  # nothing written either
    return excinfo.value.code


@pytest.mark.parametrize("module", [ppo, p3o], ids=["ppo", "p3o"])
@pytest.mark.parametrize("overrides,message", CASES)
def test_bad_input_exits_with_one_sentence(module, overrides, message, no_envs, tmp_path, monkeypatch):
    code = refusal(module, overrides, tmp_path, monkeypatch)
    # sys.exit with a string: python prints it to stderr and exits with status 1
    assert isinstance(code, str) and "\n" not in code
    if message.endswith(", "):  # the close names' order is difflib's
        assert code.startswith(f"error: {message}") and code.endswith("?")
    else:
        assert code == f"error: {message}"


@pytest.mark.parametrize("overrides,message", P3O_CASES)
def test_bad_alpha_exits_with_one_sentence(overrides, message, no_envs, tmp_path, monkeypatch):
    assert refusal(p3o, overrides, tmp_path, monkeypatch) == f"error: {message}"


def test_ppo_has_no_alpha_flag():
    assert not hasattr(ppo.Args(), "ewma_alpha")


@pytest.mark.parametrize(
    "script,flags,stderr",
    [
        ("ppo_atari_envpool.py", ["--env-id", "NoSuchGame"], "--env-id NoSuchGame is not an envpool environment."),
        ("p3o_atari_envpool.py", ["--ewma-alpha", "0"], "--ewma-alpha must lie in (0, 1], got 0.0."),
        (
            "p3o_atari_envpool.py",
            ["--num-envs", "3", "--num-steps", "3", "--num-minibatches", "2"],
            "the batch (--num-envs * --num-steps = 9) does not divide into 2 minibatches.",
        ),
    ],
)
def test_command_line_exit_status_1_and_the_sentence(script, flags, stderr, tmp_path):
    proc = subprocess.run(
        [sys.executable, os.path.join(ROOT, script), *flags], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 1
    assert proc.stderr.startswith(f"error: {stderr}") and proc.stderr.count("\n") == 1
    assert not (tmp_path / "runs").exists()

"""Bad input fails fast: one clear sentence, a non-zero exit, and no environment started."""

import os
import subprocess
import sys

import pytest

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CASES = [
    ({"env_id": "Breakout-v55"}, "is not an envpool environment. Did you mean Breakout-v5"),
    ({"env_id": "Brekout-v5"}, "Did you mean Breakout-v5"),
    ({"env_id": "CartPole-v1"}, "is an envpool environment but not an Atari game"),
    ({"num_envs": 4, "num_steps": 10, "num_minibatches": 3, "total_timesteps": 400}, "does not divide into"),
    (
        {"num_envs": 4, "num_steps": 32, "num_minibatches": 2, "total_timesteps": 100},
        "is less than one batch (128): no update would run",
    ),
    ({"num_envs": 0}, "--num-envs must be positive"),
    ({"num_steps": -1}, "--num-steps must be positive"),
    ({"num_minibatches": 0}, "--num-minibatches must be positive"),
    ({"update_epochs": 0}, "--update-epochs must be positive"),
    ({"total_timesteps": 0}, "--total-timesteps must be positive"),
    ({"learning_rate": 0.0}, "--learning-rate must be positive"),
    ({"gamma": 1.5}, "--gamma must lie in [0, 1]"),
]
P3O_CASES = [
    ({"ewma_alpha": 0.0}, "--ewma-alpha must lie in (0, 1]"),
    ({"ewma_alpha": 1.01}, "--ewma-alpha must lie in (0, 1]"),
    ({"ewma_alpha": -0.5}, "--ewma-alpha must lie in (0, 1]"),
]


@pytest.fixture
def no_envs(monkeypatch):
    import envpool

    def forbidden(*args, **kwargs):
        raise AssertionError("an environment was created before the arguments were checked")

    monkeypatch.setattr(envpool, "make", forbidden)


@pytest.mark.parametrize("module", [ppo, p3o], ids=["ppo", "p3o"])
@pytest.mark.parametrize("overrides,message", CASES)
def test_bad_input_exits_with_a_clear_message(module, overrides, message, no_envs, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:
        module.main(module.Args(**overrides))
    assert isinstance(excinfo.value.code, str) and excinfo.value.code.startswith("error: ")
    assert message in excinfo.value.code
    assert "\n" not in excinfo.value.code  # one sentence on one line
    assert not (tmp_path / "runs").exists()  # nothing written either


@pytest.mark.parametrize("overrides,message", P3O_CASES)
def test_bad_alpha_exits_with_a_clear_message(overrides, message, no_envs, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:
        p3o.main(p3o.Args(**overrides))
    assert message in excinfo.value.code


def test_ppo_has_no_alpha_flag():
    assert not hasattr(ppo.Args(), "ewma_alpha")


@pytest.mark.parametrize(
    "script,flags,message",
    [
        ("ppo_atari_envpool.py", ["--env-id", "Pong-v4"], "Did you mean Pong-v5"),
        ("p3o_atari_envpool.py", ["--ewma-alpha", "0"], "--ewma-alpha must lie in (0, 1], got 0.0."),
        ("p3o_atari_envpool.py", ["--num-envs", "3", "--num-steps", "3", "--num-minibatches", "2"], "divide"),
    ],
)
def test_command_line_exit_status_and_message(script, flags, message, tmp_path):
    proc = subprocess.run(
        [sys.executable, os.path.join(ROOT, script), *flags],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "runs").exists()

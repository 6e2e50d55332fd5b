"""Bad input fails fast: one sentence on stderr, exit status 1, no environment started, nothing written."""

import os
import subprocess
import sys

import pytest

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT

SEED_MAX = 2**31 - 1 - 1_000_009
SEED_WHY = "(envpool seeds stay below 2^31, and this run derives seeds up to --seed + 1000009)"
UNDER_RUNS = "must be a plain relative name, so that the run stays under runs/."
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
    ({"learning_rate": float("nan")}, "--learning-rate must be a finite number, got nan."),
    ({"learning_rate": float("inf")}, "--learning-rate must be a finite number, got inf."),
    ({"gamma": float("nan")}, "--gamma must be a finite number, got nan."),
    ({"clip_coef": 0.0}, "--clip-coef must be positive, got 0.0."),
    ({"vf_coef": -1.0}, "--vf-coef must be positive, got -1.0."),
    ({"max_grad_norm": 0.0}, "--max-grad-norm must be positive, got 0.0."),
    ({"ent_coef": -0.01}, "--ent-coef must be 0 or more, got -0.01."),
    ({"ent_coef": float("-inf")}, "--ent-coef must be a finite number, got -inf."),
    ({"target_kl": 0.0}, "--target-kl must be positive, got 0.0."),
    ({"target_kl": float("nan")}, "--target-kl must be a finite number, got nan."),
    ({"batch_size": 512}, "--batch-size is computed from the other sizes, so it cannot be set (got 512)."),
    ({"num_iterations": 3}, "--num-iterations is computed from the other sizes, so it cannot be set (got 3)."),
    ({"gamma": 1.5}, "--gamma must lie in [0, 1], got 1.5."),
    ({"gae_lambda": -0.1}, "--gae-lambda must lie in [0, 1], got -0.1."),
    ({"checkpoint_every": -1}, "--checkpoint-every must be 0 or more, got -1."),
    ({"eval_episodes": -2}, "--eval-episodes must be 0 or more, got -2."),
    ({"auto_resume": True}, "--auto-resume needs --run-name, the run folder it continues."),
    # the defaults derive seeds up to seed + 1,000,009 (the 10th evaluation game); envpool's end at 2^31 - 1
    ({"seed": -1}, f"--seed must lie in [0, {SEED_MAX}] {SEED_WHY}, got -1."),
    ({"seed": 2**31 - 1}, f"--seed must lie in [0, {SEED_MAX}] {SEED_WHY}, got 2147483647."),
    # trained the whole run, then crashed in the final evaluation (its last game's seed was past 2^31 - 1)
    ({"seed": SEED_MAX + 1}, f"--seed must lie in [0, {SEED_MAX}] {SEED_WHY}, got {SEED_MAX + 1}."),
    (
        {"seed": 10, "eval_episodes": 2**31},
        "the run would derive seeds up to --seed + 2148483647 (evaluation games and iterations x envs), past"
        " envpool's 2^31 - 1: fewer --eval-episodes or --total-timesteps.",
    ),
    ({"run_name": "../elsewhere"}, f"--run-name '../elsewhere' {UNDER_RUNS}"),
    ({"run_name": "/tmp/elsewhere"}, f"--run-name '/tmp/elsewhere' {UNDER_RUNS}"),
    ({"run_name": "group/../../elsewhere"}, f"--run-name 'group/../../elsewhere' {UNDER_RUNS}"),
    ({"run_name": "group//run"}, f"--run-name 'group//run' {UNDER_RUNS}"),
    ({"run_name": "."}, f"--run-name '.' {UNDER_RUNS}"),
    ({"run_name": ""}, f"--run-name '' {UNDER_RUNS}"),
    ({"exp_name": "group/p3o"}, f"--exp-name 'group/p3o' {UNDER_RUNS}"),
    ({"exp_name": ".."}, f"--exp-name '..' {UNDER_RUNS}"),
    # settings that would only fail after training, when the model file is written, or in the first allocation
    ({"exp_name": "p" * 240}, "--exp-name is 240 bytes long, too long for the model file's name."),
    ({"num_steps": 10**9}, "the rollout's frames (--num-envs * --num-steps = 256000000000 x 4 x 84 x 84 bytes, "),
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
    if message.endswith(", "):  # the close names' order is difflib's, or the rest is long
        assert code.startswith(f"error: {message}") and code.endswith(("?", "."))
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


def test_a_run_folder_that_cannot_be_made_is_one_sentence(tmp_path, monkeypatch, no_envs):
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "blocker").write_text("a file where the folder would go")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as excinfo:
        ppo.main(ppo.Args(run_name="blocker/run"))
    assert excinfo.value.code == "error: cannot create the run folder runs/blocker/run (Not a directory)."


@pytest.mark.parametrize("module", [ppo, p3o], ids=["ppo", "p3o"])
def test_the_device_is_said_and_a_missing_gpu_is_warned_about(module, capsys):
    import torch

    assert module.say_device(torch.device("cpu"), cuda=False) == "cpu"
    out, err = capsys.readouterr()
    assert out == "device: cpu\n" and err == ""
    module.say_device(torch.device("cpu"), cuda=True)
    out, err = capsys.readouterr()
    build = f"built for CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
    assert out == "device: cpu\n"
    assert err == (
        f"warning: --cuda is on but torch {torch.__version__} ({build}) finds no usable GPU, so this run trains on the"
        " CPU (README.md, 'GPU and driver'; --no-cuda silences this).\n"
    )


@pytest.mark.parametrize(
    "tool,flags,flag",
    [
        (
            "evaluate.py",
            ["--random", "--env-id", "Breakout-v5", "--episodes", "1", "--run-dir", "{file}/eval"],
            "--run-dir",
        ),
        ("results.py", ["{runs}", "--out", "{file}"], "--out"),
        ("results.py", ["{runs}", "--out", "{file}/tables"], "--out"),
    ],
)
def test_an_output_folder_under_a_file_is_refused_before_the_work(tool, flags, flag, tmp_path):
    """A folder that cannot be made is one sentence up front, not a traceback after the games or the tables."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where the folder would go")
    runs = os.path.join(ROOT, "benchmark", "results", "breakout_gpu", "runs")
    flags = [f.format(file=blocker, runs=runs) for f in flags]
    proc = subprocess.run(
        [sys.executable, os.path.join(ROOT, "benchmark", tool), *flags],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 1, proc.stderr
    line = f"error: {flag} {flags[flags.index(flag) + 1]} "
    assert proc.stderr.startswith(line) and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert str(blocker) in proc.stderr and "is a file" in proc.stderr
    assert "game 0" not in proc.stdout and "wrote" not in proc.stdout  # no game played, no table written
    assert blocker.read_text() == "a file where the folder would go"

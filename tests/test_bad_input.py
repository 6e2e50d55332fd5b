"""Bad input fails fast: one sentence on stderr, exit status 1, no environment started, nothing written."""

import os
import subprocess
import sys

import pytest

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT, assert_refusal

SEED_MAX = 2**31 - (20_000_000 // 65536 + 1) * 256  # the defaults' run, resumed at its last iteration
# each case: what the one-sentence refusal must name (the flag, the value, the fix), not its whole wording
CASES = [
    ({"env_id": "Breakout-v55"}, ["--env-id Breakout-v55", "not an envpool Atari game", "did you mean Breakout-v5?"]),
    ({"env_id": "Brekout-v5"}, ["--env-id Brekout-v5", "not an envpool Atari game", "did you mean Breakout-v5"]),
    ({"env_id": "NoSuchGame"}, ["--env-id NoSuchGame", "not an envpool Atari game", "Breakout-v5"]),
    ({"env_id": "CartPole-v1"}, ["--env-id CartPole-v1", "not an envpool Atari game", "Breakout-v5"]),
    ({"num_envs": 4, "num_steps": 10, "num_minibatches": 3, "total_timesteps": 400}, ["40", "3 minibatches"]),
    ({"num_envs": 4, "num_steps": 32, "num_minibatches": 2, "total_timesteps": 100}, ["--total-timesteps 100", "128"]),
    ({"num_envs": 0}, ["--num-envs", "positive", "0"]),
    ({"num_steps": -1}, ["--num-steps", "positive", "-1"]),
    ({"num_minibatches": 0}, ["--num-minibatches", "positive", "0"]),
    ({"update_epochs": 0}, ["--update-epochs", "positive", "0"]),
    ({"total_timesteps": 0}, ["--total-timesteps", "positive", "0"]),
    ({"learning_rate": 0.0}, ["--learning-rate", "positive", "0.0"]),
    ({"learning_rate": float("nan")}, ["--learning-rate", "finite", "nan"]),
    ({"learning_rate": float("inf")}, ["--learning-rate", "finite", "inf"]),
    ({"gamma": float("nan")}, ["--gamma", "finite", "nan"]),
    ({"clip_coef": 0.0}, ["--clip-coef", "positive", "0.0"]),
    ({"vf_coef": -1.0}, ["--vf-coef", "positive", "-1.0"]),
    ({"max_grad_norm": 0.0}, ["--max-grad-norm", "positive", "0.0"]),
    ({"ent_coef": -0.01}, ["--ent-coef", "0 or more", "-0.01"]),
    ({"ent_coef": float("-inf")}, ["--ent-coef", "finite", "-inf"]),
    ({"target_kl": 0.0}, ["--target-kl", "positive", "0.0"]),
    ({"target_kl": float("nan")}, ["--target-kl", "finite", "nan"]),
    ({"gamma": 1.5}, ["--gamma", "[0, 1]", "1.5"]),
    ({"gae_lambda": -0.1}, ["--gae-lambda", "[0, 1]", "-0.1"]),
    ({"checkpoint_every": -1}, ["--checkpoint-every", "0 or more", "-1"]),
    ({"auto_resume": True}, ["--auto-resume", "--run-name"]),
    # a run resumed at iteration i seeds its envs seed + i * num_envs + j; envpool's seeds end at 2^31 - 1
    ({"seed": -1}, ["--seed", f"[0, {SEED_MAX}]", "got -1"]),
    ({"seed": 2**31 - 1}, ["--seed", f"[0, {SEED_MAX}]", "2147483647"]),
    ({"seed": SEED_MAX + 1}, ["--seed", f"[0, {SEED_MAX}]", f"got {SEED_MAX + 1}"]),
    ({"run_name": "../elsewhere"}, ["--run-name '../elsewhere'", "runs/"]),
    ({"run_name": "/tmp/elsewhere"}, ["--run-name '/tmp/elsewhere'", "runs/"]),
    ({"run_name": "group/../../elsewhere"}, ["--run-name 'group/../../elsewhere'", "runs/"]),
    ({"run_name": "group//run"}, ["--run-name 'group//run'", "runs/"]),
    ({"run_name": "."}, ["--run-name '.'", "runs/"]),
    ({"run_name": ""}, ["--run-name ''", "runs/"]),
    ({"exp_name": "group/p3o"}, ["--exp-name 'group/p3o'", "runs/"]),
    ({"exp_name": ".."}, ["--exp-name '..'", "runs/"]),
    # settings that would only fail after training, when the model file is written, or in the first allocation
    ({"exp_name": "p" * 240}, ["--exp-name", "240 bytes", "model file"]),
    ({"num_steps": 10**9}, ["--num-envs * --num-steps = 256000000000", "memory"]),
]
P3O_CASES = [
    ({"ewma_alpha": 0.0}, ["--ewma-alpha", "(0, 1]", "0.0"]),
    ({"ewma_alpha": 1.01}, ["--ewma-alpha", "(0, 1]", "1.01"]),
    ({"ewma_alpha": -0.5}, ["--ewma-alpha", "(0, 1]", "-0.5"]),
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
@pytest.mark.parametrize("overrides,fragments", CASES)
def test_bad_input_exits_with_one_sentence(module, overrides, fragments, no_envs, tmp_path, monkeypatch):
    code = refusal(module, overrides, tmp_path, monkeypatch)
    # sys.exit with a string: python prints it to stderr and exits with status 1
    assert isinstance(code, str)
    assert_refusal(code, *fragments)


@pytest.mark.parametrize("overrides,fragments", P3O_CASES)
def test_bad_alpha_exits_with_one_sentence(overrides, fragments, no_envs, tmp_path, monkeypatch):
    assert_refusal(refusal(p3o, overrides, tmp_path, monkeypatch), *fragments)


def test_ppo_has_no_alpha_flag():
    assert not hasattr(ppo.Args(), "ewma_alpha")


@pytest.mark.slow
@pytest.mark.parametrize("flag", ["--batch-size", "--minibatch-size", "--num-iterations"])
def test_computed_sizes_are_not_flags(flag, tmp_path):
    """The sizes computed from the others are refused by the parser as unknown flags, before anything starts."""
    script = os.path.join(ROOT, "ppo_atari_envpool.py")
    proc = subprocess.run([sys.executable, script, flag, "512"], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 2 and "Unrecognized options" in proc.stderr and flag in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "runs").exists()
    with pytest.raises(TypeError):
        ppo.Args(batch_size=512)
    args = ppo.Args(num_envs=4, num_steps=32, num_minibatches=2, total_timesteps=400)
    assert (args.batch_size, args.minibatch_size, args.num_iterations) == (128, 64, 3)


@pytest.mark.slow
@pytest.mark.parametrize(
    "script,flags,fragments",
    [
        ("ppo_atari_envpool.py", ["--env-id", "NoSuchGame"], ["--env-id NoSuchGame"]),
        ("p3o_atari_envpool.py", ["--ewma-alpha", "0"], ["--ewma-alpha", "0.0"]),
        (
            "p3o_atari_envpool.py",
            ["--num-envs", "3", "--num-steps", "3", "--num-minibatches", "2"],
            ["9", "2 minibatches"],
        ),
    ],
)
def test_command_line_exit_status_1_and_the_sentence(script, flags, fragments, tmp_path):
    proc = subprocess.run(
        [sys.executable, os.path.join(ROOT, script), *flags], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 1
    assert_refusal(proc.stderr, *fragments)
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


@pytest.mark.slow
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

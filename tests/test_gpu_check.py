"""benchmark/gpu_check.sh, the prepared GPU command, rehearsed on the CPU at tiny sizes: every step runs and
is read back, a broken step is named in one line, and the scripts train without imageio_ffmpeg (the GPU
bundle carries it without its ffmpeg)."""

import json
import math
import os
import subprocess
import sys

import pytest

from helpers import ROOT

CHECK = os.path.join(ROOT, "benchmark", "gpu_check.sh")
STEPS = ["environment", "tiny_ppo", "read_back_ppo", "tiny_p3o", "read_back_p3o", "sps_thesis", "sps_cleanrl"]
LIMIT = 1500  # seconds the rehearsal may take
pytestmark = pytest.mark.timeout(LIMIT + 60)  # above pyproject's 900 s per test, which would cut it first


def gpu_check(out, **knobs):
    env = os.environ | {"REHEARSAL": "1", "PYTHON": sys.executable, "OUT": str(out)} | knobs
    return subprocess.run(["bash", CHECK], cwd=out.parent, env=env, capture_output=True, text=True, timeout=LIMIT)


@pytest.fixture(scope="module")
def rehearsal(tmp_path_factory):
    out = tmp_path_factory.mktemp("rehearsal") / "out"
    return out, gpu_check(out)


def test_every_step_runs_and_the_outputs_fit_what_the_device_tool_brings_back(rehearsal):
    out, proc = rehearsal
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    summary = (out / "summary.txt").read_text().splitlines()
    assert [line.split()[1] for line in summary] == STEPS
    assert all(line.startswith("ok      ") for line in summary), summary
    # at most 8 files come back from a device call: these six, and no run folder among them
    files = {"summary.txt", "gpu_check.log", "tiny_ppo.json", "tiny_p3o.json", "sps_thesis.json", "sps_cleanrl.json"}
    assert set(os.listdir(out)) == files
    log = (out / "gpu_check.log").read_text()
    assert all(f"=== {step} (exit 0): " in log for step in STEPS)


@pytest.mark.parametrize("algo", ["ppo", "p3o"])
def test_the_tiny_runs_are_read_back(rehearsal, algo):
    out, _ = rehearsal
    tiny = json.loads((out / f"tiny_{algo}.json").read_text())
    assert tiny["device"] == "cpu" and tiny["eval_games"] == 1 and math.isfinite(tiny["eval_mean"])
    assert len(tiny["losses"]["losses/value_loss"]) == 2 and all(
        map(math.isfinite, tiny["losses"]["losses/value_loss"])
    )
    assert len(tiny["sps"]) == 2 and all(s > 0 for s in tiny["sps"])


@pytest.mark.parametrize("name", ["sps_thesis", "sps_cleanrl"])
def test_both_speed_measurements_are_sps_json_with_two_rounds(rehearsal, name):
    out, _ = rehearsal
    report = json.loads((out / f"{name}.json").read_text())
    assert report["settings"]["rounds"] == 2 and report["results"]["raw_env"]["rollout_sps"] > 0
    for algo in ("ppo", "p3o"):
        assert len(report["results"][algo]["rounds"]) == 2 and report["results"][algo]["iteration_sps"] > 0
    assert "p3o/ppo_iteration" in report["ratios"]


def test_a_failing_step_is_named_with_its_reason_in_one_line(tmp_path):
    proc = gpu_check(tmp_path / "out", ENV_ID="Qbertt-v5")
    assert proc.returncode == 1
    summary = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    assert [line.split()[1] for line in summary] == STEPS and summary[0].startswith("ok      environment")
    for line in summary[1:]:
        assert line.startswith("FAILED  "), line
    for step in ("tiny_ppo", "tiny_p3o", "sps_thesis", "sps_cleanrl"):
        (line,) = [x for x in summary if x.split()[1] == step]
        assert "exit 1: error: --env-id Qbertt-v5 is not an envpool environment. Did you mean Qbert-v5" in line
    for step in ("read_back_ppo", "read_back_p3o"):
        (line,) = [x for x in summary if x.split()[1] == step]
        assert line.endswith("exit 1: nothing to read back: the tiny run wrote no eval.json")


def test_the_scripts_train_without_imageio_ffmpeg(tmp_path):
    code = (
        "import sys; sys.modules['imageio_ffmpeg'] = None\n"  # any import of it now fails
        "import ppo_atari_envpool as ppo, p3o_atari_envpool as p3o\n"
        "for m in (ppo, p3o):\n"
        "    m.main(m.Args(num_envs=2, num_steps=16, num_minibatches=2, update_epochs=1, total_timesteps=32,"
        " eval_episodes=1, run_name=m.ALGORITHM, cuda=False))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=os.environ | {"PYTHONPATH": ROOT},
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "runs" / "ppo" / "eval.json").is_file() and (tmp_path / "runs" / "p3o" / "eval.json").is_file()


def test_without_a_gpu_the_check_stops_at_the_environment_step(tmp_path):
    """On the GPU machine a torch that finds no GPU must not read "ok": every later step would train on the CPU.
    Here (no GPU) the real check, not the rehearsal, fails its first step with the reason and runs nothing else."""
    proc = gpu_check(tmp_path / "out", REHEARSAL="0")
    assert proc.returncode == 1
    (line,) = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    assert line.startswith("FAILED  environment (") and "exit 1: torch " in line and "finds no usable GPU" in line
    assert "nothing else ran" in proc.stdout
    assert sorted(os.listdir(tmp_path / "out")) == ["gpu_check.log", "summary.txt"]

"""benchmark/gpu_check.sh, the prepared GPU command, rehearsed on the CPU at tiny sizes: both real runs and
sps.py run and are read back and compared, a broken step is named in one line, and the scripts train without
imageio_ffmpeg (the GPU bundle carries it without its ffmpeg)."""

import json
import math
import os
import subprocess
import sys
import tarfile

import pytest

from helpers import ROOT, scalars

CHECK = os.path.join(ROOT, "benchmark", "gpu_check.sh")
STEPS = ["environment", "run_ppo", "read_back_ppo", "run_p3o", "read_back_p3o", "sps_thesis", "runs_tgz", "compare"]
FILES = {"summary.txt", "gpu_check.log", "run_ppo.json", "run_p3o.json", "sps_thesis.json", "runs.tgz"}
LIMIT = 1500  # seconds the rehearsal may take
pytestmark = pytest.mark.timeout(LIMIT + 60)  # above pyproject's 900 s per test, which would cut it first


def gpu_check(out, **knobs):
    env = os.environ | {"REHEARSAL": "1", "PYTHON": sys.executable, "OUT": str(out)} | knobs
    return subprocess.run(["bash", CHECK], cwd=out.parent, env=env, capture_output=True, text=True, timeout=LIMIT)


def summary_steps(out):
    """The summary's step lines (the comparison's lines under them are indented)."""
    return [line for line in (out / "summary.txt").read_text().splitlines() if not line.startswith(" ")]


@pytest.fixture(scope="module")
def rehearsal(tmp_path_factory):
    out = tmp_path_factory.mktemp("rehearsal") / "out"
    return out, gpu_check(out)


def test_every_step_runs_and_the_outputs_fit_what_the_device_tool_brings_back(rehearsal):
    out, proc = rehearsal
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    steps = summary_steps(out)
    assert [line.split()[1] for line in steps] == STEPS
    assert all(line.startswith("ok      ") for line in steps), steps
    # at most 8 files come back from a device call: these six, and no run folder among them
    assert set(os.listdir(out)) == FILES
    log = (out / "gpu_check.log").read_text()
    assert all(f"=== {step} (exit 0): " in log for step in STEPS)


@pytest.mark.parametrize("algo", ["ppo", "p3o"])
def test_the_runs_are_read_back(rehearsal, algo):
    out, _ = rehearsal
    run = json.loads((out / f"run_{algo}.json").read_text())
    assert run["device"] == "cpu" and run["eval_games"] == 1 and math.isfinite(run["eval_mean"])
    assert run["steps"] == 384 and run["iterations"] == 3 and len(run["logged_sps"]) == 3
    assert run["steady_sps"] > 0 and len(run["rollout_s"]) == 3 and all(s > 0 for s in run["update_s"])
    assert len(run["losses"]["losses/value_loss"]) == 3 and all(map(math.isfinite, run["losses"]["losses/value_loss"]))
    assert set(run["train_return_last_quarter"]) == {"mean", "games"}


def test_the_archive_holds_both_runs_without_checkpoints(rehearsal, tmp_path):
    out, _ = rehearsal
    with tarfile.open(out / "runs.tgz") as archive:
        archive.extractall(tmp_path, filter="data")
    for algo in ("ppo", "p3o"):
        run = tmp_path / f"Breakout-v5__{algo}_atari_envpool__1"
        names = os.listdir(run)
        assert {"eval.json", "train.log"} <= set(names) and ".lock" not in names
        assert not any(n.endswith((".pt", ".cleanrl_model")) for n in names)
        assert [step for step, _ in scalars(str(run))["charts/SPS"]] == [128, 256, 384]
        assert "iteration 3/3" in (run / "train.log").read_text()


def test_sps_and_the_comparison(rehearsal):
    out, _ = rehearsal
    report = json.loads((out / "sps_thesis.json").read_text())
    assert report["settings"]["rounds"] == 1 and report["results"]["raw_env"]["rollout_sps"] > 0
    assert report["settings"]["num_envs"] == 4 and report["settings"]["num_steps"] == 32  # the runs' sizes
    for algo in ("ppo", "p3o"):
        assert report["results"][algo]["iteration_sps"] > 0
    compared = [line.strip() for line in (out / "summary.txt").read_text().splitlines() if line.startswith(" ")]
    assert [line.split(":")[0] for line in compared] == ["ppo", "p3o", "p3o/ppo"]
    for algo, line in zip(("ppo", "p3o"), compared, strict=False):
        run = json.loads((out / f"run_{algo}.json").read_text())["steady_sps"]
        assert f"run {run:,.0f} steps/s" in line and "x raw envpool" in line and "x the run" in line


def test_a_failing_step_is_named_with_its_reason_in_one_line(tmp_path):
    proc = gpu_check(tmp_path / "out", ENV_ID="Qbertt-v5")
    assert proc.returncode == 1
    steps = summary_steps(tmp_path / "out")
    assert [line.split()[1] for line in steps] == STEPS and steps[0].startswith("ok      environment")
    failed = {line.split()[1]: line for line in steps[1:]}
    assert all(line.startswith("FAILED  ") for line in failed.values()), steps
    for step in ("run_ppo", "run_p3o", "sps_thesis"):
        assert "exit 1: error: --env-id Qbertt-v5 is not an envpool Atari game; did you mean Qbert-v5" in failed[step]
    for step in ("read_back_ppo", "read_back_p3o"):
        assert failed[step].endswith("exit 1: nothing to read back: the run wrote no eval.json")
    assert "run_ppo.json, run_p3o.json missing" in failed["compare"]


def test_the_scripts_train_without_imageio_ffmpeg(tmp_path):
    code = (
        "import sys; sys.modules['imageio_ffmpeg'] = None\n"  # any import of it now fails
        "import ppo_atari_envpool as ppo, p3o_atari_envpool as p3o\n"
        "for m in (ppo, p3o):\n"
        "    m.main(m.Args(num_envs=2, num_steps=16, num_minibatches=2, update_epochs=1, total_timesteps=32,"
        " run_name=m.ALGORITHM, cuda=False))\n"
        "from benchmark import evaluate\n"
        "for m in (ppo, p3o):\n"
        "    evaluate.main(evaluate.Args(run=f'runs/{m.ALGORITHM}', episodes=1, cuda=False))\n"
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


def test_no_step_runs_past_the_checks_budget(tmp_path):
    """Every step's limit is cut to what is left of the whole check's budget (540 s on the GPU machine, which must
    bring back a result within its 10-minute call): with none left, the first step fails saying so."""
    proc = gpu_check(tmp_path / "out", BUDGET="0")
    assert proc.returncode == 1
    (line,) = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    assert line.startswith("FAILED  environment (") and line.endswith("exit 1: no time left of the check's 0 s")

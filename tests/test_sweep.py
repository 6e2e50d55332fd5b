"""benchmark/p3o_vs_ppo.sh: the thesis grid as a dry run, and a tiny grid run locally end to end."""

import os
import re
import shlex
import signal
import subprocess
import sys

import pytest
import torch

from helpers import ROOT, python_printing_threads

SWEEP = os.path.join(ROOT, "benchmark", "p3o_vs_ppo.sh")
THESIS_GAMES = ["Breakout-v5", "Freeway-v5", "Seaquest-v5", "Riverraid-v5", "Qbert-v5", "MsPacman-v5"]


def sweep(env, cwd):
    knobs = ("GAMES", "SEEDS", "EXTRA_ARGS", "SLURM", "DRY_RUN", "ALGOS", "WORKERS", "GROUP", "TOTAL_TIMESTEPS")
    knobs += ("OMP_NUM_THREADS",)
    keep = {k: v for k, v in os.environ.items() if k not in knobs}
    # the sweep checks every command with the training scripts' own parser, in this python
    keep["PYTHON"] = sys.executable
    return subprocess.run(["bash", SWEEP], env=keep | env, cwd=cwd, capture_output=True, text=True, timeout=900)


def test_dry_run_lists_the_thesis_grid_with_the_thesis_alphas(tmp_path):
    proc = sweep({"DRY_RUN": "1"}, tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 6 * 10 * 2
    seen = set()
    for line in lines:
        game = re.search(r"--env-id (\S+)", line).group(1)
        seed = int(re.search(r"--seed (\d+)", line).group(1))
        algo = re.search(r"(ppo|p3o)_atari_envpool\.py", line).group(1)
        assert "--total-timesteps 20000000" in line and "--auto-resume" in line
        assert f"--run-name p3o_vs_ppo/{game}__{algo}_atari_envpool__{seed} " in line + " "
        alpha = re.search(r"--ewma-alpha (\S+)", line)
        if algo == "ppo":
            assert alpha is None
        else:
            assert alpha.group(1) == {"MsPacman-v5": "0.75", "Riverraid-v5": "0.6"}.get(game, "0.9")
        seen.add((game, seed, algo))
    assert seen == {(g, s, a) for g in THESIS_GAMES for s in range(1, 11) for a in ("ppo", "p3o")}
    assert not (tmp_path / "runs").exists()


def test_dry_run_slurm_prints_one_requeueing_job_array(tmp_path):
    proc = sweep({"DRY_RUN": "1", "SLURM": "1", "WORKERS": "4"}, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "#SBATCH --array=0-119%4" in proc.stdout
    assert "#SBATCH --requeue" in proc.stdout
    assert "#SBATCH --signal=B:TERM@" in proc.stdout
    assert "scontrol requeue" in proc.stdout


def test_knobs_override_the_grid(tmp_path):
    env = {"DRY_RUN": "1", "GAMES": "Pong-v5", "SEEDS": "7 8", "TOTAL_TIMESTEPS": "4096", "EXTRA_ARGS": "--num-envs 8"}
    lines = sweep(env, tmp_path).stdout.strip().splitlines()
    assert len(lines) == 4
    assert all("--env-id Pong-v5" in x and "--total-timesteps 4096" in x and x.endswith("--num-envs 8") for x in lines)


def test_local_mode_resumes_unfinished_runs_runs_workers_at_a_time_and_skips_finished_ones(tmp_path):
    tiny = "--num-envs 4 --num-steps 32 --num-minibatches 2 --update-epochs 1 --eval-episodes 1"
    env = {
        "GAMES": "Breakout-v5 Qbert-v5",
        "SEEDS": "1",
        "TOTAL_TIMESTEPS": "512",
        "EXTRA_ARGS": tiny,
        "WORKERS": "2",
        "GROUP": "tiny",
        "PYTHON": python_printing_threads(tmp_path),
    }
    # an unfinished run: one of the grid's own commands, stopped by SIGTERM after its first iteration
    commands = sweep(env | {"DRY_RUN": "1"}, tmp_path).stdout.splitlines()
    (command,) = [c for c in commands if "--env-id Qbert-v5" in c and "p3o_atari_envpool.py" in c]
    proc = subprocess.Popen(shlex.split(command), cwd=tmp_path, stdout=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("iteration 1/"):
            proc.send_signal(signal.SIGTERM)
            break
    proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM
    stopped_at = torch.load(tmp_path / "runs/tiny/Qbert-v5__p3o_atari_envpool__1/checkpoint.pt")["iteration"]

    result = sweep(env, tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    for game in ("Breakout-v5", "Qbert-v5"):
        for algo in ("ppo", "p3o"):
            name = f"{game}__{algo}_atari_envpool__1"
            run_dir = tmp_path / "runs" / "tiny" / name
            assert torch.load(run_dir / "checkpoint.pt")["finished"]
            assert (run_dir / "eval.json").is_file()
            log = (tmp_path / "runs" / "tiny" / "logs" / f"{name}.log").read_text()
            assert "iteration 4/4 global_step=512" in log
            # two runs at a time: each with half the cores' threads, not torch's default of all of them
            assert f"OMP_NUM_THREADS={max(1, len(os.sched_getaffinity(0)) // 2)}\n" in log, log
            resumed = f"resuming runs/tiny/{name} after iteration {stopped_at} " in log
            assert resumed == (name == "Qbert-v5__p3o_atari_envpool__1"), log
    # WORKERS=2: never more than two runs at once, and two at once at some point
    running, most = 0, 0
    for line in result.stdout.splitlines():
        running += line.startswith("start: ") - line.startswith("done:  ")
        most = max(most, running)
    assert most == 2 and running == 0

    # again: every run has finished, so nothing is started
    again = sweep(env, tmp_path)
    assert again.returncode == 0
    assert (
        again.stdout == "4 of 4 runs already finished; left out\nnothing to run: every run in runs/tiny has finished\n"
    )
    log = (tmp_path / "runs" / "tiny" / "logs" / "Qbert-v5__p3o_atari_envpool__1.log").read_text()
    assert log.count("iteration 4/4") == 1


def test_local_mode_fails_with_status_1_when_a_run_fails(tmp_path):
    # a run that fails after the knobs were checked: a file where its run folder would go
    env = {"GAMES": "Breakout-v5", "SEEDS": "1", "GROUP": "bad", "PYTHON": sys.executable, "WORKERS": "2"}
    (tmp_path / "runs" / "bad").mkdir(parents=True)
    (tmp_path / "runs" / "bad" / "Breakout-v5__p3o_atari_envpool__1").write_text("in the way")
    proc = sweep(env | {"EXTRA_ARGS": "--num-envs 4 --num-steps 32 --total-timesteps 128 --eval-episodes 0"}, tmp_path)
    assert proc.returncode == 1
    log = "runs/bad/logs/Breakout-v5__p3o_atari_envpool__1.log"
    assert f"FAILED (see {log}): " in proc.stdout
    assert (
        "error: cannot create the run folder runs/bad/Breakout-v5__p3o_atari_envpool__1" in (tmp_path / log).read_text()
    )
    assert "done:  " in proc.stdout  # the other run of the grid went on


@pytest.mark.parametrize(
    "knobs,sentence",
    [
        ({"GAMES": "Breakout-v5 Qbertt-v5"}, "error: --env-id Qbertt-v5 is not an envpool environment. Did you mean "),
        ({"GAMES": "CartPole-v1"}, "error: --env-id CartPole-v1 is an envpool environment but not an Atari game."),
        ({"GAMES": " "}, "error: GAMES is empty."),
        ({"SEEDS": "1 2x"}, "error: SEEDS must be whole numbers, got '2x'."),
        ({"SEEDS": "4294967296"}, "error: --seed must lie in [0, "),
        ({"TOTAL_TIMESTEPS": "1e6"}, "error: TOTAL_TIMESTEPS must be a positive whole number, got '1e6'."),
        ({"TOTAL_TIMESTEPS": "0"}, "error: TOTAL_TIMESTEPS must be a positive whole number, got '0'."),
        ({"WORKERS": "0"}, "error: WORKERS must be a whole number of at least 1, got '0'."),
        ({"WORKERS": "two"}, "error: WORKERS must be a whole number of at least 1, got 'two'."),
        ({"ALGOS": "ppo a2c"}, "error: ALGOS must be ppo, p3o or both, got 'a2c'."),
        ({"SIGNAL_SECONDS": "-5"}, "error: SIGNAL_SECONDS must be a whole number, got '-5'."),
        ({"EXTRA_ARGS": "--learning-rate nan"}, "error: --learning-rate must be a finite number, got nan."),
        ({"GROUP": "../elsewhere"}, "error: --run-name '../elsewhere/Breakout-v5__ppo_atari_envpool__1' must be a"),
    ],
)
@pytest.mark.parametrize("mode", [{}, {"SLURM": "1"}, {"DRY_RUN": "1"}], ids=["local", "slurm", "dry-run"])
def test_bad_knobs_are_refused_before_anything_starts_or_is_submitted(knobs, sentence, mode, tmp_path):
    env = {"GAMES": "Breakout-v5", "SEEDS": "1", "PYTHON": sys.executable, "SBATCH_ARGS": "--no-such-sbatch"}
    # tiny runs, should a refusal ever fail to come
    env |= {"TOTAL_TIMESTEPS": "128", "EXTRA_ARGS": "--num-envs 4 --num-steps 32 --num-minibatches 2 --eval-episodes 0"}
    proc = sweep(env | mode | knobs, tmp_path)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith(sentence) and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert os.listdir(tmp_path) == []


def test_algos_runs_one_script_of_the_grid(tmp_path):
    lines = sweep({"DRY_RUN": "1", "GAMES": "Qbert-v5", "SEEDS": "1 2", "ALGOS": "p3o"}, tmp_path).stdout.splitlines()
    assert len(lines) == 2 and all("p3o_atari_envpool.py" in line for line in lines)

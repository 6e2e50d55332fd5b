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
    knobs += ("OMP_NUM_THREADS", "EVAL_EPISODES")
    keep = {k: v for k, v in os.environ.items() if k not in knobs}
    # the sweep checks every command with the training scripts' own parser, in this python
    keep["PYTHON"] = sys.executable
    return subprocess.run(["bash", SWEEP], env=keep | env, cwd=cwd, capture_output=True, text=True, timeout=900)


def test_dry_run_lists_the_thesis_grid_with_the_thesis_alphas(tmp_path):
    proc = sweep({"DRY_RUN": "1"}, tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stdout.strip().splitlines() if not line.startswith("#")]
    assert len(lines) == 6 * 10 * 2
    # each run is then evaluated on 10 games by evaluate.py --run
    assert (
        "# then, for each run: " in proc.stdout and "benchmark/evaluate.py --run runs/RUN --episodes 10" in proc.stdout
    )
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
    lines = sweep(env | {"EVAL_EPISODES": "0"}, tmp_path).stdout.strip().splitlines()
    assert len(lines) == 4
    assert all("--env-id Pong-v5" in x and "--total-timesteps 4096" in x and x.endswith("--num-envs 8") for x in lines)


def test_local_mode_resumes_unfinished_runs_runs_workers_at_a_time_and_skips_finished_ones(tmp_path):
    tiny = "--num-envs 4 --num-steps 32 --num-minibatches 2 --update-epochs 1"
    env = {
        "EVAL_EPISODES": "1",
        "GAMES": "Breakout-v5 Qbert-v5",
        "SEEDS": "1",
        "TOTAL_TIMESTEPS": "512",
        "EXTRA_ARGS": tiny,
        "WORKERS": "2",
        "GROUP": "tiny",
        "PYTHON": python_printing_threads(tmp_path),
    }
    # an unfinished run: one of the grid's own commands, stopped by SIGTERM after its first iteration
    commands = [c for c in sweep(env | {"DRY_RUN": "1"}, tmp_path).stdout.splitlines() if not c.startswith("#")]
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
    proc = sweep(env | {"EXTRA_ARGS": "--num-envs 4 --num-steps 32", "TOTAL_TIMESTEPS": "128"}, tmp_path)
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
        ({"GAMES": "Breakout-v5 Qbertt-v5"}, "error: --env-id Qbertt-v5 is not an envpool Atari game; did you mean "),
        ({"GAMES": "CartPole-v1"}, "error: --env-id CartPole-v1 is not an envpool Atari game; did you mean an id"),
        ({"GAMES": " "}, "error: GAMES is empty."),
        ({"SEEDS": "1 2x"}, "error: SEEDS must be whole numbers without leading zeros, got '2x'."),
        ({"SEEDS": "1 01"}, "error: SEEDS must be whole numbers without leading zeros, got '01'."),
        ({"SEEDS": "4294967296"}, "error: --seed must lie in [0, "),
        ({"TOTAL_TIMESTEPS": "1e6"}, "error: TOTAL_TIMESTEPS must be a positive whole number, got '1e6'."),
        ({"TOTAL_TIMESTEPS": "0"}, "error: TOTAL_TIMESTEPS must be a positive whole number, got '0'."),
        ({"WORKERS": "0"}, "error: WORKERS must be a whole number of at least 1, got '0'."),
        ({"WORKERS": "two"}, "error: WORKERS must be a whole number of at least 1, got 'two'."),
        (
            {"ALGOS": "ppo a2c"},
            "error: ALGOS must be ppo, p3o or P3O ablations (p3o-gae, p3o-value-beta-one, p3o-batch-minmax), got"
            " 'a2c'.",
        ),
        ({"SIGNAL_SECONDS": "-5"}, "error: SIGNAL_SECONDS must be a whole number, got '-5'."),
        ({"EXTRA_ARGS": "--learning-rate nan"}, "error: --learning-rate must be a finite number, got nan."),
        ({"GROUP": "../elsewhere"}, "error: --run-name '../elsewhere/Breakout-v5__ppo_atari_envpool__1' must be a"),
        # set but empty is a mistake, not the default grid
        ({"SEEDS": ""}, "error: SEEDS is empty."),
        ({"GAMES": ""}, "error: GAMES is empty."),
        ({"ALGOS": ""}, "error: ALGOS is empty."),
        # the same run twice would end in one of them refused by the other's lock
        ({"ALGOS": "ppo ppo"}, "error: ALGOS names 'ppo' twice."),
        ({"SEEDS": "1 2 1"}, "error: SEEDS names '1' twice."),
        ({"GAMES": "Breakout-v5 Breakout-v5"}, "error: GAMES names 'Breakout-v5' twice."),
        ({"DRY_RUN": "maybe"}, "error: DRY_RUN must be 1 (or true) or 0 (or false), got 'maybe'."),
        ({"SLURM": "2"}, "error: SLURM must be 1 (or true) or 0 (or false), got '2'."),
        # EXTRA_ARGS may not change what names a run: two folders named for seeds 1 and 2 would hold seed 7
        ({"EXTRA_ARGS": "--seed 7"}, "error: EXTRA_ARGS sets --seed (7), which the sweep sets for SEEDS."),
        (
            {"EXTRA_ARGS": "--env_id Pong-v5"},
            "error: EXTRA_ARGS sets --env-id (Pong-v5), which the sweep sets for GAMES.",
        ),
        ({"EXTRA_ARGS": "--total-timesteps=256"}, "error: EXTRA_ARGS sets --total-timesteps (256), which the sweep"),
        ({"EXTRA_ARGS": "--exp-name x"}, "error: EXTRA_ARGS sets --exp-name (x), which the sweep sets for the run"),
        ({"EXTRA_ARGS": "--run-name a/b"}, "error: EXTRA_ARGS sets --run-name (a/b), which the sweep sets for GROUP."),
        ({"EXTRA_ARGS": "--no-auto-resume"}, "error: EXTRA_ARGS sets --auto-resume (False), which the sweep sets"),
        ({"EXTRA_ARGS": "--resume runs/x"}, "error: EXTRA_ARGS sets --resume (runs/x), which the sweep sets"),
        ({"ALGOS": "p3o", "EXTRA_ARGS": "--ewma-alpha 0.5"}, "error: EXTRA_ARGS sets --ewma-alpha (0.5), which the"),
        # one sentence where the parser would print a box, and quotes that the runs would not see as the check did
        ({"EXTRA_ARGS": "--num-envs x"}, "error: EXTRA_ARGS '--num-envs x' holds a flag or value that ppo_atari_en"),
        ({"EXTRA_ARGS": "--ewma-alpha 0.5"}, "error: EXTRA_ARGS '--ewma-alpha 0.5' holds a flag or value that ppo_"),
        ({"EXTRA_ARGS": "--exp-name 'a b'"}, "error: EXTRA_ARGS and GROUP are split at spaces and cannot hold quotes"),
        ({"GROUP": "my group"}, "error: GROUP must be one folder name without spaces, got 'my group'."),
    ],
)
@pytest.mark.parametrize("mode", [{}, {"SLURM": "1"}, {"DRY_RUN": "1"}], ids=["local", "slurm", "dry-run"])
def test_bad_knobs_are_refused_before_anything_starts_or_is_submitted(knobs, sentence, mode, tmp_path):
    env = {"GAMES": "Breakout-v5", "SEEDS": "1", "PYTHON": sys.executable, "SBATCH_ARGS": "--no-such-sbatch"}
    # tiny runs, should a refusal ever fail to come
    env |= {"TOTAL_TIMESTEPS": "128", "EXTRA_ARGS": "--num-envs 4 --num-steps 32 --num-minibatches 2"}
    proc = sweep(env | mode | knobs, tmp_path)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith(sentence) and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert os.listdir(tmp_path) == []


def test_algos_runs_one_script_of_the_grid(tmp_path):
    knobs = {"DRY_RUN": "1", "GAMES": "Qbert-v5", "SEEDS": "1 2", "ALGOS": "p3o", "EVAL_EPISODES": "0"}
    lines = sweep(knobs, tmp_path).stdout.splitlines()
    assert len(lines) == 2 and all("p3o_atari_envpool.py" in line for line in lines)


def test_dry_run_true_is_a_dry_run(tmp_path):
    proc = sweep({"DRY_RUN": "true", "GAMES": "Breakout-v5", "SEEDS": "1", "EVAL_EPISODES": "0"}, tmp_path)
    assert proc.returncode == 0 and len(proc.stdout.splitlines()) == 2 and not (tmp_path / "runs").exists()


def test_runs_made_with_other_settings_are_named_not_skipped_or_resumed(tmp_path):
    """A sweep run again with a changed knob over runs of its GROUP says which run differs, and how, before
    anything starts: a finished run would otherwise be skipped as done ("nothing to run") for the new settings."""
    import ppo_atari_envpool as ppo

    env = {"GAMES": "Breakout-v5", "SEEDS": "1", "ALGOS": "ppo", "GROUP": "g", "TOTAL_TIMESTEPS": "128"}
    env |= {"EXTRA_ARGS": "--num-envs 4 --num-steps 32 --num-minibatches 2", "EVAL_EPISODES": "0"}
    run = tmp_path / "runs" / "g" / "Breakout-v5__ppo_atari_envpool__1"
    run.mkdir(parents=True)
    made = ppo.Args(env_id="Breakout-v5", seed=1, total_timesteps=128, num_envs=4, num_steps=32, num_minibatches=2)
    made.run_name, made.auto_resume = "g/Breakout-v5__ppo_atari_envpool__1", True
    torch.save({"args": vars(made), "finished": True, "iteration": 1}, run / "checkpoint.pt")
    same = sweep(env | {"DRY_RUN": "1"}, tmp_path)
    assert same.returncode == 0 and "nothing to run: every run in runs/g has finished" in same.stdout
    for knobs, was in [
        ({"TOTAL_TIMESTEPS": "256"}, "--total-timesteps 128 (now 256)"),
        ({"EXTRA_ARGS": env["EXTRA_ARGS"] + " --learning-rate 2.5e-4"}, "--learning-rate 0.001 (now 0.00025)"),
    ]:
        proc = sweep(env | knobs, tmp_path)
        assert proc.returncode == 1 and proc.stdout == ""
        assert proc.stderr == (
            f"error: runs/g/Breakout-v5__ppo_atari_envpool__1 was made with {was}; give this sweep another GROUP,"
            " or remove that run.\n"
        )
    assert sorted(os.listdir(run)) == ["checkpoint.pt"]

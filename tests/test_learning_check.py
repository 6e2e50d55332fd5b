"""benchmark/learning_check.sh end to end on the CPU: two games of one iteration each at the thesis regime's
sizes, its outputs read back (eval.json, event files, each game's alpha, tables), a second call over two seeds
that skips every pair in the driver's order, and its refusals."""

import csv
import json
import os
import shutil

import numpy as np
import pytest

from helpers import ROOT, assert_logged, run_driver

CHECK = os.path.join(ROOT, "benchmark", "learning_check.sh")
STEPS = 4096  # one iteration of 16 envs x 256 steps
GAMES = ("MsPacman-v5", "Breakout-v5")  # MsPacman has its own alpha (0.75), Breakout the default 0.9
SEED = 2  # the seed the first call trains (not 1: the evaluation games' seeds must follow the run's seed)
LIMIT = 2400  # seconds one call of the driver may take (about 3 minutes on two free cores)
# the fixture makes two calls: pyproject's 900 s per test would cut them first on a loaded machine
pytestmark = pytest.mark.timeout(2 * LIMIT + 60)


def learning_check(cwd, out, **knobs):
    knobs = {"TOTAL_TIMESTEPS": str(STEPS), "SEEDS": "1 2", "GAMES": " ".join(GAMES), "OUT": str(out)} | knobs
    return run_driver(CHECK, cwd, knobs, LIMIT)


@pytest.fixture(scope="module")
def checked(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("check")
    out = cwd / "out"
    first = learning_check(cwd, out, SEEDS=str(SEED))
    # seed 1's pairs stand in as finished (seed 2's outputs under seed 1's names): the second call, over both
    # seeds, then shows the order the driver walks the grid in, without training two more pairs (each pair is
    # two training processes and three 10-game evaluations, about 4 CPU minutes)
    for run in list((out / "runs").iterdir()):
        shutil.copytree(run, run.with_name(run.name.removesuffix(f"__{SEED}") + "__1"))
    second = learning_check(cwd, out)
    return cwd, out, first, second


def test_each_pair_trains_both_scripts_in_the_thesis_regime_with_its_alpha_and_is_evaluated(checked):
    cwd, out, first, _ = checked
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    seed = SEED
    for game in GAMES:
        games = [seed + 1_000_000 + i for i in range(10)]
        for algo in ("ppo", "p3o"):
            run = out / "runs" / f"{game}__{algo}_atari_envpool__{seed}"
            report = json.loads((run / "eval.json").read_text())
            assert report["algorithm"] == algo and report["seeds"] == games and len(report["returns"]) == 10
            assert report["env_id"] == game
            assert f"iteration 1/1 global_step={STEPS} " in (run / "train.log").read_text()
            assert_logged(
                run,
                "num_envs|16",
                "num_steps|256",
                "num_minibatches|4",
                "update_epochs|8",
                "learning_rate|0.001",
                "anneal_lr|False",
                f"seed|{seed}",
                f"total_timesteps|{STEPS}",
                f"env_id|{game}",
            )
            if algo == "p3o":  # the thesis's alpha of the game (section 5.1.2)
                assert_logged(run, f"ewma_alpha|{0.75 if game == 'MsPacman-v5' else 0.9}")
            # the checkpoint stays in runs/ of the current folder, not among the committed outputs
            assert (cwd / "runs" / "learning_check" / run.name / "checkpoint.pt").is_file()
            assert not (run / "checkpoint.pt").exists()
        random = json.loads((out / "runs" / f"{game}__random__{seed}" / "eval.json").read_text())
        assert random["seeds"] == games and len(random["returns"]) == 10 and random["env_id"] == game


def test_seed_1_of_every_game_comes_first_and_the_tables_after_each_pair(checked):
    _, out, first, second = checked
    lines = first.stdout.splitlines()
    order = [line.split(":")[0] for line in lines if line.endswith(f"done; commit {out}/ now")]
    assert order == [f"{game} seed {SEED}" for game in GAMES]
    # the grid is walked seed by seed, every game's seed 1 first (the second call, which finds every pair done)
    order = [
        line.split(":")[0]
        for line in second.stdout.splitlines()
        if line.endswith(f"done (its outputs are in {out}/runs/)")
    ]
    assert order == [f"{game} seed {seed}" for seed in (1, 2) for game in GAMES]
    first_done = lines.index(f"{GAMES[0]} seed {SEED}: done; commit {out}/ now")
    second_start = next(
        i for i, line in enumerate(lines) if line.startswith(f"{GAMES[1]} seed {SEED}: ppo and p3o -> ")
    )
    assert first_done < next(i for i, line in enumerate(lines) if line.startswith("tables: ")) < second_start
    with open(out / "table.csv") as f:
        rows = {(r["game"], r["algorithm"]): r for r in csv.DictReader(f)}
    for game in GAMES:
        for algo, folder in [("ppo_atari_envpool", "ppo_atari_envpool"), ("random", "random")]:
            means = [
                json.loads((out / "runs" / f"{game}__{folder}__{s}" / "eval.json").read_text())["mean"] for s in (1, 2)
            ]
            row = rows[game, algo]
            assert int(row["n"]) == 2 and float(row["mean"]) == pytest.approx(np.mean(means))
        assert int(rows[game, "p3o_atari_envpool"]["n"]) == 2
    with open(out / "beta_windows.csv") as f:
        beta = list(csv.DictReader(f))
    assert {r["game"] for r in beta} == set(GAMES)
    assert all(r["algorithm"] == "p3o_atari_envpool" and int(r["n"]) == 2 for r in beta)
    assert {int(r["window_end"]) - int(r["window_start"]) for r in beta} == {STEPS // 5}
    with open(out / "train_last100_windows.csv") as f:
        assert {r["algorithm"] for r in csv.DictReader(f)} == {"ppo_atari_envpool", "p3o_atari_envpool"}
    for game in GAMES:
        assert (out / f"{game}__beta_mean.png").is_file()
    assert (out / "train_last100.md").is_file()
    with open(out / "hours.csv") as f:  # one iteration per run: its elapsed time, no pace, no resume
        hours = {r["run"]: r for r in csv.DictReader(f)}
    assert set(hours) == {f"{g}__{a}_atari_envpool__{s}" for g in GAMES for a in ("ppo", "p3o") for s in (1, 2)}
    assert all((r["iterations"], r["resumes"]) == ("1", "0") and float(r["hours_elapsed"]) > 0 for r in hours.values())


def test_a_second_call_skips_finished_pairs_and_remakes_the_tables(checked):
    cwd, out, _, second = checked
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    for game in GAMES:
        for seed in (1, 2):
            assert f"{game} seed {seed}: done (its outputs are in {out}/runs/)" in second.stdout
    assert " -> " not in second.stdout and "tables: " in second.stdout
    # nothing was started: each training log holds one run
    logs = list((cwd / "runs" / "learning_check" / "logs").iterdir())
    assert len(logs) == 2 * len(GAMES)
    for log in logs:
        assert log.read_text().count(f"iteration 1/1 global_step={STEPS} ") == 1, log


@pytest.mark.parametrize(
    "knobs,sentence",
    [
        ({"MODE": "atari"}, "error: MODE must be thesis, cleanrl or ablation, got 'atari'."),
        ({"TOTAL_TIMESTEPS": "1e6"}, "error: TOTAL_TIMESTEPS must be a positive whole number, got '1e6'."),
        ({"SEEDS": "1 two"}, "error: SEEDS must be whole numbers without leading zeros, got 'two'."),
        ({"SEEDS": "1 01"}, "error: SEEDS must be whole numbers without leading zeros, got '01'."),
        ({"GAMES": "Breakout-v5 Qbertt-v5"}, "error: --env-id Qbertt-v5 is not an envpool Atari game; did you mean"),
        ({"SEEDS": "1 4294967296"}, "error: --seed must lie in"),
        ({"SEEDS": ""}, "error: SEEDS is empty."),  # set but empty: not the default seeds
        ({"GAMES": ""}, "error: GAMES is empty."),
    ],
)
def test_bad_knobs_are_refused_before_anything_runs(knobs, sentence, tmp_path):
    proc = learning_check(tmp_path, tmp_path / "out", **knobs)
    assert proc.returncode == 1 and proc.stderr.startswith(sentence) and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1
    assert os.listdir(tmp_path) == []


def test_committed_runs_of_another_length_are_named_not_skipped(tmp_path):
    """Called again with another TOTAL_TIMESTEPS over committed pairs, the check says so before anything runs,
    instead of skipping them as done and rewriting the tables with the new windows."""
    out = tmp_path / "out"
    for algo in ("ppo", "p3o"):
        run = out / "runs" / f"Breakout-v5__{algo}_atari_envpool__1"
        run.mkdir(parents=True)
        (run / "eval.json").write_text(json.dumps({"global_step": STEPS, "returns": [1.0], "mean": 1.0}))
    proc = learning_check(tmp_path, out, GAMES="Breakout-v5", SEEDS="1", TOTAL_TIMESTEPS=str(2 * STEPS))
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr == (
        f"error: {out}/runs/Breakout-v5__ppo_atari_envpool__1 was trained for 4,096 steps, not the 8,192 that"
        " TOTAL_TIMESTEPS=8192 gives; use another OUT.\n"
    )
    assert sorted(os.listdir(out)) == ["runs"] and sorted(os.listdir(tmp_path)) == ["out"]


def test_the_ablation_mode_trains_p3o_with_each_piece_off_evaluated_beside_no_random_policy(tmp_path):
    """MODE=ablation: benchmark/p3o_ablation.py's gae and value-beta-one changes in the thesis regime, with the game's
    alpha, each evaluated on the seeds the committed P3O and PPO runs of its seed played; no random policy."""
    out = tmp_path / "out"
    proc = learning_check(tmp_path, out, MODE="ablation", GAMES="MsPacman-v5", SEEDS="3")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert sorted(p.name for p in (out / "runs").iterdir()) == [
        "MsPacman-v5__p3o_gae__3",
        "MsPacman-v5__p3o_value_beta_one__3",
    ]
    for change in ("gae", "value-beta-one"):
        run = out / "runs" / f"MsPacman-v5__p3o_{change.replace('-', '_')}__3"
        report = json.loads((run / "eval.json").read_text())
        assert report["algorithm"] == f"p3o-{change}" and report["seeds"] == [1_000_003 + i for i in range(10)]
        assert f"iteration 1/1 global_step={STEPS} " in (run / "train.log").read_text()
        assert_logged(run, f"exp_name|p3o_{change.replace('-', '_')}", "ewma_alpha|0.75", "num_envs|16", "seed|3")
        assert not (run / "checkpoint.pt").exists()
    # the four arms' table, and the ablation tests' table, which says one run a side is nothing to test yet
    assert "| game | p3o_gae | p3o_value_beta_one |\n|---|---|---|\n| MsPacman-v5 | " in (out / "table.md").read_text()
    assert (out / "table_ablations.md").read_text().startswith("`eval/episodic_return`: no game has two runs or more")
    again = learning_check(tmp_path, out, MODE="ablation", GAMES="MsPacman-v5", SEEDS="3")
    assert again.returncode == 0 and "MsPacman-v5 seed 3: done" in again.stdout


def test_a_hand_edited_eval_json_is_named_in_one_sentence(tmp_path):
    out = tmp_path / "out"
    run = out / "runs" / "Breakout-v5__ppo_atari_envpool__1"
    run.mkdir(parents=True)
    (run / "eval.json").write_text('{"global_step": 4096, "returns": [1.0,')  # cut short by an editor
    proc = learning_check(tmp_path, out, GAMES="Breakout-v5", SEEDS="1")
    assert proc.returncode == 1 and proc.stdout == "" and "Traceback" not in proc.stderr
    assert proc.stderr == (
        f"error: {run}/eval.json is not an eval.json these tools wrote; mend it or remove that run's folder.\n"
    )

"""benchmark/regime.sh end to end on the CPU: one configuration of the update-regime study with both scripts,
one iteration each, its copied outputs and tables read back, a second call that starts nothing, and an unknown
configuration refused."""

import csv
import os

import pytest

from helpers import ROOT, assert_logged, run_driver, scalars

REGIME = os.path.join(ROOT, "benchmark", "regime.sh")
STEPS = 1024  # one iteration of CleanRL's 8 envs x 128 steps
CONFIG = "cleanrl_lr"  # CleanRL's sizes with the thesis's learning rate; both scripts run in it
LIMIT = 1200  # seconds one call of the driver may take
# the fixture makes two calls: pyproject's 900 s per test would cut them first on a loaded machine
pytestmark = pytest.mark.timeout(2 * LIMIT + 60)


def regime(cwd, out, **knobs):
    return run_driver(REGIME, cwd, {"TOTAL_TIMESTEPS": str(STEPS), "SEEDS": "1", "OUT": str(out)} | knobs, LIMIT)


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("regime")
    out = cwd / "out"
    return cwd, out, regime(cwd, out, CONFIGS=CONFIG), regime(cwd, out, CONFIGS=CONFIG)


def test_a_configuration_trains_both_scripts_with_its_flags_and_copies_their_outputs(ran):
    cwd, out, first, _ = ran
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    for algo in ("ppo", "p3o"):
        copy = out / "runs" / f"Breakout-v5__{algo}-{CONFIG}__1"
        assert f"iteration 1/1 global_step={STEPS} " in (copy / "train.log").read_text()
        assert_logged(
            copy,
            "num_envs|8",
            "num_steps|128",
            "update_epochs|4",
            "num_minibatches|4",
            "learning_rate|0.001",
            "anneal_lr|True",
            "seed|1",
            "env_id|Breakout-v5",
        )
        # the checkpoint stays in runs/regime/ of the current folder, not among the outputs to commit
        assert not (copy / "checkpoint.pt").exists()
        assert (cwd / "runs" / "regime" / CONFIG / f"Breakout-v5__{algo}_atari_envpool__1" / "checkpoint.pt").is_file()


def test_the_tables_have_a_row_per_algorithm_and_configuration_read_from_the_copies(ran):
    _, out, first, _ = ran
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    with open(out / "return_windows.csv") as f:
        assert {r["algorithm"] for r in csv.DictReader(f)} == {f"ppo-{CONFIG}", f"p3o-{CONFIG}"}
    logged = scalars(out / "runs" / f"Breakout-v5__p3o-{CONFIG}__1")
    with open(out / "beta_mean_windows.csv") as f:
        (row,) = list(csv.DictReader(f))  # P3O only: PPO logs no beta
    assert row["algorithm"] == f"p3o-{CONFIG}" and (row["window_start"], row["window_end"]) == ("0", "50000")
    assert float(row["mean"]) == pytest.approx(logged["p3o/beta_mean"][0][1])
    with open(out / "beta_above_half_windows.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["algorithm"] == f"p3o-{CONFIG}" and 0.0 <= float(row["mean"]) <= 1.0


def test_a_second_call_starts_nothing(ran):
    cwd, _, _, second = ran
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    assert "start: " not in second.stdout
    for algo in ("ppo", "p3o"):
        log = cwd / "runs" / "regime" / CONFIG / "logs" / f"Breakout-v5__{algo}_atari_envpool__1.log"
        assert log.read_text().count(f"iteration 1/1 global_step={STEPS} ") == 1


def test_an_unknown_configuration_is_one_sentence_before_anything_runs(tmp_path):
    proc = regime(tmp_path, tmp_path / "out", CONFIGS="cleanrl_lr thesis_lrr")
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith("error: unknown configuration 'thesis_lrr'; known: cleanrl cleanrl_lr ")
    assert len(proc.stderr.strip().splitlines()) == 1
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("knob", ["CONFIGS", "SEEDS"])
def test_an_empty_knob_is_refused_not_taken_as_the_default(knob, tmp_path):
    proc = regime(tmp_path, tmp_path / "out", **{knob: ""})
    assert proc.returncode == 1 and proc.stdout == "" and proc.stderr == f"error: {knob} is empty.\n"
    assert os.listdir(tmp_path) == []

"""benchmark/sps.py runs from the command line at tiny sizes and reports what it promises."""

import json
import os
import subprocess
import sys

from helpers import ROOT

SPS = os.path.join(ROOT, "benchmark", "sps.py")


def test_sps_measures_both_scripts_over_alternating_rounds(tmp_path):
    out = tmp_path / "sps.json"
    cmd = [sys.executable, SPS, "--num-envs", "2", "--num-steps", "16", "--num-minibatches", "2"]
    cmd += ["--update-epochs", "1", "--iterations", "2", "--warmup", "1", "--rounds", "2", "--no-cuda"]
    proc = subprocess.run([*cmd, "--out", str(out)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| ppo_atari_envpool.py |" in proc.stdout and "| p3o_atari_envpool.py |" in proc.stdout
    report = json.loads(out.read_text())
    results = report["results"]
    assert results["raw_env"]["rollout_sps"] > 0 and results["raw_env"]["peak_rss_mb"] > 0
    for name in ("ppo", "p3o"):
        r = results[name]
        assert len(r["rounds"]) == 2
        for key in ("iteration_sps", "rollout_sps", "update_sps", "peak_rss_mb"):
            assert r[key] > 0
            # the reported value is the median over the rounds (of two: their mean)
            assert abs(r[key] - sum(m[key] for m in r["rounds"]) / 2) < 1e-6 * r[key]
    # PPO first in the first round, P3O first in the second: the order alternates
    starts = [[results[name]["rounds"][i]["started"] for name in ("ppo", "p3o")] for i in range(2)]
    assert starts[0][0] < starts[0][1] and starts[1][1] < starts[1][0]
    assert starts[0][1] < starts[1][1]
    ratios = report["ratios"]
    expected = results["p3o"]["iteration_sps"] / results["ppo"]["iteration_sps"]
    assert abs(ratios["p3o/ppo_iteration"] - expected) < 1e-9


def test_sps_refuses_bad_settings(tmp_path):
    (tmp_path / "blocker").write_text("a file where a folder would go")
    for bad, message in [
        (["--warmup", "0"], "error: --iterations, --warmup and --rounds must be at least 1."),
        (["--rounds", "0"], "error: --iterations, --warmup and --rounds must be at least 1."),
        (["--scripts", "a2c"], "error: --scripts must name one or more of ['p3o', 'ppo'], got ['a2c']."),
        (["--scripts"], "error: --scripts must name one or more of ['p3o', 'ppo'], got []."),
        (
            ["--out", "blocker/sps.json"],
            f"error: --out blocker/sps.json cannot be written: {tmp_path}/blocker is a file, not a folder.",
        ),
        (["--out", "."], "error: --out . cannot be written: it is a folder."),
        (
            ["--num-envs", "3", "--num-minibatches", "5"],
            "error: the batch (--num-envs * --num-steps = 384) does not divide into 5 minibatches.",
        ),
    ]:
        proc = subprocess.run([sys.executable, SPS, *bad], cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 1 and proc.stderr == message + "\n", proc.stderr

"""benchmark/p3o_ablation.py: each change replaces exactly the piece it names, and a short run trains."""

import glob
import importlib
import json
import os
import subprocess
import sys

import pytest
import torch

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT, hyperparameters, scalars


@pytest.fixture
def ablation(monkeypatch):
    """The tool, with P3O's module functions restored after each test."""
    for name in ("gbae", "value_loss", "compute_betas", "ALGORITHM"):
        monkeypatch.setattr(p3o, name, getattr(p3o, name))
    from benchmark import p3o_ablation

    return importlib.reload(p3o_ablation)


def rollout(T=16, N=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    rewards = (torch.rand(T, N, generator=g) < 0.2).float()
    values = torch.randn(T, N, generator=g)
    dones = (torch.rand(T, N, generator=g) < 0.1).float()
    return rewards, values, dones, torch.randn(N, generator=g), torch.zeros(N), torch.rand(T + 1, N, generator=g)


def test_gae_change_gives_plain_gae_whatever_beta(ablation):
    r, v, d, nv, nd, b = rollout()
    expected = ppo.gae(r, v, d, nv, nd, 0.99, 0.95)
    assert not torch.allclose(p3o.gbae(r, v, d, nv, nd, b, 0.99, 0.95), expected)  # these betas matter
    ablation.apply("gae")
    torch.testing.assert_close(p3o.gbae(r, v, d, nv, nd, b, 0.99, 0.95), expected, rtol=0, atol=0)


def test_value_beta_one_weights_every_state_fully(ablation):
    newvalue, values, returns = torch.randn(64), torch.randn(64), torch.randn(64)
    betas, valid = torch.rand(64), (torch.rand(64) < 0.9).float()
    full = p3o.value_loss(newvalue, values, returns, torch.ones(64), valid, 0.1, True)
    weighted = p3o.value_loss(newvalue, values, returns, betas, valid, 0.1, True)
    assert weighted < full
    ablation.apply("value-beta-one")
    assert p3o.value_loss(newvalue, values, returns, betas, valid, 0.1, True).item() == full.item()


def test_batch_minmax_normalises_over_the_whole_rollout(ablation):
    g = torch.Generator().manual_seed(1)
    si = torch.rand(9, 4, generator=g) * torch.tensor([1.0, 10.0, 100.0, 1000.0])
    ablation.apply("batch-minmax")
    betas = p3o.compute_betas(si, 0.9)
    x = p3o.ewma(si, 0.9)
    torch.testing.assert_close(betas, (x - x.min()) / (x.max() - x.min()))
    assert betas.min().item() == 0.0 and betas.max().item() == 1.0
    # the small-scale environment keeps small betas, unlike per-environment min-max
    assert betas[:, 0].max() < 0.01
    assert torch.equal(p3o.compute_betas(torch.full((5, 2), 0.3), 0.9), torch.zeros(5, 2))


def test_unknown_change_is_refused(ablation):
    with pytest.raises(SystemExit, match="first argument must be one of gae, value-beta-one, batch-minmax"):
        ablation.main(["beta-zero", "--env-id", "Breakout-v5"])


def test_a_function_main_does_not_call_is_refused_loudly(ablation, monkeypatch):
    monkeypatch.setattr(p3o, "main", lambda args: None)  # as if main had stopped calling gbae by that name
    with pytest.raises(SystemExit) as excinfo:
        ablation.apply("gae")
    assert excinfo.value.code == (
        "error: p3o_atari_envpool.main does not call gbae, so the gae ablation would change nothing."
    )
    monkeypatch.delattr(p3o, "compute_betas")  # or the function was renamed
    with pytest.raises(SystemExit, match="does not call compute_betas"):
        ablation.apply("batch-minmax")


TINY = ["--env-id", "Breakout-v5", "--num-envs", "2", "--num-steps", "32", "--num-minibatches", "2"]
TINY += ["--update-epochs", "1", "--total-timesteps", "128", "--seed", "5"]


def logged(run_dir):
    return {tag: [v for _, v in points] for tag, points in scalars(run_dir).items()}, hyperparameters(run_dir)


def test_ablation_runs_are_named_apart_and_each_change_takes_effect(tmp_path):
    def run(*command):
        proc = subprocess.run([sys.executable, *command, *TINY], cwd=tmp_path, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr[-3000:]

    run(os.path.join(ROOT, "p3o_atari_envpool.py"))
    (plain_dir,) = glob.glob(str(tmp_path / "runs" / "Breakout-v5__p3o_atari_envpool__5__*"))
    plain, _ = logged(plain_dir)
    for change in ("gae", "value-beta-one", "batch-minmax"):
        run(os.path.join(ROOT, "benchmark", "p3o_ablation.py"), change)
        name = f"p3o_{change.replace('-', '_')}"
        (run_dir,) = glob.glob(str(tmp_path / "runs" / f"Breakout-v5__{name}__5__*"))
        assert os.path.isfile(os.path.join(run_dir, "checkpoint.pt"))
        values, text = logged(run_dir)
        assert f"|exp_name|{name}|" in text
        assert len(values["losses/value_loss"]) == 2  # both iterations
        # the first rollout is the same as plain P3O's (same seed, same initial agent): beta is the same
        # unless the change is to beta, and the statistic each change acts on moves
        same_beta = values["p3o/beta_mean"][0] == plain["p3o/beta_mean"][0]
        assert same_beta == (change != "batch-minmax"), change
        acted_on = {"gae": "losses/policy_loss", "value-beta-one": "losses/value_loss", "batch-minmax": "p3o/beta_std"}
        assert values[acted_on[change]][0] != plain[acted_on[change]][0], change
        assert torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)["algorithm"] == f"p3o-{change}"
        # the checkpoint knows what made it: plain P3O does not continue an ablation's run, nor the other way round
        plain_script = os.path.join(ROOT, "p3o_atari_envpool.py")
        proc = subprocess.run([sys.executable, plain_script, "--resume", run_dir], capture_output=True, text=True)
        assert proc.returncode == 1
        assert proc.stderr == (
            f"error: --resume {run_dir}/checkpoint.pt is a p3o-{change} run's checkpoint; resume it with its own"
            " script.\n"
        )
        ablation_script = os.path.join(ROOT, "benchmark", "p3o_ablation.py")
        proc = subprocess.run(
            [sys.executable, ablation_script, change, "--resume", plain_dir], capture_output=True, text=True
        )
        assert proc.returncode == 1
        assert proc.stderr == (
            f"error: --resume {plain_dir}/checkpoint.pt is a p3o run's checkpoint; resume it with its own script.\n"
        )
        # and evaluate.py plays it as the P3O model it is, naming the ablation
        evaluate_script = os.path.join(ROOT, "benchmark", "evaluate.py")
        proc = subprocess.run(
            [sys.executable, evaluate_script, "--run", run_dir, "--episodes", "1"], capture_output=True, text=True
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert json.load(open(os.path.join(run_dir, "eval.json")))["algorithm"] == f"p3o-{change}"
    assert torch.load(os.path.join(plain_dir, "checkpoint.pt"), weights_only=True)["algorithm"] == "p3o"

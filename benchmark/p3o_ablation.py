r"""P3O with one of its pieces switched off or changed: the diagnostic runs behind "Does it learn?" in
benchmark/README.md. Not a second P3O: p3o_atari_envpool.py's own `main`, with one of its module
functions replaced before training starts. The first argument names the change; the rest are
p3o_atari_envpool.py's flags.

    uv run python benchmark/p3o_ablation.py gae --env-id Breakout-v5 --num-envs 8 --num-steps 128 \
        --num-minibatches 4 --update-epochs 4 --learning-rate 2.5e-4 --total-timesteps 250880

Changes:
  gae             advantages by plain GAE (beta = 0 in GBAE); the beta-weighted value loss kept
  value-beta-one  value loss with beta = 1 at every state (no 0.5 factor, as P3O); GBAE kept
  batch-minmax    beta normalised by the min and max over the whole [T+1, N] rollout, not per environment

Runs are named `{env}__p3o_{change}__{seed}__{time}` (`--exp-name` is set), so `results.py` keeps them
apart from P3O's.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import p3o_atari_envpool as p3o  # noqa: E402

CHANGES = ("gae", "value-beta-one", "batch-minmax")


def batch_minmax_betas(si, alpha):
    """The EWMA per environment as in P3O, then min-max over every state of the rollout at once."""
    import torch

    x = p3o.ewma(si, alpha)
    span = x.max() - x.min()
    if span <= 0:
        return torch.zeros_like(x)
    return ((x - x.min()) / span).clamp(0.0, 1.0).nan_to_num(0.0)


def apply(change: str) -> None:
    """Replace the P3O function that `change` names; `main` looks them up when it calls them."""
    import torch

    gbae, value_loss = p3o.gbae, p3o.value_loss
    if change == "gae":
        p3o.gbae = lambda rewards, values, dones, next_value, next_done, betas, next_beta, *rest: gbae(
            rewards, values, dones, next_value, next_done, torch.zeros_like(betas), torch.zeros_like(next_beta), *rest
        )
    elif change == "value-beta-one":
        p3o.value_loss = lambda newvalue, values, returns, betas, valid, clip_coef, clip_vloss: value_loss(
            newvalue, values, returns, torch.ones_like(betas), valid, clip_coef, clip_vloss
        )
    elif change == "batch-minmax":
        p3o.compute_betas = batch_minmax_betas
    else:
        raise ValueError(change)


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in CHANGES:
        sys.exit(f"error: the first argument must be one of {', '.join(CHANGES)}; the rest are P3O's flags.")
    import tyro

    change = argv[0]
    args = tyro.cli(p3o.Args, args=argv[1:])
    args.exp_name = f"p3o_{change.replace('-', '_')}"
    apply(change)
    p3o.main(args)


if __name__ == "__main__":
    main(sys.argv[1:])

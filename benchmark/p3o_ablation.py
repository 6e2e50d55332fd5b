r"""P3O with one of its pieces switched off or changed: the diagnostic runs behind "Does it learn?" and "Which piece
of P3O carries its lead" in benchmark/README.md. Not a second P3O: p3o_atari_envpool.py's own `main`, with one of its
module functions replaced before training starts. The first argument names the change; the rest are
p3o_atari_envpool.py's flags.

    uv run python benchmark/p3o_ablation.py gae --env-id Breakout-v5 --num-envs 8 --num-steps 128 \
        --num-minibatches 4 --update-epochs 4 --learning-rate 2.5e-4 --total-timesteps 250880

Changes:
  gae             advantages by plain GAE (beta = 0 in GBAE); the beta-weighted value loss kept
  value-beta-one  value loss with beta = 1 at every state (no 0.5 factor, as P3O); GBAE kept
  batch-minmax    beta normalised by the min and max over the whole [T+1, N] rollout, not per environment

Runs are named `{env}__p3o_{change}__{seed}__{time}` (`--exp-name` is set), so that `results.py` keeps them apart from
P3O's. Their checkpoints and models say `p3o-{change}` where P3O's say `p3o` (the script's ALGORITHM, set here): plain
P3O does not continue an ablation's run, nor this tool plain P3O's; benchmark/evaluate.py plays them as P3O models.
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
    return torch.zeros_like(x) if span <= 0 else (x - x.min()) / span


def apply(change: str) -> None:
    """Replace the P3O function that `change` names, and name the algorithm after the change. Refuses, rather than
    silently training plain P3O, when p3o_atari_envpool.main no longer calls a module function of that name."""
    import torch

    name = {"gae": "gbae", "value-beta-one": "value_loss", "batch-minmax": "compute_betas"}[change]
    if not hasattr(p3o, name) or name not in p3o.main.__code__.co_names:
        sys.exit(f"error: p3o_atari_envpool.main does not call {name}, so the {change} ablation would change nothing.")
    original = getattr(p3o, name)

    def gbae_with_beta_zero(rewards, values, dones, next_value, next_done, betas, *rest):
        return original(rewards, values, dones, next_value, next_done, torch.zeros_like(betas), *rest)

    def value_loss_with_beta_one(newvalue, values, returns, betas, *rest):
        return original(newvalue, values, returns, torch.ones_like(betas), *rest)

    replacement = {"gae": gbae_with_beta_zero, "value-beta-one": value_loss_with_beta_one}.get(
        change, batch_minmax_betas
    )
    setattr(p3o, name, replacement)
    p3o.ALGORITHM = f"p3o-{change}"  # written into the run's checkpoints, checked when one is resumed


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in CHANGES:
        sys.exit(f"error: the first argument must be one of {', '.join(CHANGES)}; the rest are P3O's flags.")
    import tyro

    change = argv[0]
    args = tyro.cli(p3o.Args, args=argv[1:])
    args.exp_name = f"p3o_{change.replace('-', '_')}"
    apply(change)
    p3o.main(args, argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])

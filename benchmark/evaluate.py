"""Evaluate a saved model (of either training script) or a random policy, without training.

The same evaluation the training scripts run after training (`--eval-episodes`): K full games (all
lives), game i in its own environment seeded `seed + i`, actions sampled from the policy (`--greedy`
for the most probable action). Prints each game's return and the mean ± standard error.

    uv run python benchmark/evaluate.py --model-path runs/RUN/p3o_atari_envpool.cleanrl_model --episodes 10
    uv run python benchmark/evaluate.py --random --env-id Breakout-v5 --episodes 10
"""

import importlib.util
import os
import sys
from dataclasses import dataclass

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
AGENT_FORMAT = "p3o-atari-agent/1"
CHECKPOINT_FORMAT = "p3o-atari-checkpoint/1"


@dataclass
class Args:
    model_path: str | None = None
    """a `.cleanrl_model` file (--save-model) or a `checkpoint.pt` of ppo_atari_envpool.py or p3o_atari_envpool.py"""
    env_id: str | None = None
    """the game (default: the one the model was trained on; required with --random)"""
    episodes: int = 10
    """how many full games to play"""
    seed: int = 1
    """game i is played in its own environment seeded seed + i"""
    greedy: bool = False
    """play the most probable action instead of sampling from the policy"""
    random: bool = False
    """evaluate a uniformly random policy instead of a model (the baseline)"""
    cuda: bool = True
    """run the network on the GPU when there is one"""
    run_dir: str | None = None
    """also write `eval.json` and a TensorBoard event file (`eval/episodic_return`) into this folder"""


def load_script(algorithm: str):
    """The training script whose network and evaluation this uses (`ppo` or `p3o`)."""
    path = os.path.join(ROOT, f"{algorithm}_atari_envpool.py")
    spec = importlib.util.spec_from_file_location(f"{algorithm}_atari_envpool", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_model(path: str) -> dict:
    """Read a model file, refusing with one clear sentence anything the training scripts did not write."""
    import torch

    if not os.path.isfile(path):
        sys.exit(f"error: --model-path {path}: no such file.")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        sys.exit(f"error: --model-path {path} is not a model file written by these scripts ({type(e).__name__}).")
    if not isinstance(saved, dict) or saved.get("algorithm") not in ("ppo", "p3o"):
        sys.exit(f"error: --model-path {path} is not a model file written by these scripts.")
    if saved.get("format") == CHECKPOINT_FORMAT:  # a training checkpoint holds the same agent
        weights = saved["model_state_dict"]
        saved = {"env_id": saved["args"]["env_id"], "num_actions": int(weights["actor.weight"].shape[0])} | saved
    elif saved.get("format") != AGENT_FORMAT:
        sys.exit(f"error: --model-path {path} is not a model file written by these scripts.")
    return saved


def main(args: Args) -> dict:
    import envpool
    import torch

    if args.episodes <= 0:
        sys.exit(f"error: --episodes must be positive, got {args.episodes}.")
    if args.random == (args.model_path is not None):
        sys.exit("error: give either --model-path or --random.")
    if args.random:
        if args.env_id is None:
            sys.exit("error: --random needs --env-id.")
        saved, algorithm, env_id = None, "random", args.env_id
    else:
        saved = load_model(args.model_path)
        algorithm, env_id = saved["algorithm"], args.env_id or saved["env_id"]
    script = load_script("ppo" if saved is None else saved["algorithm"])
    if env_id not in script.atari_env_ids():
        sys.exit(f"error: --env-id {env_id} is not an envpool Atari game.")
    num_actions = int(envpool.make_spec(env_id).action_space.n)
    agent = script.Agent(num_actions)
    if saved is None:
        # the random policy: the same network and evaluation with a zeroed policy head, so every action
        # has logit 0 and is sampled uniformly
        torch.nn.init.zeros_(agent.actor.weight)
        torch.nn.init.zeros_(agent.actor.bias)
    else:
        if saved["num_actions"] != num_actions:
            sys.exit(
                f"error: the model in {args.model_path} has {saved['num_actions']} actions "
                f"({saved['env_id']}) but {env_id} has {num_actions}."
            )
        try:
            agent.load_state_dict(saved["model_state_dict"])
        except RuntimeError as e:
            sys.exit(f"error: the weights in {args.model_path} do not fit the Nature CNN ({str(e).splitlines()[0]}).")
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    agent = agent.to(device)

    report = script.evaluate(agent, env_id, args.episodes, args.seed, args.greedy, device)
    report |= {"algorithm": algorithm, "model_path": args.model_path}
    for game, (ret, length) in enumerate(zip(report["returns"], report["lengths"], strict=True)):
        print(f"game {game} (seed {report['seeds'][game]}): return {ret:.1f}, {length} steps")
    print(f"{algorithm} on {env_id}: {args.episodes} games, return {report['mean']:.2f} ± {report['std_err']:.2f}")
    if args.run_dir:
        from torch.utils.tensorboard import SummaryWriter

        os.makedirs(args.run_dir, exist_ok=True)
        writer = SummaryWriter(args.run_dir)
        script.write_evaluation(report, args.run_dir, writer)
        writer.close()
        print(f"wrote {os.path.join(args.run_dir, 'eval.json')}")
    return report


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))

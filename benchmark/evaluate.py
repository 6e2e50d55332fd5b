"""Evaluate a saved model (of either training script) or a random policy, without training.

The training scripts' own evaluation (`--eval-episodes`): K full games (all lives), game i in its own
environment seeded `seed + i`, actions sampled from the policy (`--greedy` for the most probable action).
Prints each game's return and the mean ± standard error.

    uv run python benchmark/evaluate.py --model-path runs/RUN/p3o_atari_envpool.cleanrl_model --episodes 10
    uv run python benchmark/evaluate.py --random --env-id Breakout-v5 --episodes 10
    uv run python benchmark/evaluate.py --model-path runs/RUN/checkpoint.pt --episodes 3 --run-dir runs/RUN/eval --video
"""

import importlib
import os
import shutil
import sys
from dataclasses import dataclass

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the training scripts

from benchmark.results import folder_problem  # noqa: E402  (the same check for results.py --out)


@dataclass
class Args:
    model_path: str | None = None
    """a `.cleanrl_model` file (--save-model) or a `checkpoint.pt` of ppo_atari_envpool.py or p3o_atari_envpool.py"""
    env_id: str | None = None
    """the game (default: the one the model was trained on; required with --random)"""
    episodes: int = 10
    """how many full games to play"""
    seed: int = 1
    """game i is played in its own environment seeded seed + i; the actions are sampled from torch's generator
    seeded with it, so the same seed plays the same games"""
    greedy: bool = False
    """play the most probable action instead of sampling from the policy"""
    random: bool = False
    """evaluate a uniformly random policy instead of a model (the baseline)"""
    cuda: bool = True
    """run the network on the GPU when there is one"""
    run_dir: str | None = None
    """also write `eval.json` and a TensorBoard event file (`eval/episodic_return`) into this new folder (a
    model's evaluation is logged as `{exp_name} (evaluate.py)`, so results.py never counts it as another run)"""
    video: bool = False
    """also write each game as an MP4 (colour, 210x160, 15 frames/s) to `RUN_DIR/videos/eval-game{i}.mp4`"""


def load_script(algorithm: str):
    """The training script (`ppo` or `p3o`) whose network and evaluation this uses."""
    return importlib.import_module(f"{algorithm}_atari_envpool")


class UniformPolicy:
    """The random policy, with the `hidden` and `actor` that a training script's `evaluate` calls: a logit of
    0 for every action, so that the same evaluation samples each uniformly, without running the network."""

    def __init__(self, num_actions: int):
        self.num_actions = num_actions

    def hidden(self, x):
        return x

    def actor(self, x):
        # x is the uint8 frame batch (hidden passes it through): float logits of its batch size, on its device
        return x.new_zeros((x.shape[0], self.num_actions)).float()

    def to(self, device):
        return self


def load_model(path: str, script) -> dict:
    """Read a model file or checkpoint, refusing with one clear sentence anything the scripts did not write."""
    import torch

    if not os.path.isfile(path):
        sys.exit(f"error: --model-path {path}: no such file.")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        sys.exit(f"error: --model-path {path} is not a model file written by these scripts ({type(e).__name__}).")
    if (
        not isinstance(saved, dict)
        or saved.get("format") != script.FORMAT
        or saved.get("algorithm") not in ("ppo", "p3o")
    ):
        sys.exit(f"error: --model-path {path} is not a model file written by these scripts.")
    return saved


def main(args: Args) -> dict:
    import torch

    if args.episodes <= 0:
        sys.exit(f"error: --episodes must be positive, got {args.episodes}.")
    if args.random == (args.model_path is not None):
        sys.exit("error: give either --model-path or --random.")
    if args.random and args.env_id is None:
        sys.exit("error: --random needs --env-id.")
    if args.video and not args.run_dir:
        sys.exit("error: --video needs --run-dir, the folder whose videos/ the games are written to.")
    if not 0 <= args.seed <= 2**31 - args.episodes:
        sys.exit(
            f"error: --seed must lie in [0, {2**31 - args.episodes}] (envpool seeds stay below 2^31), got {args.seed}."
        )
    if args.run_dir and os.path.exists(args.run_dir):
        sys.exit(f"error: --run-dir {args.run_dir} already exists; the evaluation writes a new folder of its own.")
    if args.run_dir and folder_problem(args.run_dir):  # before the games, not a traceback after them
        sys.exit(f"error: --run-dir {args.run_dir} cannot be made: {folder_problem(args.run_dir)}.")
    saved = None if args.random else load_model(args.model_path, load_script("ppo"))
    script = load_script("ppo" if saved is None else saved["algorithm"])
    env_id = args.env_id or saved["args"]["env_id"]
    script.Args(env_id=env_id)  # its checks refuse a game that is not envpool Atari
    num_actions = int(script.envpool.make_spec(env_id).action_space.n)
    if saved is None:
        agent = UniformPolicy(num_actions)
    else:
        agent = script.Agent(num_actions)
        trained_on, weights = saved["args"]["env_id"], saved["model_state_dict"]
        if weights["actor.weight"].shape[0] != num_actions:
            sys.exit(
                f"error: the model in {args.model_path} has {weights['actor.weight'].shape[0]} actions "
                f"({trained_on}) but {env_id} has {num_actions}."
            )
        agent.load_state_dict(weights)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    agent = agent.to(device)
    device_name = script.say_device(device, args.cuda)

    # the folder is written under a hidden name and renamed when complete: an interrupted evaluation leaves no
    # half-written run for results.py or the learning check to mistake for a finished one
    parent, name = os.path.split(os.path.normpath(args.run_dir)) if args.run_dir else ("", "")
    partial = os.path.join(parent, f".{name}.partial-{os.getpid()}")
    videos = os.path.join(partial, "videos") if args.video else None
    # the sampled actions come from torch's generator, which torch otherwise seeds at random in each process:
    # seeded, the same --seed plays the same games
    torch.manual_seed(args.seed)
    report = script.evaluate(agent, env_id, args.episodes, args.seed, args.greedy, device, videos)
    algorithm = "random" if saved is None else saved["algorithm"]
    report |= {"algorithm": algorithm, "model_path": args.model_path, "device": device_name}
    for game, (ret, length) in enumerate(zip(report["returns"], report["lengths"], strict=True)):
        print(f"game {game} (seed {report['seeds'][game]}): return {ret:.1f}, {length} steps")
    print(f"{algorithm} on {env_id}: {args.episodes} games, return {report['mean']:.2f} ± {report['std_err']:.2f}")
    if args.run_dir:
        from torch.utils.tensorboard import SummaryWriter

        os.makedirs(partial, exist_ok=True)
        writer = SummaryWriter(partial)
        # the run's identity, as the training scripts log it, for benchmark/results.py: a model's evaluation is
        # a group of its own, never a second run of the training run it came from
        exp_name = "random" if saved is None else f"{saved['args']['exp_name']} (evaluate.py)"
        writer.add_text(
            "hyperparameters", f"|param|value|\n|-|-|\n|exp_name|{exp_name}|\n|env_id|{env_id}|\n|seed|{args.seed}|"
        )
        if videos:
            report["videos"] = [path.replace(partial, args.run_dir, 1) for path in report["videos"]]
        script.write_evaluation(report, partial, writer)
        writer.close()
        try:
            os.rename(partial, args.run_dir)
        except OSError as e:
            shutil.rmtree(partial, ignore_errors=True)
            sys.exit(f"error: could not write --run-dir {args.run_dir} ({e.strerror}); nothing was written.")
        print(f"wrote {os.path.join(args.run_dir, 'eval.json')}" + (f" and {args.run_dir}/videos/" if videos else ""))
    return report


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))

"""Evaluate a trained run, a saved model or a random policy: the one evaluation loop of the repository (the training
scripts only train, as CleanRL's do; RL Zoo calls this `enjoy.py`).

The protocol: K full games (all lives), game i in its own environment seeded `seed + i`, the actions sampled from the
policy (`--greedy`: its most probable action); unclipped returns, their mean and standard error (population standard
deviation / sqrt(K), as the thesis's table 5.1).

    uv run python benchmark/evaluate.py --run runs/RUN                       # a training run's own evaluation
    uv run python benchmark/evaluate.py --run runs/RUN --replay              # play it again, game for game
    uv run python benchmark/evaluate.py --model-path runs/RUN/checkpoint.pt --episodes 3 --run-dir runs/RUN/clip --video
    uv run python benchmark/evaluate.py --random --env-id Breakout-v5 --episodes 10 --seed 1000001

`--run RUN` is what the sweep and the learning check call after each training run: the run's finished checkpoint
plays games seeded with the run's seed + 1,000,000 + i, sampling with torch's random state as training left it (kept
in the checkpoint), so they are the games the training process itself would have played next (the scripts did until
2026-12, and the runs they evaluated compare like for like). It writes `eval.json` and `eval/episodic_return` (step =
game index) into the run's folder once, after the last game; a run already evaluated is not played again, and
`--replay` plays it again and checks every game against its `eval.json`.
"""

import contextlib
import importlib
import json
import os
import shutil
import signal
import sys
from dataclasses import dataclass

import numpy as np
import torch
import tyro

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the training scripts

from benchmark.results import folder_problem  # noqa: E402  (the same check for results.py --out)

RUN_SEED_OFFSET = 1_000_000  # a run's evaluation games are seeded seed + 1,000,000 + i, apart from its training's


@dataclass
class Args:
    run: str | None = None
    """a training run's folder (`runs/NAME`): play its finished checkpoint as the run's own evaluation and write
    `eval.json` and `eval/episodic_return` into it (once: a run already evaluated is not played again)"""
    replay: bool = False
    """with --run: play an evaluated run's games again and check each against its `eval.json`"""
    model_path: str | None = None
    """a `.cleanrl_model` file (--save-model) or a `checkpoint.pt` of ppo_atari_envpool.py or p3o_atari_envpool.py"""
    random: bool = False
    """evaluate a uniformly random policy instead of a model (the baseline)"""
    env_id: str | None = None
    """the game (default: the one the model was trained on; required with --random)"""
    episodes: int = 10
    """how many full games to play"""
    seed: int = 1
    """game i is played in its own environment seeded seed + i; the actions are sampled from torch's generator
    seeded with it, so the same seed plays the same games (with --run: the run's seed + 1,000,000)"""
    greedy: bool = False
    """play the most probable action instead of sampling from the policy"""
    cuda: bool = True
    """run the network on the GPU when there is one"""
    run_dir: str | None = None
    """with --model-path or --random: also write `eval.json` and an event file (`eval/episodic_return`) into this new
    folder (a model's evaluation is logged as `{exp_name} (evaluate.py)`, so results.py never counts it as a run)"""
    video: bool = False
    """also write each game as an MP4 (colour, 210x160, 15 frames/s) to `videos/eval-game{i}.mp4` of --run or
    --run-dir"""


def load_script(algorithm: str):
    """The training script whose network a model of `algorithm` uses (`ppo`, `p3o`, or a P3O ablation's `p3o-...`)."""
    return importlib.import_module(f"{algorithm[:3]}_atari_envpool")


class UniformPolicy:
    """The random policy, with the `hidden` and `actor` that `play` calls: a logit of 0 for every action, so that the
    same evaluation samples each uniformly, without running the network."""

    def __init__(self, num_actions: int):
        self.num_actions = num_actions

    def hidden(self, x):
        return x

    def actor(self, x):
        # x is the uint8 frame batch (hidden passes it through): float logits of its batch size, on its device
        return x.new_zeros((x.shape[0], self.num_actions)).float()

    def to(self, device):
        return self


def play(agent, env_id, episodes, seed, greedy, device, video_dir=None) -> dict:
    """Play `episodes` full games (all lives), game i in its own environment seeded `seed + i`, with actions sampled
    from the policy (or its most probable action when `greedy`); unclipped returns. The mean's standard error uses
    the population standard deviation, as the thesis's table 5.1. With `video_dir`, game i is also written to
    `video_dir/eval-game{i}.mp4`: the colour frame after each of its agent steps, at 15 frames/s (the emulator's
    60 Hz over envpool's frame skip of 4)."""
    from torch.distributions.categorical import Categorical

    envs = load_script("ppo").make_env(env_id, episodes, seed, render_mode="rgb_array" if video_dir else None)
    paths = [f"{video_dir}/eval-game{i}.mp4" for i in range(episodes)] if video_dir else []
    if video_dir:
        import imageio_ffmpeg  # only here: nothing else needs it (the GPU bundle carries it without its ffmpeg)

        os.makedirs(video_dir, exist_ok=True)
    writers = []
    returns, lengths, playing = np.zeros(episodes), np.zeros(episodes, dtype=np.int64), np.ones(episodes, dtype=bool)
    try:
        for path in paths:
            writer = imageio_ffmpeg.write_frames(path, (160, 210), fps=15, macro_block_size=1, ffmpeg_log_level="error")
            writers.append(writer)
            writer.send(None)  # start the encoder
        obs_np, _ = envs.reset()
        with torch.inference_mode():
            while playing.any():
                stop_if_signalled()
                logits = agent.actor(agent.hidden(torch.as_tensor(obs_np, device=device)))
                action = logits.argmax(-1) if greedy else Categorical(logits=logits, validate_args=False).sample()
                obs_np, _, terminations, truncations, info = envs.step(action.cpu().numpy())
                if writers:  # the colour frame of each game still playing
                    for game, frame in zip(np.flatnonzero(playing), envs.render(np.flatnonzero(playing)), strict=True):
                        writers[game].send(np.ascontiguousarray(frame))
                returns += info["reward"] * playing
                lengths += playing
                playing &= ~np.logical_or(info["terminated"].astype(bool), truncations)
    except BaseException:  # stopped or failed: the encoders are killed, not left to finish videos that are deleted
        for writer in writers:
            with contextlib.suppress(BaseException):
                writer.throw(SystemExit)  # imageio-ffmpeg kills its ffmpeg on SystemExit
        raise
    finally:
        envs.close()
        for writer in writers:
            writer.close()
    games = {"seeds": [seed + i for i in range(episodes)], "returns": returns.tolist(), "lengths": lengths.tolist()}
    summary = {"mean": float(returns.mean()), "std_err": float(returns.std() / np.sqrt(episodes))}
    return {"env_id": env_id, "greedy": greedy} | games | summary | ({"videos": paths} if paths else {})


def load_model(path: str, flag: str = "--model-path") -> dict:
    """Read a model file or checkpoint, refusing with one clear sentence anything the scripts did not write."""
    if not os.path.isfile(path):
        sys.exit(f"error: {flag} {path}: no such file.")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        sys.exit(f"error: {flag} {path} is not a model file written by these scripts ({type(e).__name__}).")
    if not isinstance(saved, dict) or saved.get("format") != load_script("ppo").FORMAT:
        sys.exit(f"error: {flag} {path} is not a model file written by these scripts.")
    if not str(saved.get("algorithm")).startswith(("ppo", "p3o")):
        sys.exit(f"error: {flag} {path} is not a model file written by these scripts.")
    return saved


def write_evaluation(report: dict, folder: str, hyperparameters: str | None = None) -> None:
    """Each game's return as `eval/episodic_return` (step = game index) in an event file of its own, then `eval.json`,
    written whole (a temporary file, renamed) and last: it is the record that the folder was evaluated, and the event
    file is only ever there with it (one left by an evaluation that failed before eval.json is removed first)."""
    from torch.utils.tensorboard import SummaryWriter

    for stale in [f for f in os.listdir(folder) if f.startswith("events.out.tfevents.") and f.endswith(".eval")]:
        os.remove(os.path.join(folder, stale))
    with SummaryWriter(folder, filename_suffix=".eval") as writer:
        if hyperparameters:
            writer.add_text("hyperparameters", hyperparameters)
        for game, ret in enumerate(report["returns"]):
            writer.add_scalar("eval/episodic_return", ret, game)
    with open(os.path.join(folder, "eval.json.tmp"), "w") as f:
        json.dump(report, f, indent=2)
    os.replace(os.path.join(folder, "eval.json.tmp"), os.path.join(folder, "eval.json"))


def refuse(args: Args) -> str | None:
    """The first thing wrong with the arguments, before any game is played."""
    if (args.run is not None) + (args.model_path is not None) + args.random != 1:
        return "give one of --run, --model-path or --random."
    if args.episodes <= 0:
        return f"--episodes must be positive, got {args.episodes}."
    if args.replay and args.run is None:
        return "--replay plays a run's evaluation again: give --run."
    if args.run is not None and (args.run_dir or args.env_id or args.seed != 1):
        return "--run plays the run's own games into its folder: --run-dir, --env-id and --seed are for --model-path."
    if args.random and args.env_id is None:
        return "--random needs --env-id."
    if args.video and not (args.run_dir or args.run):
        return "--video needs --run-dir, the folder whose videos/ the games are written to."
    if not 0 <= args.seed <= 2**31 - args.episodes:
        return f"--seed must lie in [0, {2**31 - args.episodes}] (envpool seeds stay below 2^31), got {args.seed}."
    if args.run_dir and os.path.exists(args.run_dir):
        return f"--run-dir {args.run_dir} already exists; the evaluation writes a new folder of its own."
    if args.run_dir and folder_problem(args.run_dir):  # before the games, not a traceback after them
        return f"--run-dir {args.run_dir} cannot be made: {folder_problem(args.run_dir)}."
    return None


def main(args: Args) -> dict | None:
    problem = refuse(args)
    if problem:
        sys.exit(f"error: {problem}")
    run_eval = os.path.join(args.run, "eval.json") if args.run else None
    if run_eval and os.path.exists(run_eval) and not args.replay:
        load_script("ppo").say(f"{run_eval}: this run was evaluated before; not played again (--replay checks it).")
        return None
    if args.run:
        saved = load_model(os.path.join(args.run, "checkpoint.pt"), "--run")
        if not saved.get("finished"):
            sys.exit(f"error: --run {args.run} has not finished training; continue it with --resume {args.run} first.")
        seed = saved["args"]["seed"] + RUN_SEED_OFFSET
    else:
        saved = None if args.random else load_model(args.model_path)
        seed = args.seed
    script = load_script("ppo" if saved is None else saved["algorithm"])
    say = script.say
    env_id = saved["args"]["env_id"] if args.env_id is None else args.env_id
    script.Args(env_id=env_id)  # its checks refuse a game that is not envpool Atari
    if not 0 <= seed <= 2**31 - args.episodes:
        sys.exit(
            f"error: the run's evaluation seeds ({seed} + i) pass envpool's 2^31 - 1; use --model-path and --seed."
        )
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
    # the sampled actions come from torch's generator: a run's, as training left it (its checkpoint keeps it; a
    # checkpoint older than that starts from the evaluation seed), or seeded with --seed, so the same seed plays the
    # same games (torch seeds its generator at random in each process otherwise)
    if args.run and "rng_state" in saved:
        torch.set_rng_state(saved["rng_state"])
    else:
        torch.manual_seed(seed)

    # outputs are written under a hidden name and renamed when complete: an interrupted evaluation leaves no half-made
    # folder or video for results.py or the learning check to mistake for a finished one
    target = args.run or args.run_dir
    parent, name = os.path.split(os.path.normpath(target)) if target else ("", "")
    partial = os.path.join(parent, f".{name}.partial-{os.getpid()}")
    videos = os.path.join(partial, "videos") if args.video else None
    try:
        report = play(agent, env_id, args.episodes, seed, args.greedy, device, videos)
        stop_if_signalled()  # one that came as the encoders finished
        for game, (ret, length) in enumerate(zip(report["returns"], report["lengths"], strict=True)):
            say(f"game {game} (seed {report['seeds'][game]}): return {ret:.1f}, {length} steps")
        if args.replay:
            return check_replay(report, run_eval, say)
        if args.run:
            made = {"algorithm": saved["algorithm"], "global_step": saved["global_step"], "device": device_name}
            report |= made
            record_run(args, report, saved, partial, say)
        else:
            algorithm = "random" if saved is None else saved["algorithm"]
            report |= {"algorithm": algorithm, "model_path": args.model_path, "device": device_name}
            say(
                f"{algorithm} on {env_id}: {args.episodes} games, return {report['mean']:.2f} ± {report['std_err']:.2f}"
            )
            if args.run_dir:
                record_folder(args, report, saved, env_id, partial, say)
    except Exception:  # an error after a stop signal is its doing: it reaches the helpers ffmpeg runs in our group
        stop_if_signalled()
        raise
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return report


STOPS: list[int] = []  # the stop signals received (SIGTERM, SIGINT), from the command line


def note_stop(signum, frame):
    """A stop signal is only noted here and acted on between two steps of the games: an exit raised in the handler
    can land in Python's at-fork hooks as an encoder starts, which print it and go on (the games would play on)."""
    STOPS.append(signum)


def stop_if_signalled():
    """After a stop signal an evaluation ends at its next step, writing nothing (the model is on disk); one that
    comes once the games are played is too late to lose them: the evaluation is written."""
    if STOPS:
        load_script("ppo").say(
            f"stopped by signal {STOPS[0]}: nothing was written (the model is on disk: run this again)"
        )
        sys.exit(128 + STOPS[0])


def check_replay(report: dict, run_eval: str, say) -> dict:
    """--replay: every game of the run's eval.json played again, the same seed, return and length."""
    with open(run_eval) as f:
        recorded = json.load(f)
    keys = ("seeds", "returns", "lengths")
    if [recorded.get(k) for k in keys] != [report[k] for k in keys]:
        sys.exit(f"error: the replayed games differ from {run_eval} (another machine, torch or envpool may be why).")
    say(f"replayed {run_eval}: the same {len(report['returns'])} games, return {report['mean']:.2f}")
    return report


def record_run(args: Args, report: dict, saved: dict, partial: str, say) -> None:
    """A run's evaluation into its folder (videos first, renamed into place whole), and into its W&B run if tracked."""
    if report.get("videos"):
        os.makedirs(partial, exist_ok=True)
        shutil.rmtree(os.path.join(args.run, "videos"), ignore_errors=True)
        os.rename(os.path.join(partial, "videos"), os.path.join(args.run, "videos"))
        report["videos"] = [p.replace(partial, args.run, 1) for p in report["videos"]]
    wandb_id, train = os.path.join(args.run, "wandb_id"), saved["args"]
    wandb = importlib.import_module("wandb") if train.get("track") and os.path.exists(wandb_id) else None
    if wandb:  # the training's W&B run goes on, mirroring the evaluation's event file
        config = dict(project=train["wandb_project_name"], entity=train["wandb_entity"], id=open(wandb_id).read())
        wandb.init(**config, name=os.path.basename(os.path.normpath(args.run)), sync_tensorboard=True, resume="allow")
    write_evaluation(report, args.run)
    if wandb:
        videos = enumerate(report.get("videos", []))
        wandb.log({f"videos/eval-game{i}": wandb.Video(path) for i, path in videos})
        wandb.finish()
    say(f"eval: {args.episodes} games, return {report['mean']:.1f} ± {report['std_err']:.1f} -> {args.run}/eval.json")


def record_folder(args: Args, report: dict, saved: dict | None, env_id: str, partial: str, say) -> None:
    """A model's or the random policy's evaluation into a new folder (written under a hidden name, then renamed)."""
    os.makedirs(partial, exist_ok=True)
    # the run's identity, as the training scripts log it, for benchmark/results.py: a model's evaluation is a group
    # of its own, never a second run of the training run it came from
    exp_name = "random" if saved is None else f"{saved['args']['exp_name']} (evaluate.py)"
    text = f"|param|value|\n|-|-|\n|exp_name|{exp_name}|\n|env_id|{env_id}|\n|seed|{args.seed}|"
    if report.get("videos"):
        report["videos"] = [path.replace(partial, args.run_dir, 1) for path in report["videos"]]
    write_evaluation(report, partial, text)
    try:
        os.rename(partial, args.run_dir)
    except OSError as e:
        sys.exit(f"error: could not write --run-dir {args.run_dir} ({e.strerror}); nothing was written.")
    videos = f" and {args.run_dir}/videos/" if args.video else ""
    say(f"wrote {os.path.join(args.run_dir, 'eval.json')}{videos}")


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, note_stop)
    signal.signal(signal.SIGINT, note_stop)
    main(tyro.cli(Args))

# PPO on envpool Atari, after CleanRL's ppo_atari_envpool.py, rewritten for envpool 1.x
# (gymnasium-style `reset() -> (obs, info)` and 5-tuple `step`).
# Docs: README.md. The P3O script (p3o_atari_envpool.py) is this file plus P3O: diff the two.
import ctypes
import difflib
import json
import os
import random
import signal
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions.categorical import Categorical

ALGORITHM = "ppo"  # written into model files and checkpoints, checked when they are loaded


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (the run folder and the saved model are named after it)"""
    seed: int = 1
    """seed of the experiment: python, numpy, torch and envpool are seeded with it"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda is used when available (the script falls back to the CPU without a GPU)"""
    save_model: bool = False
    """whether to save the trained agent to `runs/{run_name}/{exp_name}.cleanrl_model`"""
    run_name: str | None = None
    """the run folder under `runs/` (default: `{env_id}__{exp_name}__{seed}__{unix_time}`)"""
    checkpoint_every: int = 10
    """write `runs/{run_name}/checkpoint.pt` every this many iterations (0: only at the end and on a signal)"""
    resume: str | None = None
    """continue the run of this checkpoint (a `checkpoint.pt` or its run folder)"""
    auto_resume: bool = False
    """continue `runs/{run_name}` if it holds a checkpoint, else start it (for sweeps and requeued jobs)"""
    eval_episodes: int = 10
    """after training, play this many full games (each its own environment and seed) and log their returns"""
    eval_greedy: bool = False
    """evaluate with the most probable action instead of sampling from the policy"""

    # Algorithm specific arguments: defaults are the thesis's table 5.2, the same for PPO and P3O
    env_id: str = "Breakout-v5"
    """the id of the envpool Atari game (`*-v5`)"""
    total_timesteps: int = 20_000_000
    """total timesteps of the experiment"""
    learning_rate: float = 1e-3
    """the learning rate of the optimizer"""
    num_envs: int = 256
    """the number of parallel game environments"""
    num_steps: int = 256
    """the number of steps to run in each environment per policy rollout"""
    anneal_lr: bool = True
    """toggle learning rate annealing for policy and value networks"""
    gamma: float = 0.99
    """the discount factor gamma"""
    gae_lambda: float = 0.95
    """the lambda for the general advantage estimation"""
    num_minibatches: int = 8
    """the number of mini-batches"""
    update_epochs: int = 8
    """the K epochs to update the policy"""
    norm_adv: bool = True
    """toggles advantages normalization (per minibatch)"""
    clip_coef: float = 0.1
    """the surrogate clipping coefficient"""
    clip_vloss: bool = True
    """toggles whether or not to use a clipped loss for the value function, as per the paper"""
    ent_coef: float = 0.01
    """coefficient of the entropy"""
    vf_coef: float = 1.0
    """coefficient of the value function"""
    max_grad_norm: float = 0.5
    """the maximum norm for the gradient clipping"""
    target_kl: float | None = None
    """the target KL divergence threshold (early stop of the update epochs when exceeded)"""

    # to be filled in runtime
    batch_size: int = 0
    """the batch size (computed in runtime: num_envs * num_steps)"""
    minibatch_size: int = 0
    """the mini-batch size (computed in runtime)"""
    num_iterations: int = 0
    """the number of iterations (computed in runtime)"""


def atari_env_ids() -> list[str]:
    import envpool

    return [i for i in envpool.list_all_envs() if envpool.registration.registry.specs[i][0] == "envpool.atari"]


def check_args(args: Args) -> None:
    """Fail fast, before any environment starts, with one clear sentence per bad input."""
    for name in ("total_timesteps", "num_envs", "num_steps", "num_minibatches", "update_epochs"):
        if getattr(args, name) <= 0:
            sys.exit(f"error: --{name.replace('_', '-')} must be positive, got {getattr(args, name)}.")
    if not args.learning_rate > 0:
        sys.exit(f"error: --learning-rate must be positive, got {args.learning_rate}.")
    for name in ("gamma", "gae_lambda"):
        if not 0 <= getattr(args, name) <= 1:
            sys.exit(f"error: --{name.replace('_', '-')} must lie in [0, 1], got {getattr(args, name)}.")
    for name in ("checkpoint_every", "eval_episodes"):
        if getattr(args, name) < 0:
            sys.exit(f"error: --{name.replace('_', '-')} must be 0 or more, got {getattr(args, name)}.")
    if args.auto_resume and not args.run_name:
        sys.exit("error: --auto-resume needs --run-name, the run folder it continues.")
    batch_size = args.num_envs * args.num_steps
    if batch_size % args.num_minibatches != 0:
        sys.exit(
            f"error: the batch of --num-envs * --num-steps = {batch_size} steps does not divide into "
            f"--num-minibatches {args.num_minibatches} equal minibatches."
        )
    if args.total_timesteps < batch_size:
        sys.exit(
            f"error: --total-timesteps {args.total_timesteps} is smaller than one batch "
            f"(--num-envs * --num-steps = {batch_size}), so not a single update would run."
        )
    import envpool

    atari = atari_env_ids()
    if args.env_id not in atari:
        close = difflib.get_close_matches(args.env_id, atari, n=3, cutoff=0.5)
        hint = f" Did you mean {', '.join(close)}?" if close else " Atari ids look like Breakout-v5."
        if args.env_id in envpool.list_all_envs():
            sys.exit(f"error: --env-id {args.env_id} is an envpool environment but not an Atari game.{hint}")
        sys.exit(f"error: --env-id {args.env_id} is not an envpool environment.{hint}")


def make_env(env_id: str, num_envs: int, seed: int):
    """envpool Atari as in CleanRL: episodic life, clipped rewards, 4 stacked 84x84 grey frames.
    envpool seeds environment i with seed + i."""
    import envpool

    return envpool.make(
        env_id, env_type="gymnasium", num_envs=num_envs, episodic_life=True, reward_clip=True, seed=seed
    )


def layer_init(layer, std=np.sqrt(2), bias_const=0.0):
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, num_actions: int):
        super().__init__()
        self.network = nn.Sequential(
            layer_init(nn.Conv2d(4, 32, 8, stride=4)),
            nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)),
            nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)),
            nn.ReLU(),
            nn.Flatten(),
            layer_init(nn.Linear(64 * 7 * 7, 512)),
            nn.ReLU(),
        )
        self.actor = layer_init(nn.Linear(512, num_actions), std=0.01)
        self.critic = layer_init(nn.Linear(512, 1), std=1)

    def hidden(self, x):
        # frames stay uint8 in storage; they become floats in [0, 1] only here, one batch at a time
        return self.network(x.float() / 255.0)

    def get_value(self, x):
        return self.critic(self.hidden(x)).squeeze(-1)

    def get_action_and_value(self, x, action=None):
        hidden = self.hidden(x)
        probs = Categorical(logits=self.actor(hidden), validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs.entropy(), self.critic(hidden).squeeze(-1)


def save_agent(path: str, agent: Agent, args: Args, num_actions: int) -> None:
    """Write the agent with what is needed to rebuild it, atomically (temporary file, then rename)."""
    checkpoint = {
        "format": "p3o-atari-agent/1",
        "algorithm": ALGORITHM,
        "exp_name": args.exp_name,
        "env_id": args.env_id,
        "num_actions": num_actions,
        "args": vars(args),
        "model_state_dict": agent.state_dict(),
    }
    tmp = f"{path}.tmp"
    torch.save(checkpoint, tmp)
    os.replace(tmp, path)


CHECKPOINT_FORMAT = "p3o-atari-checkpoint/1"
# arguments that may differ between a run and its resumption; all others define the experiment
RESUMABLE_ARGS = {
    "cuda",
    "save_model",
    "checkpoint_every",
    "resume",
    "auto_resume",
    "eval_episodes",
    "eval_greedy",
    "torch_deterministic",
}


def rng_state() -> dict:
    """The python, numpy and torch random states, in types that `torch.load(weights_only=True)` reads."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    state = {
        "python": random.getstate(),
        "numpy": (kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate((state["python"][0], tuple(state["python"][1]), state["python"][2]))
    kind, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path, agent, optimizer, args, iteration, rng, finished=False) -> None:
    """Everything needed to continue after `iteration`, written atomically (temporary file, then rename)."""
    checkpoint = {
        "format": CHECKPOINT_FORMAT,
        "algorithm": ALGORITHM,
        "args": vars(args),
        "iteration": iteration,
        "global_step": iteration * args.batch_size,
        "finished": finished,
        "model_state_dict": agent.state_dict(),
        "optimizer_state_dict": optimizer.state_dict(),
        "rng_state": rng,
    }
    tmp = f"{path}.tmp"
    torch.save(checkpoint, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str) -> tuple[str, dict]:
    """Read a checkpoint (or the one in a run folder), refusing anything else by name."""
    if os.path.isdir(path):
        path = os.path.join(path, "checkpoint.pt")
    if not os.path.isfile(path):
        sys.exit(f"error: --resume {path}: there is no checkpoint there.")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        sys.exit(f"error: --resume {path} is not a readable checkpoint; it may be truncated or corrupt ({e!r:.150}).")
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        sys.exit(f"error: --resume {path} is not a checkpoint written by these scripts.")
    if checkpoint["algorithm"] != ALGORITHM:
        sys.exit(
            f"error: --resume {path} is a {checkpoint['algorithm']} checkpoint; "
            f"resume it with {checkpoint['algorithm']}_atari_envpool.py."
        )
    return path, checkpoint


def restore(checkpoint: dict, agent, optimizer) -> None:
    """Model, optimizer (with its learning rate) and random states as the checkpoint saved them."""
    agent.load_state_dict(checkpoint["model_state_dict"])
    optimizer.load_state_dict(checkpoint["optimizer_state_dict"])
    set_rng_state(checkpoint["rng_state"])


def check_resume_args(args: Args, saved: dict, path: str) -> None:
    """Refuse to resume with arguments that would change the experiment."""
    computed = {"batch_size", "minibatch_size", "num_iterations", "run_name"}
    differ = [
        f"--{name.replace('_', '-')} {saved.get(name)!r} (now {value!r})"
        for name, value in vars(args).items()
        if name not in RESUMABLE_ARGS | computed and saved.get(name) != value
    ]
    if differ:
        sys.exit(f"error: --resume {path} was started with {', '.join(differ)}; resume it with the same arguments.")


def evaluate(agent, env_id, episodes, seed, greedy, device) -> dict:
    """Play `episodes` full games (all lives), game i in its own environment seeded `seed + i`, with
    actions sampled from the policy (or its most probable action when `greedy`); unclipped returns.
    The mean's standard error uses the population standard deviation, as the thesis's table 5.1."""
    envs = make_env(env_id, episodes, seed)
    obs_np, _ = envs.reset()
    returns = np.zeros(episodes)
    lengths = np.zeros(episodes, dtype=np.int64)
    playing = np.ones(episodes, dtype=bool)
    with torch.inference_mode():
        while playing.any():
            logits = agent.actor(agent.hidden(frames_to_device(obs_np, device, None)))
            action = logits.argmax(-1) if greedy else Categorical(logits=logits, validate_args=False).sample()
            obs_np, _, terminations, truncations, info = envs.step(action.cpu().numpy())
            returns += info["reward"] * playing
            lengths += playing
            playing &= ~np.logical_or(info["terminated"].astype(bool), truncations)
    envs.close()
    return {
        "env_id": env_id,
        "greedy": greedy,
        "seeds": [seed + i for i in range(episodes)],
        "returns": returns.tolist(),
        "lengths": lengths.tolist(),
        "mean": float(returns.mean()),
        "std_err": float(returns.std() / np.sqrt(episodes)),
    }


def write_evaluation(report: dict, run_dir: str, writer) -> None:
    """Each game's return under `eval/episodic_return` (step = game index), and `eval.json`."""
    for game, ret in enumerate(report["returns"]):
        writer.add_scalar("eval/episodic_return", ret, game)
    writer.flush()
    with open(os.path.join(run_dir, "eval.json"), "w") as f:
        json.dump(report, f, indent=2)


def gae(rewards, values, dones, next_value, next_done, gamma, gae_lambda):
    """Generalized advantage estimation over a [T, N] rollout; dones[t] = 1 means the episode ended
    just before obs[t]. Each step is one vectorised operation over the N environments."""
    advantages = torch.zeros_like(rewards)
    lastgaelam = torch.zeros_like(next_value)
    num_steps = rewards.shape[0]
    for t in reversed(range(num_steps)):
        if t == num_steps - 1:
            nextnonterminal = 1.0 - next_done
            nextvalues = next_value
        else:
            nextnonterminal = 1.0 - dones[t + 1]
            nextvalues = values[t + 1]
        delta = rewards[t] + gamma * nextvalues * nextnonterminal - values[t]
        advantages[t] = lastgaelam = delta + gamma * gae_lambda * nextnonterminal * lastgaelam
    return advantages


def masked_mean(x, valid):
    return (x * valid).sum() / valid.sum().clamp(min=1)


def normalize_advantages(advantages, valid):
    """Zero mean, unit (sample) standard deviation over the valid steps of a minibatch."""
    n = valid.sum()
    mean = (advantages * valid).sum() / n.clamp(min=1)
    std = (((advantages - mean) ** 2 * valid).sum() / (n - 1).clamp(min=1)).sqrt()
    return (advantages - mean) / (std + 1e-8)


def value_loss(newvalue, values, returns, valid, clip_coef, clip_vloss):
    """CleanRL's value loss, 0.5 * mean of the (clipped) squared error over the valid steps."""
    v_loss_unclipped = (newvalue - returns) ** 2
    if clip_vloss:
        v_clipped = values + torch.clamp(newvalue - values, -clip_coef, clip_coef)
        v_loss_clipped = (v_clipped - returns) ** 2
        err = torch.max(v_loss_unclipped, v_loss_clipped)
    else:
        err = v_loss_unclipped
    return 0.5 * masked_mean(err, valid)


def explained_variance(values, returns, valid):
    mask = valid.bool()
    y_pred, y_true = values[mask], returns[mask]
    var_y = y_true.var(unbiased=False)
    return torch.where(var_y == 0, torch.nan, 1 - (y_true - y_pred).var(unbiased=False) / var_y)


def frames_to_device(frames: np.ndarray, device: torch.device, staging: torch.Tensor | None) -> torch.Tensor:
    """envpool's uint8 frames as a tensor on the training device: no copy on the CPU; on the GPU one
    copy into pinned memory and one asynchronous host-to-device copy."""
    frames = torch.from_numpy(frames)
    if staging is None:
        return frames.to(device)
    return staging.copy_(frames).to(device, non_blocking=True)


def keep_freed_memory() -> None:
    """Let glibc keep freed memory for reuse instead of giving it back to the OS. A CPU minibatch of a
    few hundred frames allocates ~60 MB of tensors (float frames, activations, gradients) that glibc
    would otherwise unmap after use and page-fault back in for the next minibatch (benchmark/README.md).
    Blocks of 64 MB or more (thesis-size minibatches) are still unmapped when freed, so the peak host
    memory does not grow (measured within 2%). Changes no number."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc (e.g. musl): keep its defaults
        return
    libc.mallopt(-3, 64 << 20)  # M_MMAP_THRESHOLD: blocks under 64 MB come from the reusable heap
    libc.mallopt(-1, 2**31 - 1)  # M_TRIM_THRESHOLD: do not shrink the heap after each free


def main(args: Args) -> dict[str, list[float]]:
    """Train; returns the seconds each iteration spent in the rollout and in the update."""
    check_args(args)
    keep_freed_memory()
    args.batch_size = int(args.num_envs * args.num_steps)
    args.minibatch_size = int(args.batch_size // args.num_minibatches)
    args.num_iterations = args.total_timesteps // args.batch_size
    checkpoint = None
    if args.auto_resume and args.resume is None and os.path.exists(f"runs/{args.run_name}/checkpoint.pt"):
        args.resume = f"runs/{args.run_name}"
    if args.resume is not None:
        checkpoint_path, checkpoint = load_checkpoint(args.resume)
        check_resume_args(args, checkpoint["args"], checkpoint_path)
        run_dir = os.path.dirname(checkpoint_path)
        if checkpoint["finished"]:
            print(f"{run_dir} already finished ({checkpoint['global_step']} steps); nothing to do.")
            return {"rollout_s": [], "update_s": [], "iteration_s": []}
    else:
        run_name = args.run_name or f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
        run_dir = f"runs/{run_name}"
        checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
        if os.path.exists(checkpoint_path):
            sys.exit(f"error: {run_dir} already holds a run; continue it with --resume {run_dir}.")
    start_iteration = checkpoint["iteration"] if checkpoint else 0

    from torch.utils.tensorboard import SummaryWriter

    # on resume, points the killed run logged after its checkpoint are purged, so none is duplicated
    writer = SummaryWriter(run_dir, purge_step=start_iteration * args.batch_size + 1 if checkpoint else None)
    if checkpoint is None:
        writer.add_text(
            "hyperparameters",
            "|param|value|\n|-|-|\n" + "\n".join([f"|{key}|{value}|" for key, value in vars(args).items()]),
        )

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic

    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    if device.type == "cuda":
        torch.set_float32_matmul_precision("high")  # TF32 matmuls (cuDNN convolutions use TF32 by default)

    # env setup; envpool cannot save game states, so a resumed run starts fresh games (other seeds)
    envs = make_env(args.env_id, args.num_envs, args.seed + start_iteration * args.num_envs)
    num_actions = int(envs.action_space.n)
    # channels_last: the same network, with faster convolutions on the CPU and the GPU (benchmark/README.md)
    agent = Agent(num_actions).to(device, memory_format=torch.channels_last)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=device.type == "cuda")
    if checkpoint:
        restore(checkpoint, agent, optimizer)
        print(
            f"resuming {run_dir} after iteration {start_iteration} ({checkpoint['global_step']} steps)",
            flush=True,
        )
    # SIGTERM (what Slurm sends before preemption) or SIGINT: checkpoint, then stop
    stop_signal = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop_signal.append(signum))

    # ALGO Logic: Storage setup. Frames stay uint8 (a quarter of float32's memory).
    T, N = args.num_steps, args.num_envs
    obs = torch.zeros((T, N) + envs.observation_space.shape, dtype=torch.uint8, device=device)
    actions = torch.zeros((T, N), dtype=torch.long, device=device)
    logprobs = torch.zeros((T, N), device=device)
    values = torch.zeros((T, N), device=device)
    # rewards and dones come from envpool on the host: gathered there, sent once per rollout
    rewards_np = np.zeros((T, N), dtype=np.float32)
    dones_np = np.zeros((T, N), dtype=np.float32)
    # frames reach the GPU through one pinned buffer, one asynchronous copy per step
    staging = (
        torch.empty((N,) + envs.observation_space.shape, dtype=torch.uint8, pin_memory=True)
        if device.type == "cuda"
        else None
    )
    # full-game statistics (all lives), kept on the host where envpool's infos are
    episode_returns = np.zeros(N, dtype=np.float64)
    episode_lengths = np.zeros(N, dtype=np.int64)
    last_return = float("nan")

    # TRY NOT TO MODIFY: start the game
    global_step = start_global_step = start_iteration * args.batch_size
    start_time = time.time()
    next_obs_np, _ = envs.reset()
    next_obs = frames_to_device(next_obs_np, device, staging)
    next_done_np = np.zeros(N, dtype=bool)
    timings = {"rollout_s": [], "update_s": [], "iteration_s": []}

    try:
        for iteration in range(start_iteration + 1, args.num_iterations + 1):
            rng = rng_state()  # the state a checkpoint of the previous iteration holds
            # Annealing the rate if instructed to do so.
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / args.num_iterations
                lrnow = frac * args.learning_rate
                optimizer.param_groups[0]["lr"] = lrnow

            iteration_start = time.perf_counter()
            with torch.inference_mode():
                for step in range(0, T):
                    if stop_signal:
                        break
                    global_step += N
                    obs[step] = next_obs
                    dones_np[step] = next_done_np

                    # ALGO LOGIC: action logic
                    action, logprob, _, value = agent.get_action_and_value(next_obs)
                    values[step] = value
                    actions[step] = action
                    logprobs[step] = logprob

                    # TRY NOT TO MODIFY: execute the game and log data.
                    next_obs_np, reward, terminations, truncations, info = envs.step(action.cpu().numpy())
                    next_done_np = np.logical_or(terminations, truncations)
                    rewards_np[step] = reward
                    next_obs = frames_to_device(next_obs_np, device, staging)

                    # a game is over when its last life is lost or it is truncated; returns are unclipped
                    episode_returns += info["reward"]
                    episode_lengths += 1
                    game_over = np.logical_or(info["terminated"].astype(bool), truncations)
                    if game_over.any():
                        for ret, length in zip(episode_returns[game_over], episode_lengths[game_over], strict=True):
                            writer.add_scalar("charts/episodic_return", ret, global_step)
                            writer.add_scalar("charts/episodic_length", length, global_step)
                        last_return = float(episode_returns[game_over][-1])
                        episode_returns[game_over] = 0
                        episode_lengths[game_over] = 0

            if stop_signal:  # the unfinished rollout is dropped; the checkpoint holds the last iteration
                save_checkpoint(checkpoint_path, agent, optimizer, args, iteration - 1, rng)
                print(
                    f"stopped by signal {stop_signal[0]}: checkpoint after iteration {iteration - 1} in "
                    f"{checkpoint_path}; continue with --resume {run_dir}",
                    flush=True,
                )
                sys.exit(128 + stop_signal[0])
            rollout_end = time.perf_counter()
            rewards = torch.as_tensor(rewards_np, device=device)
            dones = torch.as_tensor(dones_np, device=device)
            next_done = torch.as_tensor(next_done_np, dtype=torch.float32, device=device)

            # envpool resets a finished episode on the next `step`, ignoring that step's action and
            # returning reward 0: a step with dones[t] = 1 is no decision, so it is masked out of the
            # losses and of advantage normalisation (README, "Known differences").
            valid = 1.0 - dones

            # bootstrap value if not done
            with torch.no_grad():
                next_value = agent.get_value(next_obs)
                advantages = gae(rewards, values, dones, next_value, next_done, args.gamma, args.gae_lambda)
                returns = advantages + values

            # flatten the batch
            b_obs = obs.reshape((-1,) + envs.observation_space.shape)
            b_logprobs = logprobs.reshape(-1)
            b_actions = actions.reshape(-1)
            b_advantages = advantages.reshape(-1)
            b_returns = returns.reshape(-1)
            b_values = values.reshape(-1)
            b_valid = valid.reshape(-1)

            # Optimizing the policy and value network; statistics stay on the device until the end
            clipfracs = []
            for _epoch in range(args.update_epochs):
                b_inds = torch.randperm(args.batch_size, device=device)
                for start in range(0, args.batch_size, args.minibatch_size):
                    end = start + args.minibatch_size
                    mb_inds = b_inds[start:end]
                    mb_valid = b_valid[mb_inds]

                    _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb_inds], b_actions[mb_inds])
                    logratio = newlogprob - b_logprobs[mb_inds]
                    ratio = logratio.exp()

                    with torch.no_grad():
                        # calculate approx_kl http://joschu.net/blog/kl-approx.html
                        old_approx_kl = masked_mean(-logratio, mb_valid)
                        approx_kl = masked_mean((ratio - 1) - logratio, mb_valid)
                        clipfracs.append(masked_mean(((ratio - 1.0).abs() > args.clip_coef).float(), mb_valid))

                    mb_advantages = b_advantages[mb_inds]
                    if args.norm_adv:
                        mb_advantages = normalize_advantages(mb_advantages, mb_valid)

                    # Policy loss
                    pg_loss1 = -mb_advantages * ratio
                    pg_loss2 = -mb_advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
                    pg_loss = masked_mean(torch.max(pg_loss1, pg_loss2), mb_valid)

                    # Value loss
                    v_loss = value_loss(
                        newvalue,
                        b_values[mb_inds],
                        b_returns[mb_inds],
                        mb_valid,
                        args.clip_coef,
                        args.clip_vloss,
                    )

                    entropy_loss = masked_mean(entropy, mb_valid)
                    loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef

                    optimizer.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                    optimizer.step()

                if args.target_kl is not None and approx_kl.item() > args.target_kl:
                    break

            # one host transfer for all of this iteration's statistics
            stats = {
                "losses/value_loss": v_loss.detach(),
                "losses/policy_loss": pg_loss.detach(),
                "losses/entropy": entropy_loss.detach(),
                "losses/old_approx_kl": old_approx_kl,
                "losses/approx_kl": approx_kl,
                "losses/clipfrac": torch.stack(clipfracs).mean(),
                "losses/explained_variance": explained_variance(b_values, b_returns, b_valid),
            }
            for tag, x in zip(stats, torch.stack(list(stats.values())).tolist(), strict=True):
                writer.add_scalar(tag, x, global_step)
            iteration_end = time.perf_counter()
            timings["rollout_s"].append(rollout_end - iteration_start)
            timings["update_s"].append(iteration_end - rollout_end)
            timings["iteration_s"].append(iteration_end - iteration_start)
            sps = int((global_step - start_global_step) / (time.time() - start_time))
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/SPS", sps, global_step)
            writer.flush()
            print(
                f"iteration {iteration}/{args.num_iterations} global_step={global_step} SPS={sps} "
                f"last_return={last_return:.1f}",
                flush=True,
            )
            if args.checkpoint_every and iteration % args.checkpoint_every == 0 and iteration < args.num_iterations:
                save_checkpoint(checkpoint_path, agent, optimizer, args, iteration, rng_state())

        save_checkpoint(checkpoint_path, agent, optimizer, args, args.num_iterations, rng_state())
        if args.eval_episodes:
            report = evaluate(agent, args.env_id, args.eval_episodes, args.seed + 1_000_000, args.eval_greedy, device)
            write_evaluation(report | {"algorithm": ALGORITHM, "global_step": global_step}, run_dir, writer)
            print(
                f"eval: {args.eval_episodes} games, return {report['mean']:.1f} ± {report['std_err']:.1f}", flush=True
            )

        if args.save_model:
            model_path = os.path.join(run_dir, f"{args.exp_name}.cleanrl_model")
            save_agent(model_path, agent, args, num_actions)
            print(f"model saved to {model_path}", flush=True)
        save_checkpoint(checkpoint_path, agent, optimizer, args, args.num_iterations, rng_state(), finished=True)
    finally:
        envs.close()
        writer.close()
    return timings


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))

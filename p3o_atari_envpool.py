# P3O on envpool Atari: ppo_atari_envpool.py plus chapter 4 of "Preferential Proximal Policy Optimization in
# Reinforcement Learning" (Balasuntharam, Ontario Tech University; ICMLA 2023). README.md has the docs.
import contextlib
import ctypes
import difflib
import fcntl
import glob
import importlib.util
import json
import math
import os
import random
import shutil
import signal
import socket
import sys
import time
import uuid
from dataclasses import dataclass, field, fields, replace

import envpool
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions.categorical import Categorical

ALGORITHM = "p3o"  # written into checkpoints and model files, checked when they are loaded
ABLATION = None  # the change benchmark/p3o_ablation.py makes (it sets this), also written into checkpoints


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
    """the run folder under `runs/` (default: `{env_id}__{exp_name}__{seed}__{unix_time}`); one process at a time"""
    checkpoint_every: int = 10
    """write `runs/{run_name}/checkpoint.pt` every this many iterations (0: only at the end and on a signal)"""
    resume: str | None = None
    """continue the run of this checkpoint (a `checkpoint.pt` or its run folder) with its saved arguments; run flags
    (--save-model, --eval-episodes, --capture-video, --track, ...) keep the run's values unless given again"""
    auto_resume: bool = False
    """continue `runs/{run_name}` if it holds a checkpoint, else start it (for sweeps and requeued jobs)"""
    eval_episodes: int = 10
    """after training, play this many full games (each its own environment and seed) and log their returns"""
    eval_greedy: bool = False
    """evaluate with the most probable action instead of sampling from the policy"""
    capture_video: bool = False
    """write each evaluation game as an MP4 (colour, 210x160, 15 frames/s) to `runs/{run_name}/videos/`"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases (needs the `wandb` extra)"""
    wandb_project_name: str = "p3o-atari"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""

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
    ewma_alpha: float = 0.9
    """P3O: the EWMA weight of the newest state importance, in (0, 1] (thesis eq. 4.2, section 5.1.2)"""

    # to be filled in runtime (init=False: not flags)
    batch_size: int = field(init=False, default=0)
    """the batch size (computed in runtime: num_envs * num_steps)"""
    minibatch_size: int = field(init=False, default=0)
    """the mini-batch size (computed in runtime)"""
    num_iterations: int = field(init=False, default=0)
    """the number of iterations (computed in runtime)"""

    def __post_init__(self):
        self.batch_size = self.num_envs * self.num_steps
        self.minibatch_size = self.batch_size // max(self.num_minibatches, 1)
        self.num_iterations = self.total_timesteps // max(self.batch_size, 1)
        if not resuming(self):  # bad input fails where it is parsed; a resume's, with its checkpoint's arguments
            check_args(self)


def make_env(env_id: str, num_envs: int, seed: int, render_mode: str | None = None):
    """envpool Atari as in CleanRL: episodic life, clipped rewards, 4 stacked 84x84 grey frames.
    envpool seeds environment i with seed + i. `render_mode="rgb_array"` adds colour frames for videos."""
    kwargs = dict(episodic_life=True, reward_clip=True, seed=seed, render_mode=render_mode)
    return envpool.make(env_id, env_type="gymnasium", num_envs=num_envs, **kwargs)


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

    def get_value_and_probs(self, x):
        hidden = self.hidden(x)
        return self.critic(hidden).squeeze(-1), Categorical(logits=self.actor(hidden), validate_args=False).probs

    def get_action_and_value(self, x, action=None):
        hidden = self.hidden(x)
        probs = Categorical(logits=self.actor(hidden), validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs.entropy(), self.critic(hidden).squeeze(-1), probs.probs


def state_importance(probs, values):
    """SI(s) = Var_a[pi(a|s)] * |V(s)| (thesis eq. 4.1): the population variance of the action
    probability vector (probs [..., A]) times the magnitude of the value (values [...])."""
    return probs.var(dim=-1, unbiased=False) * values.abs()


def ewma(si, alpha):
    """The EWMA over time of state importance si [T+1, N], per environment (thesis eq. 4.2): x_0 = si_0,
    x_t = alpha * si_t + (1 - alpha) * x_{t-1}, written x_{t-1} + alpha * (si_t - x_{t-1}) so that a
    constant input stays exactly constant (no rounding noise for the min-max to blow up)."""
    x = si.clone()
    for t in range(1, si.shape[0]):
        x[t] = x[t - 1] + alpha * (si[t] - x[t - 1])
    return x


def compute_betas(si, alpha):
    """beta(s) from state importance si [T+1, N] (thesis section 4.1.1): per environment, the EWMA over
    time (eq. 4.2), then min-max over the T+1 states of the rollout. An environment whose smoothed SI
    is constant gets beta = 0. Elementwise operations only: no matmul, so no TF32 on CUDA."""
    x = ewma(si, alpha)
    low, high = x.min(dim=0).values, x.max(dim=0).values
    span = high - low
    return torch.where(span > 0, (x - low) / torch.where(span > 0, span, 1.0), 0.0)


def gbae(rewards, values, dones, next_value, next_done, betas, gamma, gae_lambda):
    """Generalized beta-advantage estimation (thesis eq. 4.3) over a [T, N] rollout: GAE whose trace is cut
    by (1 - beta(s_{t+1})) after important states; betas [T+1, N] are beta(s_0..s_T). Each step is one
    vectorised operation over the N environments."""
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
        advantages[t] = lastgaelam = delta + gamma * gae_lambda * nextnonterminal * (1.0 - betas[t + 1]) * lastgaelam
    return advantages


def masked_mean(x, valid):
    return (x * valid).sum() / valid.sum().clamp(min=1)


def normalize_advantages(advantages, valid):
    """Zero mean, unit (sample) standard deviation over the valid steps of a minibatch."""
    n = valid.sum()
    mean = (advantages * valid).sum() / n.clamp(min=1)
    std = (((advantages - mean) ** 2 * valid).sum() / (n - 1).clamp(min=1)).sqrt()
    return (advantages - mean) / (std + 1e-8)


def value_loss(newvalue, values, returns, betas, valid, clip_coef, clip_vloss):
    """P3O's value loss (thesis eq. 4.5): the beta-weighted mean of CleanRL's (clipped) squared error
    over the valid steps, without PPO's 0.5 factor (as in eq. 4.5 and the thesis's own code)."""
    v_loss_unclipped = (newvalue - returns) ** 2
    if clip_vloss:
        v_clipped = values + torch.clamp(newvalue - values, -clip_coef, clip_coef)
        v_loss_clipped = (v_clipped - returns) ** 2
        err = torch.max(v_loss_unclipped, v_loss_clipped)
    else:
        err = v_loss_unclipped
    return masked_mean(betas * err, valid)


def explained_variance(values, returns, valid):
    mask = valid.bool()
    y_pred, y_true = values[mask], returns[mask]
    var_y = y_true.var(unbiased=False)
    return torch.where(var_y == 0, torch.nan, 1 - (y_true - y_pred).var(unbiased=False) / var_y)


def main(args: Args, cli: list[str] | None = None) -> None:
    """Train. A resume parses `cli`, the command line `args` came from, again over the checkpoint's arguments."""
    with contextlib.ExitStack() as run:  # the run folder's lock, the writer, the envs: released however it ends
        args, run_dir, checkpoint = run.enter_context(open_run(args, cli))  # a resume's args are its checkpoint's
        if checkpoint and checkpoint["finished"]:
            print(f"{run_dir} already finished ({checkpoint['global_step']} steps); nothing to do.")
            return
        start_iteration = checkpoint["iteration"] if checkpoint else 0

        device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
        device_name = say_device(device, args.cuda)

        writer = run.enter_context(open_writer(args, run_dir, checkpoint, device_name))

        # TRY NOT TO MODIFY: seeding. envpool cannot save game states, so a resumed run plays fresh games with
        # fresh random numbers: it is seeded past the environment seeds the run has used so far.
        seed = args.seed + start_iteration * args.num_envs
        random.seed(seed)
        np.random.seed(seed)
        torch.manual_seed(seed)
        torch.backends.cudnn.deterministic = args.torch_deterministic
        if device.type == "cuda":
            torch.set_float32_matmul_precision("high")  # TF32 matmuls (cuDNN convolutions use TF32 by default)

        # env setup
        envs = run.enter_context(contextlib.closing(make_env(args.env_id, args.num_envs, seed)))
        # channels_last: the same network, with faster convolutions on the CPU and the GPU (benchmark/README.md)
        agent = Agent(int(envs.action_space.n)).to(device, memory_format=torch.channels_last)
        optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=device.type == "cuda")
        if checkpoint:
            agent.load_state_dict(checkpoint["model_state_dict"])
            optimizer.load_state_dict(checkpoint["optimizer_state_dict"])
            print(f"resuming {run_dir} after iteration {start_iteration} ({checkpoint['global_step']} steps)")
        stop_signal = catch_stop_signals()

        # ALGO Logic: Storage setup. Frames stay uint8 (a quarter of float32's memory); rewards and dones are
        # gathered on the host, where envpool returns them, and sent to the device once per rollout.
        T, N = args.num_steps, args.num_envs
        obs = torch.zeros((T, N) + envs.observation_space.shape, dtype=torch.uint8, device=device)
        actions = torch.zeros((T, N), dtype=torch.long, device=device)
        logprobs = torch.zeros((T, N), device=device)
        values = torch.zeros((T, N), device=device)
        rewards_np = np.zeros((T, N), dtype=np.float32)
        dones_np = np.zeros((T, N), dtype=np.float32)
        state_importances = torch.zeros((T + 1, N), device=device)  # SI(s_0) .. SI(s_T)
        # full-game statistics (all lives)
        episode_returns, episode_lengths, last_return = np.zeros(N), np.zeros(N, dtype=np.int64), float("nan")

        # TRY NOT TO MODIFY: start the game
        global_step = start_global_step = start_iteration * args.batch_size
        start_time = time.time()
        next_obs_np, _ = envs.reset()
        next_obs = torch.as_tensor(next_obs_np, device=device)
        next_done_np = np.zeros(N, dtype=bool)

        for iteration in range(start_iteration + 1, args.num_iterations + 1):
            # Annealing the rate if instructed to do so.
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / args.num_iterations
                lrnow = frac * args.learning_rate
                optimizer.param_groups[0]["lr"] = lrnow

            iteration_start = time.perf_counter()
            with torch.inference_mode():
                for step in range(0, T):
                    global_step += N
                    obs[step] = next_obs
                    dones_np[step] = next_done_np

                    # ALGO LOGIC: action logic
                    action, logprob, _, value, probs = agent.get_action_and_value(next_obs)
                    values[step] = value
                    state_importances[step] = state_importance(probs, value)
                    actions[step] = action
                    logprobs[step] = logprob

                    # TRY NOT TO MODIFY: execute the game and log data.
                    next_obs_np, reward, terminations, truncations, info = envs.step(action.cpu().numpy())
                    next_done_np = np.logical_or(terminations, truncations)
                    rewards_np[step] = reward
                    next_obs = torch.as_tensor(next_obs_np, device=device)

                    # a game is over when its last life is lost or it is truncated; returns are unclipped
                    episode_returns += info["reward"]
                    episode_lengths += 1
                    game_over = np.logical_or(info["terminated"].astype(bool), truncations)
                    for ret, length in zip(episode_returns[game_over], episode_lengths[game_over], strict=True):
                        writer.add_scalar("charts/episodic_return", ret, global_step)
                        writer.add_scalar("charts/episodic_length", length, global_step)
                        last_return = ret
                    episode_returns[game_over], episode_lengths[game_over] = 0, 0

            rollout_end = time.perf_counter()
            rewards = torch.as_tensor(rewards_np, device=device)
            dones = torch.as_tensor(dones_np, device=device)
            next_done = torch.as_tensor(next_done_np, dtype=torch.float32, device=device)
            # envpool resets a finished episode on the next `step`, ignoring that step's action and returning
            # reward 0: a step with dones[t] = 1 is no decision, so it is masked out of the losses, of advantage
            # normalisation and of the statistics (README, "Known differences").
            valid = 1.0 - dones

            # bootstrap value if not done
            with torch.no_grad():
                next_value, next_probs = agent.get_value_and_probs(next_obs)
                state_importances[T] = state_importance(next_probs, next_value)
                all_betas = compute_betas(state_importances, args.ewma_alpha)  # beta(s_0) .. beta(s_T)
                advantages = gbae(rewards, values, dones, next_value, next_done, all_betas, args.gamma, args.gae_lambda)
                betas = all_betas[:T]
                returns = advantages + values

            # flatten the batch
            b_obs = obs.reshape((-1,) + envs.observation_space.shape)
            b_logprobs = logprobs.reshape(-1)
            b_actions = actions.reshape(-1)
            b_advantages = advantages.reshape(-1)
            b_returns = returns.reshape(-1)
            b_values = values.reshape(-1)
            b_valid = valid.reshape(-1)
            b_betas = betas.reshape(-1)

            # Optimizing the policy and value network; statistics stay on the device until the end
            clipfracs = []
            finite = torch.ones((), dtype=torch.bool, device=device)  # every loss and gradient norm so far
            for _epoch in range(args.update_epochs):
                b_inds = torch.randperm(args.batch_size, device=device)
                for start in range(0, args.batch_size, args.minibatch_size):
                    end = start + args.minibatch_size
                    mb_inds = b_inds[start:end]
                    mb_valid = b_valid[mb_inds]

                    _, newlogprob, entropy, newvalue, _ = agent.get_action_and_value(b_obs[mb_inds], b_actions[mb_inds])
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
                    mb_values, mb_returns, mb_betas = b_values[mb_inds], b_returns[mb_inds], b_betas[mb_inds]
                    v_loss = value_loss(
                        newvalue, mb_values, mb_returns, mb_betas, mb_valid, args.clip_coef, args.clip_vloss
                    )

                    entropy_loss = masked_mean(entropy, mb_valid)
                    loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef

                    optimizer.zero_grad()
                    loss.backward()
                    grad_norm = nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                    optimizer.step()
                    finite &= torch.isfinite(loss) & torch.isfinite(grad_norm)

                if args.target_kl is not None and approx_kl.item() > args.target_kl:
                    break

            stop_if_not_finite(finite, agent, next_obs, iteration, run_dir)  # its check waits for the device
            update_end = time.perf_counter()

            # one host transfer for all of this iteration's statistics
            stats = {
                "losses/value_loss": v_loss.detach(),
                "losses/policy_loss": pg_loss.detach(),
                "losses/entropy": entropy_loss.detach(),
                "losses/old_approx_kl": old_approx_kl,
                "losses/approx_kl": approx_kl,
                "losses/clipfrac": torch.stack(clipfracs).mean(),
                "losses/explained_variance": explained_variance(b_values, b_returns, b_valid),
                "p3o/beta_mean": betas.mean(),
                "p3o/beta_std": betas.std(),
                "p3o/state_importance_mean": state_importances.mean(),
            }
            for tag, x in zip(stats, torch.stack(list(stats.values())).tolist(), strict=True):
                writer.add_scalar(tag, x, global_step)
            sps = int((global_step - start_global_step) / (time.time() - start_time))
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/SPS", sps, global_step)
            writer.add_scalar("charts/rollout_time", rollout_end - iteration_start, global_step)  # seconds (sps.py)
            writer.add_scalar("charts/update_time", update_end - rollout_end, global_step)
            writer.add_histogram("p3o/beta", betas, global_step)
            writer.flush()
            print(
                f"iteration {iteration}/{args.num_iterations} {global_step=} SPS={sps} {last_return=:.1f}", flush=True
            )
            checkpoint_or_stop(stop_signal, iteration, run_dir, agent, optimizer, args)

        finish(args, run_dir, agent, optimizer, writer, stop_signal, device, device_name)


# Run management: bad input, checkpoints and resume, evaluation, the allocator.


def check_args(args: Args) -> None:
    """Refuse bad input before any environment starts: one sentence, exit status 1."""
    a, flag = vars(args), {name: "--" + name.replace("_", "-") for name in vars(args)}
    bad = [
        f"{flag[n]} must be a finite number, got {v}."
        for n, v in a.items()
        if isinstance(v, float) and not math.isfinite(v)
    ]
    # zero or a negative clip coefficient, value coefficient or gradient norm leaves nothing to learn
    positive = ("total_timesteps", "num_envs", "num_steps", "num_minibatches", "update_epochs", "learning_rate")
    positive += ("clip_coef", "vf_coef", "max_grad_norm")
    bad += [f"{flag[n]} must be positive, got {a[n]}." for n in positive if not a[n] > 0]
    bad += [f"{flag[n]} must lie in [0, 1], got {a[n]}." for n in ("gamma", "gae_lambda") if not 0 <= a[n] <= 1]
    not_negative = ("checkpoint_every", "eval_episodes", "ent_coef")
    bad += [f"{flag[n]} must be 0 or more, got {a[n]}." for n in not_negative if not a[n] >= 0]
    if args.target_kl is not None and not args.target_kl > 0:
        bad.append(f"--target-kl must be positive, got {args.target_kl}.")
    bad += [f"--ewma-alpha must lie in (0, 1], got {args.ewma_alpha}."] if not 0 < args.ewma_alpha <= 1 else []
    for n in ("exp_name", "run_name"):
        parts = [] if a[n] is None else a[n].split("/")
        if parts and (
            any(p in ("", ".", "..") for p in parts)
            or "\\" in a[n]
            or "\0" in a[n]
            or (n == "exp_name" and len(parts) > 1)
        ):
            bad.append(f"{flag[n]} {a[n]!r} must be a plain relative name, so that the run stays under runs/.")
    # the model file is written after training: a name the file system cannot take must fail before it
    if args.exp_name and len(f"{args.exp_name}.cleanrl_model.tmp".encode()) > 255:
        bad.append(f"--exp-name is {len(args.exp_name.encode())} bytes long, too long for the model file's name.")
    if args.auto_resume and not args.run_name:
        bad.append("--auto-resume needs --run-name, the run folder it continues.")
    if args.capture_video and not args.eval_episodes:
        bad.append("--capture-video records the evaluation games, but --eval-episodes is 0.")
    # a leftover ./wandb/ folder of an offline run is found as an empty namespace package (no origin), not wandb
    if args.track and getattr(importlib.util.find_spec("wandb"), "origin", None) is None:
        bad.append("--track needs wandb: run with `uv run --extra wandb ...` (or `pip install wandb`).")
    batch = args.num_envs * args.num_steps
    if not bad and batch % args.num_minibatches:
        bad.append(
            f"the batch (--num-envs * --num-steps = {batch}) does not divide into {args.num_minibatches} minibatches."
        )
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if not bad and batch * 4 * 84 * 84 > memory:  # the rollout's uint8 frames, its largest buffer
        bad.append(
            f"the rollout's frames (--num-envs * --num-steps = {batch} x 4 x 84 x 84 bytes, {batch * 28224 / 2**30:.1f}"
            f" GiB) would not fit this machine's {memory / 2**30:.1f} GiB of memory."
        )
    if not bad and args.total_timesteps < batch:
        bad.append(f"--total-timesteps {args.total_timesteps} is less than one batch ({batch}): no update would run.")
    if not bad:
        # envpool takes seeds below 2^31 (numpy none below 0); the run derives seed + i for env i of a rollout
        # resumed at any iteration, and seed + 1,000,000 + i for evaluation game i
        derived = max((args.total_timesteps // batch + 1) * args.num_envs, 1_000_000 + args.eval_episodes) - 1
        if derived > 2**31 - 1:
            bad.append(
                f"the run would derive seeds up to --seed + {derived} (evaluation games and iterations x envs),"
                " past envpool's 2^31 - 1: fewer --eval-episodes or --total-timesteps."
            )
        elif not 0 <= args.seed <= 2**31 - 1 - derived:
            bad.append(
                f"--seed must lie in [0, {2**31 - 1 - derived}] (envpool seeds stay below 2^31, and this run"
                f" derives seeds up to --seed + {derived}), got {args.seed}."
            )
    atari = [i for i in envpool.list_all_envs() if envpool.registration.registry.specs[i][0] == "envpool.atari"]
    if args.env_id not in atari:
        known = args.env_id in envpool.list_all_envs()
        close = [] if known else difflib.get_close_matches(args.env_id, atari, n=3, cutoff=0.5)
        what = "an envpool environment but not an Atari game" if known else "not an envpool environment"
        hint = f"Did you mean {', '.join(close)}?" if close else "Atari ids look like Breakout-v5."
        bad.append(f"--env-id {args.env_id} is {what}. {hint}")
    if bad:
        sys.exit(f"error: {bad[0]}")


FORMAT = "atari-envpool/2"  # checkpoints and saved models: the agent, its arguments and more
# flags that may change when a run is resumed (they keep the run's values unless given again); the other
# arguments are the experiment's, from its checkpoint
RUN_FLAGS = {"cuda", "save_model", "checkpoint_every", "resume", "auto_resume", "eval_episodes", "eval_greedy"}
RUN_FLAGS |= {"capture_video", "track", "wandb_project_name", "wandb_entity"}
INIT = [f.name for f in fields(Args) if f.init]  # the arguments; the others are computed from them


def save(path: str, agent: Agent, args: Args, **extra) -> None:
    """The agent, its arguments and `extra`, written atomically (a temporary file, then a rename): a failed write
    (a full disk) stops the run with a sentence and leaves the previous file as it was."""
    state = {
        "format": FORMAT,
        "algorithm": ALGORITHM,
        "ablation": ABLATION,
        "args": vars(args),
        "model_state_dict": agent.state_dict(),
    }
    try:
        torch.save(state | extra, f"{path}.tmp")
        os.replace(f"{path}.tmp", path)
    except (OSError, RuntimeError) as e:
        if os.path.exists(f"{path}.tmp"):
            os.remove(f"{path}.tmp")
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e).strip().splitlines()[0]
        free = shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free  # torch's own errors rarely say
        before = "is as it was before" if os.path.exists(path) else "was not written"
        sys.exit(
            f"error: writing {path} failed ({why}; {free / 2**20:.0f} MB free there), so it {before}; make room"
            f" and continue with --resume {os.path.dirname(path)}."
        )


def save_checkpoint(path, agent, optimizer, args, iteration, finished=False) -> None:
    progress = dict(iteration=iteration, global_step=iteration * args.batch_size, finished=finished)
    save(path, agent, args, optimizer_state_dict=optimizer.state_dict(), **progress)


@contextlib.contextmanager
def open_run(args: Args, cli: list[str] | None = None):
    """The run folder, held by this process alone until the `with` ends, as (args, run_dir, checkpoint): a resume's
    checkpoint and arguments (read_checkpoint), or a new run's clean folder and no checkpoint."""
    keep_freed_memory()
    args = replace(args)  # made again: a value set after Args(...) is checked and the sizes computed from it
    resume = f"runs/{args.run_name}" if resuming(args) and args.resume is None else args.resume
    path = None
    if resume is None:
        run_dir = f"runs/{args.run_name or f'{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}'}"
    else:
        path = os.path.join(resume, "checkpoint.pt") if os.path.isdir(resume) else resume
        if not os.path.isfile(path):
            sys.exit(f"error: --resume {path}: there is no checkpoint there.")
        run_dir = os.path.dirname(path)
    with hold(run_dir):
        if path is None:
            start_clean(run_dir)
            yield args, run_dir, None
        else:
            args, checkpoint = read_checkpoint(path, resume, args, cli)
            yield args, run_dir, checkpoint


def resuming(args: Args) -> bool:
    """Whether this call continues a run: --resume, or --auto-resume of a run folder that holds a checkpoint."""
    auto = args.auto_resume and args.run_name and os.path.exists(f"runs/{args.run_name}/checkpoint.pt")
    return args.resume is not None or bool(auto)


def start_clean(run_dir: str) -> None:
    """A new run's folder: never another run's, and without what a start killed before its first checkpoint
    left there (its points would be logged again)."""
    if os.path.exists(f"{run_dir}/checkpoint.pt"):
        sys.exit(f"error: {run_dir} already holds a run; continue it with --resume {run_dir}.")
    if os.path.exists(f"{run_dir}/eval.json"):
        sys.exit(f"error: {run_dir} holds an evaluation but no checkpoint; give this run another --run-name.")
    stale = glob.glob(f"{run_dir}/events.out.tfevents.*") + glob.glob(f"{run_dir}/checkpoint.pt.tmp")
    if finished_logs([path for path in stale if ".tfevents." in path]):  # never delete what a finished run wrote
        sys.exit(
            f"error: {run_dir} holds the logs of a finished run but no checkpoint; give this run another --run-name."
        )
    for path in stale:
        os.remove(path)
    if stale:
        print(
            f"{run_dir} held no checkpoint: removed what an earlier start left ({len(stale)} file(s)); starting afresh"
        )


def finished_logs(paths: list[str]) -> bool:
    """Whether event files hold a finished run (its checkpoint deleted): an evaluation, or the last iteration
    by the sizes it logged with its hyperparameters. A start killed before its first checkpoint has neither."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    sizes, steps = {}, set()
    for path in paths:
        try:
            for event in EventFileLoader(path).Load():
                for value in event.summary.value:
                    if value.tag.startswith("eval/"):
                        return True
                    if value.tag == "hyperparameters/text_summary":
                        rows = value.tensor.string_val[0].decode().splitlines()
                        sizes |= dict(row.strip("|").split("|", 1) for row in rows if row.count("|") == 3)
                    elif value.tag == "charts/SPS":
                        steps.add(event.step)
        except Exception:  # a file cut short: what it held up to there counts
            continue
    try:
        return int(sizes["num_iterations"]) * int(sizes["batch_size"]) in steps
    except (KeyError, ValueError):
        return False


def read_checkpoint(path: str, resume: str, args: Args, cli: list[str] | None) -> tuple[Args, dict]:
    """A resume's checkpoint and arguments: the experiment's from the checkpoint, refusing one given here that
    contradicts them; the run flags keep the run's values unless given again."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        sys.exit(f"error: --resume {path} is not a readable checkpoint; it may be truncated or corrupt ({e!r:.150}).")
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != FORMAT or "iteration" not in checkpoint:
        sys.exit(f"error: --resume {path} is not a checkpoint written by these scripts.")
    if checkpoint["algorithm"] != ALGORITHM:
        algo = checkpoint["algorithm"]
        sys.exit(f"error: --resume {path} is a {algo} checkpoint; resume it with {algo}_atari_envpool.py.")
    if checkpoint.get("ablation") != ABLATION:  # a run of benchmark/p3o_ablation.py and plain P3O's do not mix
        made = (
            f"benchmark/p3o_ablation.py {checkpoint['ablation']}"
            if checkpoint.get("ablation")
            else "p3o_atari_envpool.py"
        )
        sys.exit(f"error: --resume {path} is a run of {made}; resume it with that script.")
    # the command line again, over the checkpoint's arguments (what it leaves out keeps them); in-process, every
    # value of `args` is given. resume=path: the saved arguments alone are not checked (the merged ones are, below)
    saved = {k: v for k, v in checkpoint["args"].items() if k in INIT}
    if cli is not None:
        import tyro

        parsed = tyro.cli(Args, args=cli, default=Args(**saved | {"resume": path}))
    given = {name: getattr(parsed if cli is not None else args, name) for name in INIT}
    experiment = [name for name in INIT if name not in RUN_FLAGS and name in saved]
    differ = [name for name in experiment if given[name] != saved[name]]
    if differ:
        was = ", ".join(f"--{n.replace('_', '-')} {saved[n]!r} (now {given[n]!r})" for n in differ)
        sys.exit(f"error: --resume {path} was started with {was}; resume it with the same arguments.")
    args = Args(**given | {"resume": resume, "auto_resume": args.auto_resume})
    check_args(args)  # the run flags it keeps together with those given now
    return args, checkpoint


@contextlib.contextmanager
def hold(run_dir: str):
    """Make the run folder and lock it for this process until the `with` ends (an OS lock, released however the
    process ends, so a killed run never blocks its own resume); a second process given the same folder is refused."""
    try:
        os.makedirs(run_dir, exist_ok=True)
        lock = open(os.path.join(run_dir, ".lock"), "a+")
    except OSError as e:
        sys.exit(f"error: cannot create the run folder {run_dir} ({e.strerror}).")
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.seek(0)
            holder = lock.read().strip() or "another process"
            sys.exit(
                f"error: {run_dir} is in use by {holder}; one run folder takes one process (wait, or choose"
                " another --run-name)."
            )
        lock.seek(0)
        lock.truncate()
        lock.write(f"process {os.getpid()} on {socket.gethostname()}")
        lock.flush()
        yield


def say_device(device: torch.device, cuda: bool) -> str:
    """Print the device the run trains on, warning when --cuda is on but torch finds no GPU; returns its name."""
    name = f"cuda ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "cpu"
    if cuda and device.type == "cpu":
        build = f"built for CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        print(
            f"warning: --cuda is on but torch {torch.__version__} ({build}) finds no usable GPU, so this run trains on"
            " the CPU (README.md, 'GPU and driver'; --no-cuda silences this).",
            file=sys.stderr,
        )
    print(f"device: {name}", flush=True)
    return name


def open_writer(args: Args, run_dir: str, checkpoint: dict | None, device_name: str):
    """CleanRL's TensorBoard writer (and W&B with --track). A new run logs its hyperparameters; a resume purges
    the points the killed run logged after its checkpoint, so none is duplicated."""
    from torch.utils.tensorboard import SummaryWriter

    if args.track:  # W&B mirrors the TensorBoard events; started before the writer, which it patches
        start_wandb(args, run_dir, resuming=checkpoint is not None)
    purge_step = checkpoint["iteration"] * args.batch_size + 1 if checkpoint else None
    writer = SummaryWriter(run_dir, purge_step=purge_step)
    if checkpoint is None:
        table = "\n".join([f"|{key}|{value}|" for key, value in (vars(args) | {"device": device_name}).items()])
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


def start_wandb(args: Args, run_dir: str, resuming: bool):
    """W&B as CleanRL starts it. The run id is kept in the run folder, so a resumed run continues its W&B run."""
    import wandb

    os.makedirs(run_dir, exist_ok=True)
    id_path = os.path.join(run_dir, "wandb_id")
    run_id = open(id_path).read() if resuming and os.path.exists(id_path) else uuid.uuid4().hex
    with open(id_path, "w") as f:
        f.write(run_id)
    try:
        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=os.path.basename(run_dir),
            save_code=True,
            id=run_id,
            resume="allow",
        )
    except Exception as e:  # most often no login: offline mode needs none
        why = (str(e).strip().splitlines() or [type(e).__name__])[0]
        sys.exit(
            f"error: W&B did not start ({why}); log in with `wandb login`, or set WANDB_MODE=offline to log"
            " locally and `wandb sync` later."
        )
    return wandb


def catch_stop_signals() -> list[int]:
    """SIGTERM (what Slurm sends before a preemption or the time limit) or SIGINT: noted in the list returned, so
    that the run finishes its iteration, checkpoints and stops (checkpoint_or_stop)."""
    stop_signal = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop_signal.append(signum))
    return stop_signal


def stop_if_not_finite(finite, agent, next_obs, iteration, run_dir) -> None:
    """Stop before a checkpoint can take weights the agent cannot act with: a non-finite loss or gradient norm
    (`finite`), or weights blown up but finite whose outputs on the next states are not."""
    with torch.no_grad():
        hidden = agent.hidden(next_obs)
        finite &= torch.isfinite(agent.actor(hidden)).all() & torch.isfinite(agent.critic(hidden)).all()
    if not finite.item():
        path = os.path.join(run_dir, "checkpoint.pt")
        kept = f"{path} keeps the last weights it could act with" if os.path.exists(path) else "nothing was saved"
        sys.exit(
            f"error: the loss or the policy became non-finite (nan or inf) in iteration {iteration}, so the run"
            f" stopped and {kept} (a lower --learning-rate or --max-grad-norm may help)."
        )


def checkpoint_or_stop(stop_signal, iteration, run_dir, agent, optimizer, args) -> None:
    """The periodic checkpoint; after a stop signal, a checkpoint of this iteration and the exit."""
    if stop_signal or (args.checkpoint_every and iteration % args.checkpoint_every == 0):
        save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), agent, optimizer, args, iteration)
    if stop_signal:
        print(f"stopped by signal {stop_signal[0]} after iteration {iteration}; continue with --resume {run_dir}")
        sys.exit(128 + stop_signal[0])


def finish(args, run_dir, agent, optimizer, writer, stop_signal, device, device_name) -> None:
    """After the last iteration: a checkpoint, the evaluation (logged once, even when this stage is redone), the
    model file, then the checkpoint marked finished. A failure or a signal here keeps the first checkpoint, from
    which --resume redoes only this stage."""
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    save_checkpoint(checkpoint_path, agent, optimizer, args, args.num_iterations)
    for sig in (signal.SIGTERM, signal.SIGINT):  # from here a signal stops the stage at once
        signal.signal(sig, stop_final_stage)
    try:
        if stop_signal:  # it came after the last iteration's check
            raise Stopped(stop_signal[0])
        evaluated = os.path.exists(f"{run_dir}/eval.json")
        if evaluated:
            print(f"{run_dir}/eval.json: this run's evaluation was logged before; not played again")
        if args.eval_episodes and not evaluated:
            print(f"evaluating: {args.eval_episodes} full games", flush=True)
            videos = f"{run_dir}/videos" if args.capture_video else None
            seed = args.seed + 1_000_000
            report = evaluate(agent, args.env_id, args.eval_episodes, seed, args.eval_greedy, device, videos)
            global_step = args.num_iterations * args.batch_size
            made = {"algorithm": ALGORITHM, "global_step": global_step, "device": device_name}
            write_evaluation(report | made, run_dir, writer)
            print(f"eval: {args.eval_episodes} games, return {report['mean']:.1f} ± {report['std_err']:.1f}")
            if args.track and videos:
                import wandb

                wandb.log({f"videos/eval-game{i}": wandb.Video(path) for i, path in enumerate(report["videos"])})
        if args.save_model:
            model_path = f"{run_dir}/{args.exp_name}.cleanrl_model"
            save(model_path, agent, args, env_id=args.env_id, num_actions=agent.actor.out_features)
    except Stopped as stop:
        print(f"stopped by signal {stop.signum} in the final stage; continue with --resume {run_dir}")
        sys.exit(128 + stop.signum)
    except Exception as e:  # after a whole training: one sentence, and the checkpoint to redo this stage from
        sys.exit(
            f"error: the evaluation or model saving after training failed ({type(e).__name__}: {e}); the trained"
            f" agent is kept in {checkpoint_path}: run again with --resume {run_dir} to redo them."
        )
    save_checkpoint(checkpoint_path, agent, optimizer, args, args.num_iterations, finished=True)


def evaluate(agent, env_id, episodes, seed, greedy, device, video_dir=None) -> dict:
    """Play `episodes` full games (all lives), game i in its own environment seeded `seed + i`, with
    actions sampled from the policy (or its most probable action when `greedy`); unclipped returns.
    The mean's standard error uses the population standard deviation, as the thesis's table 5.1.
    With `video_dir`, game i is also written to `video_dir/eval-game{i}.mp4`: the colour frame after each
    of its agent steps, at 15 frames/s (the emulator's 60 Hz over envpool's frame skip of 4)."""
    envs = make_env(env_id, episodes, seed, render_mode="rgb_array" if video_dir else None)
    paths = [f"{video_dir}/eval-game{i}.mp4" for i in range(episodes)] if video_dir else []
    if video_dir:
        import imageio_ffmpeg  # only here: nothing else needs it (the GPU bundle carries it without its ffmpeg)

        os.makedirs(video_dir, exist_ok=True)
    writers = [imageio_ffmpeg.write_frames(path, (160, 210), fps=15, macro_block_size=1) for path in paths]
    for writer in writers:
        writer.send(None)  # start the encoder
    obs_np, _ = envs.reset()
    returns, lengths, playing = np.zeros(episodes), np.zeros(episodes, dtype=np.int64), np.ones(episodes, dtype=bool)
    with torch.inference_mode():
        while playing.any():
            logits = agent.actor(agent.hidden(torch.as_tensor(obs_np, device=device)))
            action = logits.argmax(-1) if greedy else Categorical(logits=logits, validate_args=False).sample()
            obs_np, _, terminations, truncations, info = envs.step(action.cpu().numpy())
            if writers:  # the colour frame of each game still playing
                for game, frame in zip(np.flatnonzero(playing), envs.render(np.flatnonzero(playing)), strict=True):
                    writers[game].send(np.ascontiguousarray(frame))
            returns += info["reward"] * playing
            lengths += playing
            playing &= ~np.logical_or(info["terminated"].astype(bool), truncations)
    envs.close()
    for writer in writers:
        writer.close()
    games = {"seeds": [seed + i for i in range(episodes)], "returns": returns.tolist(), "lengths": lengths.tolist()}
    summary = {"mean": float(returns.mean()), "std_err": float(returns.std() / np.sqrt(episodes))}
    return {"env_id": env_id, "greedy": greedy} | games | summary | ({"videos": paths} if paths else {})


def write_evaluation(report: dict, run_dir: str, writer) -> None:
    """Each game's return under `eval/episodic_return` (step = game index), then `eval.json`, written whole (a
    temporary file, renamed): it is the record that the evaluation was logged, which a redone last stage reads."""
    for game, ret in enumerate(report["returns"]):
        writer.add_scalar("eval/episodic_return", ret, game)
    writer.flush()
    path = os.path.join(run_dir, "eval.json")
    with open(f"{path}.tmp", "w") as f:
        json.dump(report, f, indent=2)
    os.replace(f"{path}.tmp", path)


class Stopped(BaseException):
    """A signal in the final stage (not an Exception: the stage's error handling must not take it for a failure)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def stop_final_stage(signum, frame):
    raise Stopped(signum)


def keep_freed_memory() -> None:
    """glibc keeps freed blocks under 64 MB for reuse instead of unmapping them and faulting them back in for
    the next CPU minibatch: 1.17x faster CPU training, the same numbers and peak memory (benchmark/README.md).
    `MALLOC_MMAP_THRESHOLD_` would do the same, but only when set before python starts."""
    try:
        libc = ctypes.CDLL("libc.so.6") if sys.platform.startswith("linux") else None
    except OSError:  # not glibc (e.g. musl): keep its defaults
        libc = None
    if libc is not None:
        libc.mallopt(-3, 64 << 20)  # M_MMAP_THRESHOLD: blocks under 64 MB come from the reusable heap
        libc.mallopt(-1, 2**31 - 1)  # M_TRIM_THRESHOLD: do not shrink the heap after each free


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args), sys.argv[1:])

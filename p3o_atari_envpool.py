# P3O on envpool Atari: ppo_atari_envpool.py plus chapter 4 of "Preferential Proximal Policy Optimization in
# Reinforcement Learning" (Balasuntharam, Ontario Tech University; ICMLA 2023). README.md has the docs.
import contextlib
import ctypes
import difflib
import fcntl
import importlib.util
import io
import os
import random
import signal
import sys
import time
from dataclasses import dataclass, field, fields, replace

import envpool
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
import tyro
from torch.distributions.categorical import Categorical

ALGORITHM = "p3o"  # written into checkpoints and model files, checked when they are loaded


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (the run folder and the saved model are named after it)"""
    seed: int = 1
    """seed of the experiment: python, numpy, torch and envpool are seeded with it"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    # Run flags: where and how the run goes (a resume keeps the run's unless they are given again), not what it is
    cuda: bool = True
    """if toggled, cuda is used when available (the script falls back to the CPU without a GPU)"""
    save_model: bool = False
    """whether to save the trained agent to `runs/{run_name}/{exp_name}.cleanrl_model`"""
    run_name: str | None = None
    """the run folder under `runs/` (default: `{env_id}__{exp_name}__{seed}__{unix_time}`); one process at a time"""
    checkpoint_every: int = 10
    """write `runs/{run_name}/checkpoint.pt` every this many iterations (0: at the start, the end and a signal)"""
    resume: str | None = None
    """continue the run of this checkpoint (or run folder), with its arguments (run flags: unless given again)"""
    auto_resume: bool = False
    """continue `runs/{run_name}` if it holds a checkpoint, else start it (for sweeps and requeued jobs)"""
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
        # bad input stops here, before any environment starts: the flag and its value in one sentence, exit status 1
        if self.resume is None:  # a resume's arguments: once merged with its checkpoint's (open_run)
            for problem in problems(self):
                sys.exit(f"error: {problem}")


def make_env(env_id: str, num_envs: int, seed: int, render_mode: str | None = None):
    """envpool Atari as in CleanRL: episodic life, clipped rewards, 4 stacked 84x84 grey frames.
    envpool seeds environment i with seed + i. `render_mode="rgb_array"` adds colour frames (for videos)."""
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


def main(args: Args, cli: list[str] | None = None, run: contextlib.ExitStack | None = None) -> None:
    """Train. A resumed run takes its checkpoint's arguments, with `cli` (the command line) parsed over them."""
    if run is None:  # `run` holds the run folder's lock, the writer and the envs: released however main ends
        with contextlib.ExitStack() as run:
            return main(args, cli, run)
    args, run_dir, checkpoint, stop = open_run(run, args, cli)  # `stop`: the signals that ask the run to stop
    if checkpoint and checkpoint["finished"]:
        return say(f"{run_dir} already finished ({checkpoint['global_step']} steps); nothing to do.")
    start_iteration = checkpoint["iteration"] if checkpoint else 0
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    device_name = say_device(device, args.cuda)

    # TRY NOT TO MODIFY: seeding. envpool cannot save game states, so a resumed run plays fresh games with
    # fresh random numbers: it is seeded past the environment seeds the run has used so far.
    seed = args.seed + start_iteration * args.num_envs
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_float32_matmul_precision("high" if device.type == "cuda" else "highest")  # TF32 matmuls on a GPU

    # env setup
    envs = run.enter_context(contextlib.closing(make_env(args.env_id, args.num_envs, seed)))
    # channels_last: the same network, with faster convolutions on the CPU and the GPU (benchmark/README.md)
    agent = Agent(int(envs.action_space.n)).to(device, memory_format=torch.channels_last)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=device.type == "cuda")
    if checkpoint:
        agent.load_state_dict(checkpoint["model_state_dict"])
        optimizer.load_state_dict(checkpoint["optimizer_state_dict"])
        say(f"resuming {run_dir} after iteration {start_iteration} ({checkpoint['global_step']} steps)")
    writer = run.enter_context(open_writer(args, run_dir, checkpoint, device_name, agent, optimizer))

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
    episode_returns = np.zeros(N)  # full-game statistics (all lives)
    episode_lengths = np.zeros(N, dtype=np.int64)
    last_return = float("nan")

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
        for step in range(0, T):
            global_step += N
            obs[step] = next_obs
            dones_np[step] = next_done_np

            # ALGO LOGIC: action logic
            with torch.inference_mode():
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
            episode_returns[game_over] = 0
            episode_lengths[game_over] = 0

        rollout_end = time.perf_counter()
        rewards = torch.as_tensor(rewards_np, device=device)
        dones = torch.as_tensor(dones_np, device=device)
        next_done = torch.as_tensor(next_done_np, dtype=torch.float32, device=device)
        # dones[t] = 1: envpool reset that game at step t, ignoring the action and giving reward 0, so the step is no
        # decision: `valid` leaves it out of the losses, the advantage normalisation and the statistics (README).
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

        writer.add_scalar("losses/value_loss", v_loss.item(), global_step)
        writer.add_scalar("losses/policy_loss", pg_loss.item(), global_step)
        writer.add_scalar("losses/entropy", entropy_loss.item(), global_step)
        writer.add_scalar("losses/old_approx_kl", old_approx_kl.item(), global_step)
        writer.add_scalar("losses/approx_kl", approx_kl.item(), global_step)
        writer.add_scalar("losses/clipfrac", torch.stack(clipfracs).mean().item(), global_step)
        writer.add_scalar("losses/explained_variance", explained_variance(b_values, b_returns, b_valid), global_step)
        writer.add_scalar("p3o/beta_mean", betas.mean().item(), global_step)
        writer.add_scalar("p3o/beta_std", betas.std(correction=int(betas.numel() > 1)).item(), global_step)  # one β: 0
        writer.add_scalar("p3o/state_importance_mean", state_importances.mean().item(), global_step)
        sps = int((global_step - start_global_step) / (time.time() - start_time))
        writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
        writer.add_scalar("charts/SPS", sps, global_step)
        writer.add_scalar("charts/rollout_time", rollout_end - iteration_start, global_step)  # seconds (sps.py)
        writer.add_scalar("charts/update_time", update_end - rollout_end, global_step)
        writer.add_histogram("p3o/beta", betas, global_step)
        writer.flush()
        say(f"iteration {iteration}/{args.num_iterations} {global_step=} SPS={sps} {last_return=:.1f}")
        # a checkpoint every --checkpoint-every iterations and after the last; one, and the exit, after a stop signal
        if stop or iteration == args.num_iterations or args.checkpoint_every and iteration % args.checkpoint_every == 0:
            save(f"{run_dir}/checkpoint.pt", agent, args, optimizer, iteration)
        if stop:
            say(f"stopped by signal {stop[0]} after iteration {iteration}; continue with --resume {run_dir}")
            sys.exit(128 + stop[0])

    # the model file (evaluate.py plays it, or the checkpoint), then the checkpoint marked finished
    if args.save_model:
        save(f"{run_dir}/{args.exp_name}.cleanrl_model", agent, args)
    save(f"{run_dir}/checkpoint.pt", agent, args, optimizer, args.num_iterations, finished=True)


# Run management: bad input, the run folder, checkpoints and resume, signals.

FORMAT = "atari-envpool/2"  # checkpoints and saved models: the agent, its arguments and more
INIT = [f.name for f in fields(Args) if f.init]  # the arguments; a resume may change the run flags, not the others
RUN_FLAGS = set(INIT[INIT.index("cuda") : INIT.index("env_id")])
POSITIVE = ["total_timesteps", "num_envs", "num_steps", "num_minibatches", "update_epochs", "learning_rate"]
RULES = [  # flags, the test each value must pass, what it must be (no clipping, value weight or gradient norm learns)
    (INIT, lambda v: not isinstance(v, float) or abs(v) < float("inf"), "be a finite number"),
    (POSITIVE + ["clip_coef", "vf_coef", "max_grad_norm", "target_kl"], lambda v: v is None or v > 0, "be positive"),
    (["gamma", "gae_lambda"], lambda v: 0 <= v <= 1, "lie in [0, 1]"),
    (["ewma_alpha"], lambda v: 0 < v <= 1, "lie in (0, 1]"),
    (["checkpoint_every", "ent_coef"], lambda v: v >= 0, "be 0 or more"),
]


def problems(a: Args):  # each rule the arguments break, in order: a rule may assume that the ones before it hold
    for names, test, what in RULES:
        yield from (f"--{n.replace('_', '-')} must {what}, got {v}." for n in names if not test(v := getattr(a, n)))
    for n, name in (("exp", a.exp_name), ("run", a.run_name)):
        parts = [] if name is None else name.split("/")
        if any(p in ("", ".", "..") or "\\" in p or "\0" in p for p in parts) or n == "exp" and len(parts) > 1:
            yield f"--{n}-name {name!r} must be a plain relative name, so that the run stays under runs/."
    if len(f"{a.exp_name}.cleanrl_model.tmp".encode()) > 255:  # the model file is written after training
        yield f"--exp-name is {len(a.exp_name.encode())} bytes long, too long for the model file's name."
    if a.auto_resume and not a.run_name:
        yield "--auto-resume needs --run-name, the run folder it continues."
    # a leftover ./wandb/ folder of an offline run is found as an empty namespace package (no origin), not wandb
    if a.track and getattr(importlib.util.find_spec("wandb"), "origin", None) is None:
        yield "--track needs wandb: run with `uv run --extra wandb ...` (or `pip install wandb`)."
    batch, memory = a.num_envs * a.num_steps, os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if batch % a.num_minibatches:
        yield f"the batch (--num-envs * --num-steps = {batch}) does not divide into {a.num_minibatches} minibatches."
    if batch * 4 * 84 * 84 > memory:  # the rollout's uint8 frames, its largest buffer
        yield f"the rollout's frames (--num-envs * --num-steps = {batch} x 4 x 84 x 84 bytes) won't fit in memory."
    if a.total_timesteps < batch:
        yield f"--total-timesteps {a.total_timesteps} is less than one batch ({batch}): no update would run."
    highest = 2**31 - (a.total_timesteps // batch + 1) * a.num_envs  # a resume at iteration i seeds seed + i * N + j
    if not 0 <= a.seed <= highest:
        yield f"--seed must lie in [0, {highest}] (the run's envpool seeds must stay below 2^31), got {a.seed}."
    atari = [i for i, spec in envpool.registration.registry.specs.items() if spec[0] == "envpool.atari"]
    if a.env_id not in atari:
        close = difflib.get_close_matches(a.env_id, atari, n=3, cutoff=0.7) or ["an id like Breakout-v5"]
        yield f"--env-id {a.env_id} is not an envpool Atari game; did you mean {', '.join(close)}?"


def open_run(run: contextlib.ExitStack, args: Args, cli: list[str] | None):
    """(args, run_dir, checkpoint, stop) until `run` closes: the folder under an OS lock (gone however a process ends),
    a resume's checkpoint and arguments (the command line parsed again over them), and the stop signals received."""
    with contextlib.suppress(OSError):  # glibc keeps freed blocks under 64 MB for the next CPU minibatch instead of
        ctypes.CDLL("libc.so.6").mallopt(-3, 64 << 20)  # unmapping them: 1.17x faster training (benchmark/README.md)
        ctypes.CDLL("libc.so.6").mallopt(-1, 2**31 - 1)  # and never shrinks the heap after a free
    auto = args.auto_resume and os.path.isfile(f"runs/{args.run_name}/checkpoint.pt")
    how, resume = ("--resume", args.resume) if args.resume else ("--auto-resume", auto and f"runs/{args.run_name}")
    args = replace(args)  # made again: a value set after Args(...) is checked, and the sizes computed from it
    path = resume and (os.path.join(resume, "checkpoint.pt") if os.path.isdir(resume) else resume)
    if path and not os.path.isfile(path):
        sys.exit(f"error: {how} {path}: there is no checkpoint there.")
    name = args.run_name or f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir = os.path.dirname(path) if path else f"runs/{name}"
    try:
        os.makedirs(run_dir, exist_ok=True)
        lock = run.enter_context(open(f"{run_dir}/.lock", "a+"))
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        why = "one run folder takes one process (wait, or choose another --run-name)"
        sys.exit(f"error: {run_dir} is in use by {open(lock.name).read()}; {why}.")
    except OSError as e:
        sys.exit(f"error: cannot create the run folder {run_dir} ({e.strerror}).")
    lock.truncate(0)
    print(f"process {os.getpid()} on {os.uname().nodename}", file=lock, end="", flush=True)
    stop = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        run.callback(signal.signal, sig, signal.signal(sig, lambda signum, frame: stop.append(signum)))
    if not path:
        if "checkpoint.pt" in os.listdir(run_dir) or any(f.startswith("events.out") for f in os.listdir(run_dir)):
            sys.exit(f"error: {run_dir} holds a run already; continue it with --resume, or use another --run-name.")
        return args, run_dir, None, stop
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
        if checkpoint.get("format") != FORMAT or "iteration" not in checkpoint:
            raise ValueError("written by these scripts, but not as a checkpoint")
    except Exception:  # unreadable, or not a checkpoint of these scripts
        sys.exit(f"error: {how} {path} is not a checkpoint these scripts can read (damaged, or another kind of file).")
    if checkpoint["algorithm"] != ALGORITHM:
        sys.exit(f"error: {how} {path} is a {checkpoint['algorithm']} run's checkpoint; resume it with its own script.")
    saved = {k: v for k, v in checkpoint["args"].items() if k in INIT}
    if cli is not None:
        args = tyro.cli(Args, args=cli, default=Args(**saved | {"resume": path}))
    given = {name: getattr(args, name) for name in INIT}
    differ = [name for name in INIT if name not in RUN_FLAGS and name in saved and given[name] != saved[name]]
    if differ:
        was = ", ".join(f"--{n.replace('_', '-')} {saved[n]!r} (now {given[n]!r})" for n in differ)
        sys.exit(f"error: {how} {path} was started with {was}; resume it with the same arguments.")
    return Args(**given | {"resume": None}), run_dir, checkpoint, stop  # checked, with the run flags given now


def save(path: str, agent: Agent, args: Args, optimizer=None, iteration=0, finished=False) -> None:
    """The agent and its arguments; with the optimizer, a checkpoint (progress, and the random state evaluate.py plays
    the run's own games with). Written whole or not at all: a failed write leaves the old file as it was, and stops."""
    state = dict(format=FORMAT, algorithm=ALGORITHM, args=vars(args), model_state_dict=agent.state_dict())
    state |= dict(env_id=args.env_id, num_actions=agent.actor.out_features)
    if optimizer:
        state |= dict(optimizer_state_dict=optimizer.state_dict(), rng_state=torch.get_rng_state())
        state |= dict(iteration=iteration, global_step=iteration * args.batch_size, finished=finished)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    try:
        with open(f"{path}.tmp", "wb") as f:
            f.write(buffer.getbuffer())
        os.replace(f"{path}.tmp", path)
    except OSError as e:
        with contextlib.suppress(OSError):
            os.remove(f"{path}.tmp")
        then = f"continue with --resume {os.path.dirname(path)}" if iteration or not optimizer else "run it again"
        sys.exit(f"error: writing {path} failed ({e.strerror or e}), so it is as it was; make room and {then}.")


def say(text: str) -> None:
    """print that outlives its reader (`| tee` ended by Ctrl-C): the rest goes to /dev/null, the run on."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def say_device(device: torch.device, cuda: bool) -> str:  # and a warning when --cuda finds no GPU
    name = f"cuda ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "cpu"
    if cuda and device.type == "cpu":
        build = f"built for CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        warn = f"warning: --cuda is on but torch {torch.__version__} ({build}) finds no usable GPU, so this run trains"
        print(f"{warn} on the CPU (README.md, 'GPU and driver'; --no-cuda silences this).", file=sys.stderr)
    say(f"device: {name}")
    return name


def open_writer(args: Args, run_dir: str, checkpoint: dict | None, device_name: str, agent, optimizer):
    """CleanRL's writer (W&B with --track), after a new run's first checkpoint: a run with events has a checkpoint."""
    from torch.utils.tensorboard import SummaryWriter

    if args.track:  # W&B mirrors the TensorBoard events: started before the writer, which it patches
        wandb = importlib.import_module("wandb")  # one W&B run however often the run resumes: its id stays here
        id_path = f"{run_dir}/wandb_id"
        run_id = open(id_path).read() if checkpoint and os.path.exists(id_path) else os.urandom(16).hex()
        open(id_path, "w").write(run_id)
        config = dict(project=args.wandb_project_name, entity=args.wandb_entity, config=vars(args), id=run_id)
        try:
            wandb.init(**config, name=os.path.basename(run_dir), sync_tensorboard=True, save_code=True, resume="allow")
        except Exception as e:  # most often no login: offline mode needs none
            why = (str(e).strip().splitlines() or [type(e).__name__])[0]
            sys.exit(f"error: W&B did not start ({why}); log in with `wandb login`, or set WANDB_MODE=offline.")
    if not checkpoint:
        save(f"{run_dir}/checkpoint.pt", agent, args, optimizer, iteration=0)
    # a resume purges the points the stopped run logged after its checkpoint (TensorBoard leaves out what follows)
    writer = SummaryWriter(run_dir, purge_step=checkpoint["iteration"] * args.batch_size + 1 if checkpoint else None)
    if not checkpoint:
        table = "\n".join([f"|{key}|{value}|" for key, value in (vars(args) | {"device": device_name}).items()])
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


def stop_if_not_finite(finite, agent, next_obs, iteration, run_dir) -> None:  # before a checkpoint takes such weights
    with torch.no_grad():
        hidden = agent.hidden(next_obs)
        finite &= torch.isfinite(agent.actor(hidden)).all() & torch.isfinite(agent.critic(hidden)).all()
    if not finite.item():
        why = f"the loss or the policy became non-finite (nan or inf) in iteration {iteration}, so the run stopped"
        kept = f"{run_dir}/checkpoint.pt keeps the last weights it could act with"
        sys.exit(f"error: {why} and {kept} (a lower --learning-rate or --max-grad-norm may help).")


if __name__ == "__main__":
    main(tyro.cli(Args), sys.argv[1:])

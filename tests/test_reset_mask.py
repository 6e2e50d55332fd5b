"""envpool's next-step reset, on a real envpool game: the steps the scripts mask out (dones[t] = 1,
the episode ended just before obs[t]) are exactly the steps whose action envpool ignores."""

import numpy as np
import pytest

import ppo_atari_envpool as ppo
from helpers import scalars

STEPS, N = 700, 3


def play(env_id, action_for):
    """Step the env as the training loop does and record dones[t], rewards[t], info per step."""
    envs = ppo.make_env(env_id, N, seed=7)
    next_obs, _ = envs.reset()
    next_done = np.zeros(N, dtype=bool)
    dones, rewards, elapsed, obs = [], [], [], []
    for t in range(STEPS):
        dones.append(next_done)  # as the scripts: dones[step] = next_done
        obs.append(next_obs)
        next_obs, reward, terminations, truncations, info = envs.step(action_for(t, next_done))
        next_done = np.logical_or(terminations, truncations)
        rewards.append(reward)
        elapsed.append(info["elapsed_step"].copy())
    envs.close()
    return np.array(dones), np.array(rewards), np.array(elapsed), np.array(obs)


@pytest.mark.parametrize("env_id", ["Breakout-v5", "Qbert-v5"])
def test_masked_steps_are_exactly_the_reset_steps(env_id):
    num_actions = ppo.make_env(env_id, 1, seed=0).action_space.n
    rng = np.random.default_rng(0)
    random_actions = rng.integers(0, num_actions, size=(STEPS, N)).astype(np.int32)
    dones, rewards, elapsed, obs = play(env_id, lambda t, done: random_actions[t])
    valid = 1.0 - dones  # the scripts' mask
    masked = valid == 0
    assert masked.sum() >= 5, "the test needs several episode ends to say anything"

    # a real step advances envpool's step counter by one; the reset step does not (it keeps the
    # count after a lost life and restarts it at 0 after a finished game)
    previous = np.vstack([np.zeros((1, N), dtype=elapsed.dtype), elapsed[:-1]])
    real_step = elapsed == previous + 1
    np.testing.assert_array_equal(masked, ~real_step)
    assert (rewards[masked] == 0).all()

    # change every masked step's action: nothing at all changes
    other = (random_actions + 1) % num_actions
    dones2, rewards2, _, obs2 = play(env_id, lambda t, done: np.where(done, other[t], random_actions[t]))
    np.testing.assert_array_equal(dones2, dones)
    np.testing.assert_array_equal(rewards2, rewards)
    np.testing.assert_array_equal(obs2, obs)

    # change the unmasked steps' actions instead: the games change
    _, _, _, obs3 = play(env_id, lambda t, done: np.where(done, random_actions[t], other[t]))
    assert not np.array_equal(obs3, obs)


class RecordingEnvs:
    """envpool's environments, remembering which ones the last step ended (their next step is a reset)."""

    def __init__(self, envs):
        self.envs, self.ended = envs, None

    def __getattr__(self, name):
        return getattr(self.envs, name)

    def reset(self):
        obs, info = self.envs.reset()
        self.ended = np.zeros(len(obs), dtype=bool)
        return obs, info

    def step(self, action):
        out = self.envs.step(action)
        self.ended = np.logical_or(out[2], out[3])
        return out


def train_logging(module, change_masked_steps, tmp_path, monkeypatch, shift_values=False):
    """A short real training run; with `change_masked_steps`, the action the agent stores at every reset
    step (and its log-probability) is replaced by another action, and with `shift_values` the value it
    stores there too. Returns the logged scalars and the number of changed steps."""
    import torch

    made, flipped = [], []
    make_env, original = module.make_env, module.Agent.get_action_and_value

    def recording_make_env(*args, **kwargs):
        made.append(RecordingEnvs(make_env(*args, **kwargs)))
        return made[-1]

    def get_action_and_value(self, x, action=None):
        out = original(self, x, action)
        if action is None and change_masked_steps:
            ended = torch.as_tensor(made[-1].ended)
            flipped.append(int(ended.sum()))
            # the same forward pass for another action: no random numbers are drawn
            out = original(self, x, torch.where(ended, (out[0] + 1) % self.actor.out_features, out[0]))
            if shift_values:
                out = (*out[:3], torch.where(ended, out[3] + 5.0, out[3]), *out[4:])
        return out

    monkeypatch.setattr(module, "make_env", recording_make_env)
    monkeypatch.setattr(module.Agent, "get_action_and_value", get_action_and_value)
    monkeypatch.chdir(tmp_path)
    name = f"changed{int(change_masked_steps)}"
    args = module.Args(env_id="Breakout-v5", num_envs=4, num_steps=128, num_minibatches=2, update_epochs=2)
    args.total_timesteps, args.seed, args.run_name = 1024, 7, name
    module.main(args)
    return scalars(tmp_path / "runs" / name), sum(flipped)


# PPO: the stored action and value of a reset step both change. P3O: only the action, because the value of
# that state (the last frame of the finished life) enters its state importance and so every beta of the
# environment's min-max window, as the thesis's P3O has it.
@pytest.mark.parametrize("script,shift_values", [("ppo", True), ("p3o", False)])
def test_the_update_and_its_statistics_ignore_the_masked_steps(script, shift_values, tmp_path, monkeypatch):
    import importlib

    module = importlib.import_module(f"{script}_atari_envpool")
    plain, _ = train_logging(module, False, tmp_path, monkeypatch)
    changed, flips = train_logging(module, True, tmp_path, monkeypatch, shift_values)
    assert flips >= 10, "the test needs reset steps to say anything"
    # envpool ignores those actions, so the games are the same; the losses, the KL and clip statistics and
    # the explained variance are computed only over the other steps, so they are the same to the last bit
    # (advantages at other steps never read a reset step's value: the episode boundary cuts the trace)
    for timing in ("charts/SPS", "charts/rollout_time", "charts/update_time"):  # wall-clock, not computed
        assert changed.pop(timing) and plain.pop(timing)
    assert changed == plain

"""envpool's next-step reset, on a real envpool game: the steps the scripts mask out (dones[t] = 1,
the episode ended just before obs[t]) are exactly the steps whose action envpool ignores."""

import numpy as np
import pytest

import ppo_atari_envpool as ppo

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

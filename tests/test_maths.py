"""The maths of both scripts, pinned on small hand-checkable inputs (thesis chapter 4)."""

import numpy as np
import pytest
import torch

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo

GAMMA, LAM = 0.99, 0.95


def rollout(T=7, N=3, seed=0, done_at=((3, 0), (5, 2))):
    g = torch.Generator().manual_seed(seed)
    rewards = torch.randn(T, N, generator=g, dtype=torch.float64)
    values = torch.randn(T, N, generator=g, dtype=torch.float64)
    dones = torch.zeros(T, N, dtype=torch.float64)
    for t, n in done_at:
        dones[t, n] = 1.0
    next_value = torch.randn(N, generator=g, dtype=torch.float64)
    next_done = torch.tensor([0.0, 1.0, 0.0][:N], dtype=torch.float64)
    betas = torch.rand(T, N, generator=g, dtype=torch.float64)
    next_beta = torch.rand(N, generator=g, dtype=torch.float64)
    return rewards, values, dones, next_value, next_done, betas, next_beta


def gbae(rewards, values, dones, next_value, next_done, betas, next_beta, gamma, lam):
    """p3o.gbae with beta(s_0..s_{T-1}) and beta(s_T) given apart, as the references below take them."""
    return p3o.gbae(rewards, values, dones, next_value, next_done, torch.cat([betas, next_beta[None]]), gamma, lam)


def deltas(rewards, values, dones, next_value, next_done, gamma=GAMMA):
    next_values = torch.cat([values[1:], next_value[None]])
    next_nonterminal = 1.0 - torch.cat([dones[1:], next_done[None]])
    return rewards + gamma * next_values * next_nonterminal - values


def beta_return_reference(rewards, values, dones, next_value, next_done, betas, next_beta, gamma):
    """G^b_t = r_t + gamma (1 - d_{t+1}) [b_{t+1} V_{t+1} + (1 - b_{t+1}) G^b_{t+1}], G^b_T = V(s_T)
    (thesis appendix A.1), written as plain Python loops over floats."""
    T, N = rewards.shape
    out = np.zeros((T, N))
    for n in range(N):
        g_next = float(next_value[n])
        for t in reversed(range(T)):
            if t == T - 1:
                v1, b1, d1 = float(next_value[n]), float(next_beta[n]), float(next_done[n])
            else:
                v1, b1, d1 = float(values[t + 1, n]), float(betas[t + 1, n]), float(dones[t + 1, n])
            g = float(rewards[t, n]) + gamma * (1 - d1) * (b1 * v1 + (1 - b1) * g_next)
            out[t, n] = g
            g_next = g
    return torch.from_numpy(out)


# --- GAE / GBAE -------------------------------------------------------------------------------


def test_gae_matches_a_hand_computed_two_step_example():
    rewards = torch.tensor([[1.0], [2.0]])
    values = torch.tensor([[0.5], [1.0]])
    dones = torch.zeros(2, 1)
    adv = ppo.gae(rewards, values, dones, torch.tensor([3.0]), torch.tensor([0.0]), 0.9, 0.5)
    d1 = 2.0 + 0.9 * 3.0 - 1.0
    d0 = 1.0 + 0.9 * 1.0 - 0.5
    torch.testing.assert_close(adv, torch.tensor([[d0 + 0.9 * 0.5 * d1], [d1]]))


def test_gbae_with_beta_zero_is_gae():
    r, v, d, nv, nd, _, _ = rollout()
    zeros = torch.zeros_like(r)
    got = gbae(r, v, d, nv, nd, zeros, torch.zeros_like(nv), GAMMA, LAM)
    torch.testing.assert_close(got, ppo.gae(r, v, d, nv, nd, GAMMA, LAM), rtol=0, atol=0)


def test_gbae_with_lambda_zero_is_the_td_error():
    r, v, d, nv, nd, b, nb = rollout()
    torch.testing.assert_close(gbae(r, v, d, nv, nd, b, nb, GAMMA, 0.0), deltas(r, v, d, nv, nd))


def test_gbae_with_beta_one_is_the_td_error():
    r, v, d, nv, nd, b, nb = rollout()
    got = gbae(r, v, d, nv, nd, torch.ones_like(b), torch.ones_like(nb), GAMMA, LAM)
    torch.testing.assert_close(got, deltas(r, v, d, nv, nd))


def test_gbae_with_lambda_one_is_the_beta_return_minus_value():
    r, v, d, nv, nd, b, nb = rollout(T=9, N=3, seed=3)
    got = gbae(r, v, d, nv, nd, b, nb, GAMMA, 1.0)
    expected = beta_return_reference(r, v, d, nv, nd, b, nb, GAMMA) - v
    torch.testing.assert_close(got, expected)


def test_gbae_recursion_on_a_hand_computed_example():
    # one env, T = 2: A_1 = delta_1; A_0 = delta_0 + gamma lambda (1 - beta_1) A_1
    r = torch.tensor([[1.0], [0.0]])
    v = torch.tensor([[0.0], [2.0]])
    got = gbae(
        r, v, torch.zeros(2, 1), torch.tensor([1.0]), torch.tensor([0.0]),
        torch.tensor([[0.3], [0.25]]), torch.tensor([0.9]), 0.5, 0.8,
    )  # fmt: skip
    d1 = 0.0 + 0.5 * 1.0 - 2.0
    d0 = 1.0 + 0.5 * 2.0 - 0.0
    torch.testing.assert_close(got, torch.tensor([[d0 + 0.5 * 0.8 * 0.75 * d1], [d1]]))


@pytest.mark.parametrize("fn", ["gae", "gbae"])
def test_episode_end_cuts_the_trace(fn):
    r, v, d, nv, nd, b, nb = rollout(T=8, N=1, done_at=((4, 0),))

    def adv(rewards, values):
        if fn == "gae":
            return ppo.gae(rewards, values, d, nv, nd, GAMMA, LAM)
        return gbae(rewards, values, d, nv, nd, b, nb, GAMMA, LAM)

    base = adv(r, v)
    r2, v2 = r.clone(), v.clone()
    r2[4:] += 100.0  # everything from the new episode on
    v2[4:] -= 50.0
    changed = adv(r2, v2)
    torch.testing.assert_close(changed[:4], base[:4], rtol=0, atol=0)
    assert not torch.allclose(changed[4:], base[4:])
    # the last step of the finished episode does not bootstrap: its advantage is r - V
    torch.testing.assert_close(base[3], r[3] - v[3])


# --- state importance and beta ----------------------------------------------------------------


def test_state_importance_is_population_variance_of_probabilities_times_abs_value():
    probs = torch.tensor([[0.7, 0.2, 0.1], [0.25, 0.25, 0.5]], dtype=torch.float64)
    values = torch.tensor([-2.0, 3.0], dtype=torch.float64)
    expected = torch.tensor(
        [np.var([0.7, 0.2, 0.1]) * 2.0, np.var([0.25, 0.25, 0.5]) * 3.0], dtype=torch.float64
    )  # np.var divides by the number of actions
    torch.testing.assert_close(p3o.state_importance(probs, values), expected)
    # by hand for the first row: mean 1/3, squared deviations summed / 3
    by_hand = ((0.7 - 1 / 3) ** 2 + (0.2 - 1 / 3) ** 2 + (0.1 - 1 / 3) ** 2) / 3 * 2.0
    assert p3o.state_importance(probs, values)[0].item() == pytest.approx(by_hand, rel=1e-12)


def test_state_importance_of_a_uniform_policy_is_zero():
    probs = torch.full((5, 4, 6), 1 / 6)
    values = torch.randn(5, 4) * 100
    assert torch.equal(p3o.state_importance(probs, values), torch.zeros(5, 4))


def test_state_importance_keeps_leading_shape():
    probs = torch.softmax(torch.randn(3, 2, 9), -1)
    assert p3o.state_importance(probs, torch.randn(3, 2)).shape == (3, 2)


def ewma_reference(si, alpha):
    x = si.clone()
    for t in range(1, si.shape[0]):
        x[t] = alpha * si[t] + (1 - alpha) * x[t - 1]
    return x


def test_betas_closed_form_on_a_small_input():
    si = torch.tensor([[1.0], [0.0], [0.0], [4.0]], dtype=torch.float64)
    # EWMA with alpha 0.5: 1, 0.5, 0.25, 2.125; min-max over the four values
    x = torch.tensor([1.0, 0.5, 0.25, 2.125], dtype=torch.float64)
    expected = ((x - 0.25) / (2.125 - 0.25))[:, None]
    torch.testing.assert_close(p3o.compute_betas(si, 0.5), expected)


@pytest.mark.parametrize("alpha", [0.6, 0.75, 0.9, 1.0])
def test_betas_equal_the_recursive_ewma_then_min_max_per_environment(alpha):
    si = torch.rand(33, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 3
    x = ewma_reference(si, alpha)
    lo, hi = x.min(0).values, x.max(0).values
    torch.testing.assert_close(p3o.compute_betas(si, alpha), (x - lo) / (hi - lo))


def test_alpha_one_is_plain_min_max():
    si = torch.tensor([[2.0, 0.0], [4.0, 1.0], [3.0, 3.0]])
    torch.testing.assert_close(p3o.compute_betas(si, 1.0), torch.tensor([[0.0, 0.0], [1.0, 1 / 3], [0.5, 1.0]]))


def test_float32_betas_span_exactly_0_to_1_and_match_a_float64_reference():
    # SI over nine orders of magnitude across environments, in the scripts' float32
    scale = torch.logspace(-6, 3, 8, dtype=torch.float64)
    si = torch.rand(257, 8, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * scale
    betas = p3o.compute_betas(si.float(), 0.9)
    assert betas.dtype == torch.float32 and betas.shape == si.shape
    assert torch.equal(betas.min(0).values, torch.zeros(8)) and torch.equal(betas.max(0).values, torch.ones(8))
    x = ewma_reference(si.float().double(), 0.9)  # the same float32 inputs, smoothed in float64
    reference = (x - x.min(0).values) / (x.max(0).values - x.min(0).values)
    torch.testing.assert_close(betas.double(), reference, rtol=0, atol=1e-5)


def test_betas_are_computed_per_environment():
    si = torch.rand(17, 3, generator=torch.Generator().manual_seed(4))
    alone = p3o.compute_betas(si[:, 1:2], 0.9)
    si_scaled = si.clone()
    si_scaled[:, 0] *= 1000
    si_scaled[:, 2] = 0
    torch.testing.assert_close(p3o.compute_betas(si_scaled, 0.9)[:, 1:2], alone)


@pytest.mark.parametrize("value", [0.0, 1e-30, 0.37, 123456.0])
def test_constant_state_importance_gives_beta_zero(value):
    si = torch.full((257, 4), value)
    betas = p3o.compute_betas(si, 0.9)
    assert torch.equal(betas, torch.zeros_like(si))


def test_rounding_noise_span_gives_finite_betas_in_unit_interval():
    base = torch.full((65, 3), 0.1)
    noise = torch.zeros_like(base)
    noise[::7, 0] = torch.finfo(torch.float32).eps * 0.1  # a span of one ulp
    noise[::5, 1] = torch.finfo(torch.float32).tiny  # a subnormal-sized span
    noise[3, 2] = 1e-45  # the smallest subnormal on a zero column
    si = base + noise
    si[:, 2] = noise[:, 2]
    betas = p3o.compute_betas(si, 0.9)
    assert torch.isfinite(betas).all()
    assert betas.min() >= 0 and betas.max() <= 1


# --- losses --------------------------------------------------------------------------------------


@pytest.mark.parametrize("clip_vloss", [True, False])
def test_p3o_value_loss_with_beta_one_is_twice_ppo(clip_vloss):
    g = torch.Generator().manual_seed(5)
    newvalue, values, returns = (torch.randn(64, generator=g) for _ in range(3))
    valid = (torch.rand(64, generator=g) > 0.2).float()
    ones = torch.ones(64)
    ppo_loss = ppo.value_loss(newvalue, values, returns, valid, 0.1, clip_vloss)
    p3o_loss = p3o.value_loss(newvalue, values, returns, ones, valid, 0.1, clip_vloss)
    torch.testing.assert_close(p3o_loss, 2 * ppo_loss)


def test_p3o_value_loss_weights_each_step_by_beta():
    newvalue = torch.tensor([1.0, 2.0, 0.0])
    returns = torch.tensor([0.0, 0.0, 0.0])
    betas = torch.tensor([0.5, 0.25, 1.0])
    valid = torch.tensor([1.0, 1.0, 0.0])
    loss = p3o.value_loss(newvalue, newvalue, returns, betas, valid, 0.1, False)
    assert loss.item() == pytest.approx((0.5 * 1.0 + 0.25 * 4.0) / 2)


def test_value_loss_clipping_takes_the_larger_error():
    # new value moved from 0 to 1 but the clipped one only to 0.1; returns at 1: clipped error wins
    loss = ppo.value_loss(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([1.0]), torch.ones(1), 0.1, True)
    assert loss.item() == pytest.approx(0.5 * 0.9**2)


@pytest.mark.parametrize("module", [ppo, p3o])
def test_advantage_normalisation_ignores_masked_steps(module):
    adv = torch.tensor([1.0, 2.0, 3.0, 1000.0])
    valid = torch.tensor([1.0, 1.0, 1.0, 0.0])
    out = module.normalize_advantages(adv, valid)
    torch.testing.assert_close(out[:3], torch.tensor([-1.0, 0.0, 1.0]), atol=1e-6, rtol=0)
    adv2 = adv.clone()
    adv2[3] = -5.0
    torch.testing.assert_close(module.normalize_advantages(adv2, valid)[:3], out[:3])


def test_masked_mean_ignores_masked_steps_and_survives_an_empty_mask():
    x = torch.tensor([1.0, 3.0, 100.0])
    assert ppo.masked_mean(x, torch.tensor([1.0, 1.0, 0.0])).item() == 2.0
    assert ppo.masked_mean(x, torch.zeros(3)).item() == 0.0


def test_importing_the_scripts_starts_nothing(monkeypatch):
    import importlib

    import envpool

    def forbidden(*args, **kwargs):
        raise AssertionError("importing a training script must not create environments")

    monkeypatch.setattr(envpool, "make", forbidden)
    monkeypatch.setattr("sys.argv", ["x", "--not-a-flag"])
    for module in (ppo, p3o):
        importlib.reload(module)

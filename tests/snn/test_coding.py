"""Spike coding (SPEC §4): population encoder statistics, replayable hash sampler, raster input, decoders."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sb3_spikeplastic.snn.coding import (
    EXP_FLOOR,
    ContinuousDecoder,
    CounterBernoulli,
    DiscreteDecoder,
    PopulationEncoder,
    RasterInput,
    advance_keys,
    initial_keys,
)

LOW, HIGH = [-3.0, -1.0, 0.0], [3.0, 2.0, 5.0]


def place_cell_probabilities_np(x, low, high, pop=50, beta=15.0, p_min=0.05):
    """SPEC §4: p = clip(exp(-beta (Omega - x)^2), theta_min, 1), Omega evenly spaced over [low, high], x clipped
    to [low, high] first."""
    out = []
    for xi, lo, hi in zip(x, low, high):
        omega = np.linspace(lo, hi, pop)
        xi = min(max(xi, lo), hi)
        out.append(np.clip(np.exp(-beta * (omega - xi) ** 2), p_min, 1.0))
    return np.concatenate(out)


def test_encoder_probabilities_match_formula():
    enc = PopulationEncoder(LOW, HIGH)
    assert enc.n_neurons == 150
    rng = np.random.default_rng(0)
    x = np.stack([rng.uniform(lo - 0.5, hi + 0.5, 8) for lo, hi in zip(LOW, HIGH)], 1)
    got = enc.probabilities(torch.tensor(x, dtype=torch.float32)).numpy()
    expected = np.stack([place_cell_probabilities_np(xi, LOW, HIGH) for xi in x])
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("p_min", [0.05, 0.0], ids=["floor", "no-floor"])
def test_encoder_exponent_floor_leaves_the_probabilities_bit_identical(p_min):
    """With the paper's beta = 15 over [-3, 3], more than a third of the cells' exponents lie below -87 (where
    exp underflows); the floored exponent gives exactly the unfloored formula's probabilities. Without a floor
    probability the tiny values are the formula's own."""
    enc = PopulationEncoder([-3.0] * 4, [3.0] * 4, pop_size=50, beta=15.0, p_min=p_min)
    x = torch.tensor([[-3.0, 3.0, 0.0, 1.234], [2.9, -0.7, -2.2, 0.01]])
    exponent = -enc.beta * (enc.centres - x.unsqueeze(-1)) ** 2
    assert bool((exponent < EXP_FLOOR).float().mean() > 0.3)
    direct = torch.exp(exponent).clamp(p_min, 1.0).flatten(1)
    assert torch.equal(enc.probabilities(x), direct)
    if p_min == 0.0:
        assert bool((enc.probabilities(x) < math.exp(EXP_FLOOR)).any())  # not floored: smaller values remain


def test_encoder_clips_to_its_bounds_so_out_of_range_values_fire_the_edge_cell():
    enc = PopulationEncoder(LOW, HIGH, pop_size=10)
    p = enc.probabilities(torch.tensor([[-7.0, 2.5, 50.0]]))
    assert torch.equal(p, enc.probabilities(torch.tensor([[-3.0, 2.0, 5.0]])))  # the same as at the bounds
    assert (p.view(3, 10)[:, [0, -1, -1]].diagonal() == 1.0).all()  # the edge cells fire at every step


def test_encoder_indices_encode_the_chosen_dimensions_only():
    enc = PopulationEncoder(LOW, HIGH, pop_size=10, indices=[2, 0])
    assert enc.n_neurons == 20
    x = torch.tensor([[1.2, 99.0, 3.3], [-0.4, -99.0, 0.1]])  # dimension 1 is ignored whatever its value
    expected = np.stack(
        [place_cell_probabilities_np([xi[2], xi[0]], [LOW[2], LOW[0]], [HIGH[2], HIGH[0]], pop=10) for xi in x.numpy()]
    )
    np.testing.assert_allclose(enc.probabilities(x).numpy(), expected, rtol=1e-5, atol=1e-6)
    for bad in ([3], [0, 0], []):
        with pytest.raises(ValueError, match="encoder indices"):
            PopulationEncoder(LOW, HIGH, indices=bad)


def test_encoder_empirical_firing_probability_within_binomial_tolerance():
    enc = PopulationEncoder(LOW, HIGH)
    # a centre exactly (p = 1), between centres, and near an edge
    x = np.array([-3 + 6 * 10 / 49, 0.37, 4.9])
    p = place_cell_probabilities_np(x, LOW, HIGH)
    B, T, env_steps = 200, 50, 3
    keys = initial_keys(B, seed=3)
    obs = torch.tensor(np.tile(x, (B, 1)), dtype=torch.float32)
    counts = torch.zeros(enc.n_neurons, dtype=torch.float64)
    for _ in range(env_steps):  # different keys per environment and per step
        counts += enc(obs, keys, T).sum((0, 1)).double()
        keys = advance_keys(keys)
    n = B * T * env_steps  # 30,000 Bernoulli samples per cell
    emp = counts.numpy() / n
    # 5 binomial standard errors (+ 1/n for cells with p at 0 or 1)
    tol = 5 * np.sqrt(p * (1 - p) / n) + 1.0 / n
    bad = np.abs(emp - p) > tol
    assert not bad.any(), f"cells {np.flatnonzero(bad)}: empirical {emp[bad]} vs p {p[bad]} (tol {tol[bad]})"
    assert p.max() > 0.999 and p.min() == pytest.approx(0.05)


def test_encoder_replay_is_bit_exact_and_keys_matter():
    enc = PopulationEncoder(LOW, HIGH)
    g = torch.Generator().manual_seed(1)
    B, T = 6, 50
    obs = torch.rand(B, 3, generator=g) * 4 - 1
    keys = initial_keys(B, seed=7)
    s1 = enc(obs, keys, T)
    # same obs and key: same spikes, also from a fresh encoder (empty hash cache) and in another batch order
    assert torch.equal(enc(obs, keys, T), s1)
    assert torch.equal(PopulationEncoder(LOW, HIGH)(obs, keys, T), s1)
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    assert torch.equal(enc(obs[perm], keys[perm], T), s1[perm])
    assert torch.equal(enc(obs[2:4], keys[2:4], T), s1[2:4])
    # other keys (another seed, or the next step's keys) give different spikes
    for other in (initial_keys(B, seed=8), advance_keys(keys)):
        s2 = enc(obs, other, T)
        assert not torch.equal(s1, s2)
        assert (s1 != s2).float().mean() > 0.05
    # environments of one batch have distinct streams
    assert len(set(keys.tolist())) == B
    same_obs = obs[:1].expand(B, 3)
    s3 = enc(same_obs, keys, T)
    assert all(not torch.equal(s3[0], s3[b]) for b in range(1, B))


def test_hash_uniforms_look_uniform():
    B, T, n = 64, 128, 128
    keys = initial_keys(B, seed=11)
    u = CounterBernoulli().uniform(keys, T, n).double()
    N = u.numel()  # 1,048,576
    assert u.min() >= 0 and u.max() < 1
    assert abs(u.mean().item() - 0.5) < 5 * np.sqrt(1 / 12 / N)
    # var of U(0,1) is 1/12; the sample variance has std sqrt((1/80 - 1/144)/N)
    assert abs(u.var().item() - 1 / 12) < 5 * np.sqrt((1 / 80 - 1 / 144) / N)
    # Kolmogorov-Smirnov statistic vs the U(0,1) CDF (1.95/sqrt(N) is the 0.1% critical value)
    v = np.sort(u.flatten().numpy())
    i = np.arange(1, N + 1)
    D = max(np.max(i / N - v), np.max(v - (i - 1) / N))
    assert D < 1.95 / np.sqrt(N)
    # no correlation between neighbouring neurons, neighbouring time steps, or consecutive keys (env steps)
    c = u - 0.5
    lim = 5 / np.sqrt(N)
    for a, b in [(c[..., 1:], c[..., :-1]), (c[:, 1:], c[:, :-1])]:
        assert abs((a * b).mean().item() / (1 / 12)) < lim * 1.1
    nxt = CounterBernoulli().uniform(advance_keys(keys), T, n).double() - 0.5
    assert abs((c * nxt).mean().item() / (1 / 12)) < lim


def test_raster_input_passes_through_and_rejects_mismatch():
    raster = RasterInput(steps=25, n_neurons=40)
    x = (torch.rand(3, 25, 40) < 0.2).float()
    assert raster(x, initial_keys(3), 25) is x
    with pytest.raises(ValueError) as e:
        raster(torch.zeros(3, 24, 40), initial_keys(3), 25)
    assert "(24, 40)" in str(e.value) and "25" in str(e.value) and "40" in str(e.value)
    with pytest.raises(ValueError, match=r"\(25, 41\)"):
        raster(torch.zeros(3, 25, 41), initial_keys(3), 25)
    with pytest.raises(ValueError, match="T=30"):
        raster(x, initial_keys(3), 30)


# ---------------------------------------------------------------------------------------------------------------
# 9. Decoders


def test_continuous_decoder_extremes_and_centre():
    low, high, N = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 0.5, 3.0]), 10
    dec = ContinuousDecoder(low, high, pop_size=N)
    first = torch.tensor(([1.0] * 5 + [0.0] * 5) * 3).unsqueeze(0)
    second = torch.tensor(([0.0] * 5 + [1.0] * 5) * 3).unsqueeze(0)
    np.testing.assert_allclose(dec(first)[0].numpy(), high, atol=1e-6)
    np.testing.assert_allclose(dec(second)[0].numpy(), low, atol=1e-6)
    np.testing.assert_allclose(dec(torch.zeros(1, 30))[0].numpy(), (low + high) / 2, atol=1e-6)
    np.testing.assert_allclose(dec(torch.ones(1, 30))[0].numpy(), (low + high) / 2, atol=1e-6)


def test_continuous_decoder_hand_example_asymmetric_bounds():
    dec = ContinuousDecoder([-2.0, 0.0], [1.0, 4.0], pop_size=4)
    # dim 0: rates [1, .5 | 0, .5]: A = (2/4)(1 + .5 - 0 - .5) = 0.5; centre -0.5, half range 1.5 -> -0.5 + 0.75 = 0.25
    # dim 1: rates [0, 0 | 1, 0]:   A = (2/4)(-1) = -0.5;          centre 2,    half range 2   -> 2 - 1 = 1.0
    rates = torch.tensor([[1.0, 0.5, 0.0, 0.5, 0.0, 0.0, 1.0, 0.0]])
    np.testing.assert_allclose(dec(rates)[0].numpy(), [0.25, 1.0], atol=1e-6)


def test_continuous_decoder_matches_spike_count_formula():
    rng = np.random.default_rng(2)
    n_act, N, T, B = 3, 6, 50, 4
    low, high = rng.uniform(-3, 0, n_act), rng.uniform(0.5, 3, n_act)
    S = (rng.random((B, T, n_act * N)) < 0.3).astype(np.float64)
    w = np.tile(np.r_[np.ones(N // 2), -np.ones(N // 2)], n_act)
    A = np.stack(
        [(2 / N) / T * (S[:, :, k * N : (k + 1) * N] * w[k * N : (k + 1) * N]).sum((1, 2)) for k in range(n_act)], 1
    )
    expected = low + (A + 1) / 2 * (high - low)
    got = ContinuousDecoder(low, high, pop_size=N).double()(torch.from_numpy(S.mean(1)))
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-6, atol=1e-6)


def test_discrete_decoder_logits_are_scaled_population_rates():
    dec = DiscreteDecoder(3, pop_size=4, logit_scale_init=7.0)
    rates = torch.rand(5, 12, generator=torch.Generator().manual_seed(3))
    expected = 7.0 * rates.numpy().reshape(5, 3, 4).mean(-1)
    np.testing.assert_allclose(dec(rates).detach().numpy(), expected, rtol=1e-6)
    assert [n for n, _ in dec.named_parameters()] == ["logit_scale"]


def test_decoder_gradchecks():
    g = torch.Generator().manual_seed(4)
    cont = ContinuousDecoder([-2.0, 0.0], [1.0, 4.0], pop_size=6).double()
    rates = torch.rand(3, 12, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(cont, (rates,))

    disc = DiscreteDecoder(2, pop_size=5).double()
    rates = torch.rand(3, 10, generator=g, dtype=torch.float64).requires_grad_()
    scale = torch.tensor(20.0, dtype=torch.float64, requires_grad=True)

    def f(rates, scale):
        return torch.func.functional_call(disc, {"logit_scale": scale}, (rates,))

    assert torch.autograd.gradcheck(f, (rates, scale))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_compiled_sampler_is_bit_identical_to_the_eager_hash(compiled_ops, monkeypatch, dtype):
    """The compiled sampler (``_fast.bernoulli_spikes``) against the eager int32 hash, including keys with the
    sign bit set and probabilities 0 and 1; and ``SB3_SPIKEPLASTIC_NO_COMPILE`` gives the eager spikes."""
    from sb3_spikeplastic.snn import _fast

    sampler = CounterBernoulli()
    keys = torch.tensor([0, -1, 2**31 - 1, -(2**31), 12345, -987654], dtype=torch.int32)
    p = torch.rand(6, 37, generator=torch.Generator().manual_seed(0), dtype=dtype)
    p[:, 0], p[:, 1] = 0.0, 1.0
    compiled = _fast.bernoulli_spikes(p, keys, sampler.index_hash(23, 37, keys.device))
    eager = (sampler.uniform(keys, 23, 37) < p.unsqueeze(1)).to(dtype)
    assert compiled is not None and compiled.dtype == dtype
    assert torch.equal(compiled, eager)
    assert compiled[..., 0].sum() == 0 and compiled[..., 1].min() == 1
    assert torch.equal(sampler.sample(p, keys, 23), eager)
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    assert _fast.bernoulli_spikes(p, keys, sampler.index_hash(23, 37, keys.device)) is None
    assert torch.equal(sampler.sample(p, keys, 23), eager)

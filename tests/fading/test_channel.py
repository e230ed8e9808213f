"""Fading channel (channels/fading.py): Jakes autocorrelation, exponential SNR, explicit units, bad input."""

import math

import numpy as np
import pytest
from pydantic import ValidationError

from netkf_cli.channels.fading import FadingChannel


def chan(**kw):
    base = {"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"}, "noise": {"model": "ber", "N_p": 10, "Delta": 0.0390625}}
    base.update(kw)
    return FadingChannel.model_validate(base)


def test_iid_snr_is_exponential_with_mean():
    ch = chan()
    Y = ch.sample(np.random.default_rng(0), 50_000, 3).snr
    assert abs(Y.mean() - 100.0) < 5 * Y.std() / math.sqrt(Y.size)
    # exponential: Pr[Υ < t] = 1 − e^{−t/100}; proportion within 5 binomial standard errors
    p = 1 - math.exp(-0.14)
    assert abs((Y < 14).mean() - p) < 5 * math.sqrt(p * (1 - p) / Y.size)


def test_jakes_autocorrelation_matches_J0():
    ch = chan(correlation={"model": "jakes", "carrier_hz": 1e9, "speed": {"value": 25, "unit": "mph"}, "interval_s": 0.01})
    from netkf_cli.channels.fading import sample_gain
    h = sample_gain(np.random.default_rng(1), 20_000, 40, ch.correlation)
    lags = np.arange(8)
    t0 = 39
    prod = (h[t0][None, :] * np.conj(h[t0 - lags])).real  # iid over runs
    est = prod.mean(1)
    se = prod.std(1) / math.sqrt(prod.shape[1])
    assert np.all(np.abs(est - ch.correlation.autocorr(lags)) < 5 * se)
    Y = 100.0 * np.abs(h) ** 2
    assert abs(Y.mean() - 100.0) < 5 * Y.std() / math.sqrt(Y.size) * 6  # correlated samples: generous factor


def test_units_are_explicit():
    assert chan(snr_avg={"value": 100, "unit": "linear"}).mean_snr == 100.0
    assert chan().mean_snr == pytest.approx(100.0)
    with pytest.raises(ValidationError):
        chan(snr_avg={"value": 20})  # no unit: never guessed
    with pytest.raises(ValidationError):
        chan(snr_avg={"value": -3, "unit": "linear"})


@pytest.mark.parametrize("noise", [{"model": "ber", "alpha": 1e-4}, {"model": "ber", "alpha": 1, "delta": 2, "N_p": 3},
                                   {"model": "inverse_snr"}, {"model": "ber", "N_p": 0, "Delta": 0.1}])
def test_bad_noise_rejected(noise):
    with pytest.raises(ValidationError):
        chan(noise=noise)


def test_cli_error_names_the_field(tmp_path):
    from netkf_cli.core.errors import ConfigError
    from netkf_cli.app.runner import run_scenario_file

    p = tmp_path / "bad.yaml"
    p.write_text("name: bad\nchannel:\n  kind: fading\n  snr_avg: {value: 20, unit: db}\n"
                 "  noise: {model: ber, N_p: 10, Delta: 0.04}\nanalysis:\n  kind: fading_averages\n"
                 "  thresholds: {unit: linear, values: [1, 2]}\n")
    with pytest.raises(ConfigError) as e:
        run_scenario_file(p, out_dir=tmp_path / "o", runs=10)
    assert "channel.snr_avg.unit" in str(e.value)
    p.write_text("name: bad\nchannel:\n  kind: fading\n  snr_avg: {value: 20, unit: dB}\n"
                 "  noise: {model: inverse_snr, beta: 1}\nanalysis:\n  kind: fading_averages\n"
                 "  thresholds: {unit: linear, values: [1, 2]}\n")
    with pytest.raises(ConfigError) as e:
        run_scenario_file(p, out_dir=tmp_path / "o", runs=10)
    assert "channel.noise.model" in str(e.value)


@pytest.mark.parametrize("model", ["iid", "jakes"])
def test_gain_parts_are_the_complex_gain_bit_for_bit(model):
    """gain_parts (the SNR's path) gives Re h and Im h of the complex formula h = (x + i y)/√2 (then L h for
    Jakes) bit for bit, and the generator ends in the same state."""
    from netkf_cli.channels.fading import gain_parts, jakes_factor

    corr = chan(correlation={"model": "jakes", "carrier_hz": 1e9, "speed": {"value": 25, "unit": "mph"},
                             "interval_s": 0.01}).correlation if model == "jakes" else chan().correlation
    r1, r2 = np.random.default_rng(5), np.random.default_rng(5)
    re, im = gain_parts(r1, 3000, 50, corr)
    z = (r2.standard_normal((50, 3000)) + 1j * r2.standard_normal((50, 3000))) / np.sqrt(2.0)
    if model == "jakes":
        L = jakes_factor(50, corr)
        z = np.einsum("ij,jk->ik", L, z.real) + 1j * np.einsum("ij,jk->ik", L, z.imag)
    assert np.array_equal(re, z.real) and np.array_equal(im, z.imag)
    assert np.array_equal(100.0 * (re**2 + im**2), 100.0 * (z.real**2 + z.imag**2))
    assert r1.random() == r2.random()


@pytest.mark.parametrize("model", ["iid", "jakes"])
def test_a_drawn_sample_is_reused_with_the_generator_state_after_it(model):
    """DrawnSamples: the second and later draws from one generator state return the first draw's SNR, and leave the
    generator exactly where a fresh draw leaves it (the next numbers equal); another state or size draws anew."""
    from netkf_cli.channels import fading as cf

    corr = {"model": "iid"} if model == "iid" else {"model": "jakes", "carrier_hz": 1e9, "interval_s": 0.01,
                                                      "speed": {"value": 25, "unit": "mph"}}
    ch = chan(correlation=corr)
    drawn = []
    real = ch.sample

    def counted(rng, runs, horizon):
        drawn.append((runs, horizon))
        return real(rng, runs, horizon)

    object.__setattr__(ch, "sample", counted)
    seq = np.random.SeedSequence(9, spawn_key=(0, 3))
    fresh = np.random.default_rng(seq)
    ref = real(fresh, 50, 20).snr
    after = fresh.random(5)
    for i in range(4):
        rng = np.random.default_rng(seq)
        tr = ch.sample_trace(rng, 50, 20)
        assert tr.snr.tobytes() == ref.tobytes()
        assert rng.random(5).tobytes() == after.tobytes()
    assert len(drawn) == 2  # drawn when first seen and when seen again (then kept), reused from then on
    assert not ch.sample_trace(np.random.default_rng(seq), 50, 20).snr.flags.writeable
    ch.sample_trace(np.random.default_rng(seq), 50, 21)
    ch.sample_trace(np.random.default_rng(np.random.SeedSequence(9, spawn_key=(0, 4))), 50, 20)
    assert len(drawn) == 4


def test_noise_helpers_equal_the_noise_of_the_whole_array_bit_for_bit():
    """noise_given_kept / noise_where_kept (σ_n² of the kept entries from the sample's σ_n²(Υ), only the dropped
    ones per threshold) = noise(snr_given_kept(Υ)) / noise(np.where(keep, Υ, 1)), byte for byte, whatever was asked
    before; the same array again for the same threshold (the receivers of one chunk), recomputed for another."""
    from netkf_cli.channels.fading import NoiseFn, noise_given_kept, noise_where_kept, snr_given_kept

    ch = chan()
    tr = ch.sample_trace(np.random.default_rng(np.random.SeedSequence(5)), 400, 30)
    noise = NoiseFn.of(ch.noise)
    for T in (0.0, 1.0, 14.0, 60.0):
        for t, k in ((0, 30), (3, 17)):
            Y = tr.snr[t:k]
            got = noise_given_kept(tr, t, k, T, 100.0, noise)
            assert got.tobytes() == noise(snr_given_kept(Y, T, 100.0)).tobytes()
            got2 = noise_where_kept(tr, t, k, T, noise)
            assert got2.tobytes() == noise(np.where(Y >= T, Y, 1.0)).tobytes()
            assert noise_given_kept(tr, t, k, T, 100.0, noise) is got
            assert noise_where_kept(tr, t, k, T, noise) is got2
    assert noise_given_kept(tr, 0, 30, 14.0, 100.0, noise).tobytes() == noise(snr_given_kept(tr.snr, 14.0, 100.0)).tobytes()
    tr.snr = np.full(tr.snr.shape, 1e12)  # another array: its own σ_n²(Υ), not the sample's
    assert noise_where_kept(tr, 0, 30, 14.0, noise).tobytes() == noise(tr.snr).tobytes()

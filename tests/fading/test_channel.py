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

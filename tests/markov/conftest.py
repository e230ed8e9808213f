"""Shared fixtures of the Moayedi, Soh & Foo 2009 tests: the two examples' models and chains."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from netkf_cli.config.loader import load_scenario

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "markov"
PRINTED_RHO = {"example1": [0.8, 0.02, 0.09, 0.09], "example2": [0.7, 0.045, 0.085, 0.17]}


def setup_of(name: str, **over):
    sc = load_scenario(CONFIGS / f"{name}_exact.yaml", over or None)
    return sc, sc.analysis._setup(sc)


@pytest.fixture(scope="session", params=["example1", "example2"])
def example(request):
    sc, (sysm, ch, est, model, x0, xs0, P0, rho) = setup_of(request.param)
    return dict(name=request.param, sc=sc, ch=ch, est=est, model=model, x0=x0, xs0=xs0, P0=P0, rho=rho,
                T=ch.T, pi0=ch.pi0)

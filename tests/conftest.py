import matplotlib

matplotlib.use("Agg")

import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture
def root() -> pathlib.Path:
    return ROOT

from hypothesis import settings  # noqa: E402

# Derandomized examples: CI and every developer machine test the same cases, so a Monte Carlo
# assertion at 5 standard errors cannot turn red because the search wandered elsewhere.
settings.register_profile("netkf", derandomize=True, print_blob=True)
settings.load_profile("netkf")

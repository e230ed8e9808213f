import matplotlib

matplotlib.use("Agg")

import os
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


# ---- parallel suite (pytest-xdist; `-n auto --dist loadfile` in pyproject's addopts) ----------
# Workers: NETKF_TEST_WORKERS if set; in-process (0) when every argument is a file or a test id (a
# targeted run pays no worker start-up, and --pdb works); otherwise one per usable core, at most 8
# (each worker imports the stack and loads every numba kernel it needs once). The tests of one file
# run on one worker (their module fixtures and compiled kernel shapes are built once).
# The session's quick reproduction (tests/reproduce/_quick.py, shared by the workers through a lock)
# starts first, with the figure lint, and the other file reading it is scheduled last.
FIRST = ("tests/figures/test_lint.py",)
LAST = ("tests/reproduce/test_repo_artefacts.py",)


def pytest_xdist_auto_num_workers(config):
    env = os.environ.get("NETKF_TEST_WORKERS")
    if env:
        return int(env)
    if config.args and all(pathlib.Path(a.split("::")[0]).is_file() for a in config.args):
        return 0
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return min(cpus, 8)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        path = item.nodeid.split("::")[0]
        return 0 if path in FIRST else 2 if path in LAST else 1

    items.sort(key=rank)  # stable: collection order within each rank

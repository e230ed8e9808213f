import netkf_cli  # noqa: F401  (first: its one-BLAS-thread default must reach OpenBLAS before numpy loads it)
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
# Order, longest first so that no long file starts last: the figure lint first (it runs the session's
# quick reproduction, tests/reproduce/_quick.py, which the workers share through a lock), then the
# files by their seconds in the previous run (.pytest_cache: netkf/file_seconds), then by their number
# of tests (a fresh clone), and test_repo_artefacts.py (the quick reproduction's other reader) last.
FIRST = ("tests/figures/test_lint.py",)
LAST = ("tests/reproduce/test_repo_artefacts.py",)
_SECONDS_KEY = "netkf/file_seconds"
_seconds: dict[str, float] = {}


def _file(nodeid: str) -> str:
    return nodeid.split("::")[0]


def pytest_xdist_auto_num_workers(config):
    env = os.environ.get("NETKF_TEST_WORKERS")
    if env:
        return int(env)
    if config.args and all(pathlib.Path(_file(a)).is_file() for a in config.args):
        return 0
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return min(cpus, 8)


def pytest_configure(config):
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False  # xdist keeps the order below instead of sorting by test count


def pytest_collection_modifyitems(config, items):
    before = config.cache.get(_SECONDS_KEY, {}) if getattr(config, "cache", None) else {}
    count: dict[str, int] = {}
    for item in items:
        count[_file(item.nodeid)] = count.get(_file(item.nodeid), 0) + 1

    def rank(item):
        f = _file(item.nodeid)
        return (0 if f in FIRST else 2 if f in LAST else 1, -float(before.get(f, 0.0)), -count[f], f)

    items.sort(key=rank)  # stable: collection order within each file


def pytest_runtest_logreport(report):
    f = _file(report.nodeid)
    _seconds[f] = _seconds.get(f, 0.0) + float(getattr(report, "duration", 0.0) or 0.0)


def pytest_sessionfinish(session):
    config = session.config
    if hasattr(config, "workerinput") or not _seconds or not getattr(config, "cache", None):
        return  # a worker (the controller records what every worker reported)
    config.cache.set(_SECONDS_KEY, {**config.cache.get(_SECONDS_KEY, {}), **{f: round(t, 2) for f, t in _seconds.items()}})

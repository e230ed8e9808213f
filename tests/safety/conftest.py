"""Every test here ends with a scan for leftovers (tests/safety/debris.py)."""

from tests.safety.debris import no_debris  # noqa: F401 - autouse fixture


def pytest_configure(config):
    config.addinivalue_line("markers", "keeps_resume_cache: the test interrupts a run on purpose; its "
                                       ".netkf-cache is kept for --resume and is not debris")
    config.addinivalue_line("markers", "sigkilled: the test SIGKILLs a run; what it leaves is cleaned by the next run "
                                       "(tested in test_outputs.py), not by the killed one")

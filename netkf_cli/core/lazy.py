"""Required libraries a module names at its top but loads on first use (issue 20's 300 MB).

``from netkf_cli.core.lazy import pandas as pd`` reads like ``import pandas as pd``; pandas (40 MB resident,
~0.3 s here) is imported by the first ``pd.<name>`` that runs (and so scipy.integrate / scipy.optimize, 19 MB,
which only the fading closed forms use). A Monte Carlo run builds its tables only after
its chunks, so a one-point run forks its workers and computes every chunk without pandas in any process
(markov/example1 and example2 at ``--jobs 2``: 324 → 295 MB peak PSS), and ``netkf list`` / ``netkf mind`` never load it.

The proxy is not put in ``sys.modules``: other libraries, and ``import pandas`` anywhere, see the real module.
Once loaded, the module's names are copied onto the proxy, so later lookups are plain attribute reads.
"""

from __future__ import annotations

import importlib
from types import ModuleType


class LazyModule:
    """The module ``name``, imported on the first attribute read (then every name of it is the proxy's own)."""

    def __init__(self, name: str):
        self.__dict__["_lazy_name"] = name

    def load(self) -> ModuleType:
        mod = importlib.import_module(self.__dict__["_lazy_name"])
        self.__dict__.update(vars(mod))
        return mod

    def __getattr__(self, attr: str):  # only for names not (yet) on the proxy
        return getattr(self.load(), attr)

    def __setattr__(self, attr: str, value) -> None:
        raise AttributeError(f"{self.__dict__['_lazy_name']} through netkf_cli.core.lazy is read-only")

    def __repr__(self) -> str:
        return f"<lazy module {self.__dict__['_lazy_name']!r}>"


pandas = LazyModule("pandas")
"""pandas, loaded by the first ``pd.DataFrame`` / ``pd.concat`` … (tables are built after the Monte Carlo)."""

scipy_integrate = LazyModule("scipy.integrate")
"""scipy.integrate (with scipy.optimize and scipy.sparse, which it imports: 19 MB, 0.15 s): the fading closed forms'
quadratures only."""

scipy_optimize = LazyModule("scipy.optimize")
"""scipy.optimize: the fading closed forms' root finding and bounded minimisation only."""


def load_all() -> None:
    """Import every lazy module now: a parent about to fork workers that all need them (``netkf reproduce --jobs
    N``: each artefact builds tables, and the parent reads them to judge the checks while the workers run) shares
    one import (~0.4 s CPU here) instead of paying it in every process, the parent's while the workers compute."""
    for mod in (pandas, scipy_integrate, scipy_optimize):
        mod.load()

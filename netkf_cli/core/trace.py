"""One trace type for every channel: what a batch of runs saw on the network.

Every channel samples ``runs`` independent realisations of ``horizon`` steps into a
:class:`Trace` (``ChannelModel.sample_trace(rng, runs, horizon)``); every estimator maps a
trace to batched error covariances (``EstimatorModel.covariances(system, trace, steps)``).
Arrays are time-major with the **run axis innermost** (``x[..., t, :]`` is contiguous over
runs), the layout the hot kernels use (design.md).

Fields (``None`` when the channel does not produce them); ``S`` = number of sensors/links:

* ``arrival`` — ``(S, horizon, runs)`` bool: the measurement of step t (of sensor s) reaches
  the estimator (in time, for a delay channel viewed as pure loss);
* ``delay``   — ``(S, horizon, runs)`` int32: delay in steps of packet t, ``LOST`` if never;
  ``meta['buffer']`` (D) and ``meta['convention']`` say which delays the receiver keeps;
* ``snr``     — ``(horizon, runs)`` float: received SNR Υ_t (linear) of a fading link;
* ``mode``    — ``(horizon, runs)`` int8: index of the channel's Markov mode at step t.

Time index: step t = 0 … horizon−1 carries measurement y_{t+1} (the first measurement is
y_1, after one prediction from P0), so the covariance after processing step t is P_{t+1}.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

LOST = np.int32(2**30)
"""Delay value of a packet that never arrives."""

FIELDS = ("arrival", "delay", "snr", "mode")


@dataclass
class Trace:
    """A batch of channel realisations (run axis innermost). See the module docstring."""

    runs: int
    horizon: int
    arrival: np.ndarray | None = None
    delay: np.ndarray | None = None
    snr: np.ndarray | None = None
    mode: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def derived(self, key, compute):
        """``compute()``, once per trace and ``key``: a quantity several estimators of one chunk derive from the
        same trace (the fading receivers' σ_n²(Υ) of a block of steps) is computed once, the same array for each.
        The key must name everything the value depends on besides the trace; the value must not be modified."""
        try:
            hit = key in self._derived
        except TypeError:  # an unhashable part (a caller's own noise function): not shared
            return compute()
        if not hit:
            self._derived[key] = compute()
        return self._derived[key]

    def __post_init__(self) -> None:
        for name in ("arrival", "delay"):
            a = getattr(self, name)
            if a is not None:
                if a.ndim == 2:  # one sensor given as (horizon, runs)
                    a = a[None]
                    setattr(self, name, a)
                if a.ndim != 3 or a.shape[1:] != (self.horizon, self.runs):
                    raise ValueError(f"trace.{name} must be (sensors, {self.horizon}, {self.runs}), got {a.shape}")
        for name in ("snr", "mode"):
            a = getattr(self, name)
            if a is not None and a.shape != (self.horizon, self.runs):
                raise ValueError(f"trace.{name} must be ({self.horizon}, {self.runs}), got {a.shape}")

    @property
    def kinds(self) -> frozenset[str]:
        """The fields this trace carries (what an estimator can ask for)."""
        return frozenset(f for f in FIELDS if getattr(self, f) is not None)

    @property
    def sensors(self) -> int:
        a = self.arrival if self.arrival is not None else self.delay
        return 1 if a is None else int(a.shape[0])

"""``kind: trace`` — replay a recorded arrival (or delay) sequence from a CSV file.

The file has one column per sensor (a header row naming them is allowed) and one row per
time step: ``0``/``1`` arrivals (``values: arrival``) or integer delays in steps with an
empty cell, ``-1`` or ``lost`` for a packet that never arrived (``values: delay``). A run of
``horizon`` steps starting at row ``offset`` takes rows ``offset … offset+horizon−1``:

* ``mode: once`` — every run replays the same recording (the recording must be at least
  ``offset + horizon`` rows long); Monte Carlo then only averages the estimator's own
  randomness (none for covariance-only metrics, so ``runs: 1`` is enough);
* ``mode: cycle`` — the recording is repeated end to end as needed, and run ``r`` starts at
  row ``offset + r·stride`` (``stride`` default 0: all runs identical), so a long recording
  can be cut into many runs.

A relative ``file`` is resolved against the scenario file's folder. From Python,
``TraceChannel.from_array(gamma)`` replays a numpy array without a file.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, PrivateAttr, ValidationInfo, field_validator, model_validator

from netkf_cli.core.errors import ConfigError
from netkf_cli.core.spec import ChannelModel, NonNegInt
from netkf_cli.core.trace import LOST, Trace

MAX_ROWS = 10_000_000


def read_recording(path: Path, values: str) -> np.ndarray:
    """The recording as (sensors, rows): bool arrivals or int32 delays (LOST for a lost packet)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError.at("channel.file", f"file not found: {path}") from None
    except UnicodeDecodeError:
        raise ConfigError.at("channel.file", f"{path} is not a UTF-8 text CSV file") from None
    numbered = [(i + 1, r) for i, r in enumerate(csv.reader(text.splitlines()))]
    filled = [k for k, (_, r) in enumerate(numbered) if r and any(c.strip() for c in r)]
    # blank lines before the first and after the last filled line are formatting; between them a blank line is a
    # row whose cells are empty: a lost packet of a delay recording (a one-column file writes an empty cell so),
    # and an error naming its line for arrivals (dropping it shifted every later step by one)
    numbered = numbered[filled[0]:filled[-1] + 1] if filled else []
    if numbered and not all(_is_value(c) for c in numbered[0][1]):
        numbered = numbered[1:]  # header
    cols = max((len(r) for _, r in numbered), default=1)
    numbered = [(n, r if r and any(c.strip() for c in r) else [""] * cols) for n, r in numbered]
    lines = [n for n, _ in numbered]  # the file's line of each data row, for messages
    rows = [r for _, r in numbered]
    if not rows:
        raise ConfigError.at("channel.file", f"{path} has no data rows")
    if len(rows) > MAX_ROWS:
        raise ConfigError.at("channel.file", f"{path} has {len(rows)} rows; at most {MAX_ROWS} are supported")
    width = {len(r) for r in rows}
    if len(width) != 1:
        raise ConfigError.at("channel.file", f"{path}: rows have different numbers of columns {sorted(width)}")
    out = np.empty((width.pop(), len(rows)), dtype=np.int64)
    for t, r in enumerate(rows):
        for s, c in enumerate(r):
            c = c.strip().lower()
            if values == "arrival":
                if c not in ("0", "1", "0.0", "1.0", "true", "false"):
                    raise ConfigError.at("channel.file", f"{path} line {lines[t]} column {s + 1}: expected 0 or 1, got {c!r}")
                out[s, t] = 1 if c in ("1", "1.0", "true") else 0
            else:
                if c in ("", "-1", "lost", "nan", "inf"):  # nan/inf: how some tools write "never arrived"
                    out[s, t] = LOST
                else:
                    out[s, t] = _delay_cell(c, path, lines[t], s)
    return out.astype(bool) if values == "arrival" else out.astype(np.int32)


MAX_DELAY = 2**31 - 2
"""Largest recorded delay in steps (int32 traces); a delay beyond any horizon is simply never usable."""


def _delay_cell(c: str, path: Path, line: int, s: int) -> int:
    """One delay cell: an integer number of steps ≥ 0 (``-1``, empty or ``lost`` mean lost, handled
    by the caller); anything else is refused naming the file, the row and the column."""
    where = f"{path} line {line} column {s + 1}"
    try:
        v = float(c)
    except ValueError:
        raise ConfigError.at("channel.file", f"{where}: expected a delay (integer ≥ 0, or empty/-1/lost), "
                                             f"got {c!r}") from None
    if not np.isfinite(v):
        raise ConfigError.at("channel.file", f"{where}: a delay must be a finite number of steps (empty, -1 or "
                                             f"'lost' for a lost packet), got {c!r}")
    if v != int(v):
        raise ConfigError.at("channel.file", f"{where}: a delay is a whole number of steps, got {c!r}")
    if v < 0:
        raise ConfigError.at("channel.file", f"{where}: a delay must be ≥ 0 (or -1 for a lost packet), got {c!r}")
    if v > MAX_DELAY:
        raise ConfigError.at("channel.file", f"{where}: delay {c} is beyond the largest supported delay "
                                             f"({MAX_DELAY} steps); write -1 or 'lost' for a packet that never arrived")
    return int(v)


_READ: dict = {}


def _read_cached(path: Path, values: str) -> np.ndarray:
    """:func:`read_recording`, once per file version (a sweep validates every point's channel)."""
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_mtime_ns, st.st_size, values)
    except OSError:
        return read_recording(path, values)  # it says what is wrong with the path
    if key not in _READ:
        if len(_READ) > 16:
            _READ.clear()
        arr = read_recording(path, values)
        arr.setflags(write=False)  # shared by every channel that replays this file
        _READ[key] = arr
    return _READ[key]


def _is_value(c: str) -> bool:
    c = c.strip().lower()
    if c in ("", "lost", "true", "false", "nan", "inf"):
        return True
    try:
        float(c)
        return True
    except ValueError:
        return False


class TraceChannel(ChannelModel):
    """``kind: trace`` — replay a recorded arrival/delay sequence (CSV, one column per sensor)."""

    kind: Literal["trace"]
    file: str = Field(description="CSV file: one column per sensor, one row per step (relative to the scenario file)")
    values: Literal["arrival", "delay"] = Field("arrival", description="cells are 0/1 arrivals or delays in steps")
    mode: Literal["once", "cycle"] = Field("once", description="once: every run replays rows offset…offset+horizon−1; "
                                                               "cycle: the recording repeats and run r starts at offset + r·stride")
    offset: NonNegInt = Field(0, description="first row used (0-based)")
    stride: NonNegInt = Field(0, description="cycle mode: rows between the starts of consecutive runs")
    buffer: int = Field(1, ge=1, description="delay traces: receive buffer length D")
    convention: Literal["delay_le_D", "delay_lt_D"] = Field("delay_le_D", description="delay traces: which delays the buffer keeps")

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"arrival", "delay"})
    _data: np.ndarray | None = PrivateAttr(None)

    @field_validator("file")
    @classmethod
    def _resolve(cls, v: str, info: ValidationInfo) -> str:
        base = (info.context or {}).get("base_dir") if info.context else None
        p = Path(v)
        if not p.is_absolute() and base:
            p = Path(base) / p
        return str(p)

    @model_validator(mode="after")
    def _read_now(self):
        """Read (and check) the recording at validation, so `netkf validate` refuses a bad file
        naming it, its row and column — not the first Monte Carlo chunk."""
        if self._data is None and not self.file.startswith("<"):
            try:
                self._data = _read_cached(Path(self.file), self.values)
            except ConfigError as exc:
                raise ValueError("file: " + "; ".join(p.message for p in exc.problems)) from None
        return self

    @classmethod
    def from_array(cls, data, values: str = "arrival", **kw) -> "TraceChannel":
        """A trace channel replaying ``data`` (shape (rows,) or (sensors, rows)) instead of a file."""
        arr = np.asarray(data)
        if arr.ndim not in (1, 2) or arr.size == 0 or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise ConfigError.at("channel", f"a recording is a non-empty numeric array of shape (rows,) or "
                                            f"(sensors, rows), got {arr.dtype} of shape {arr.shape}")
        a = arr.astype(float)
        if values == "arrival":
            bad = ~np.isin(a, (0.0, 1.0))
            want = "0 or 1"
        else:
            bad = ~np.isfinite(a) | (a != np.round(a)) | (a < -1) | (a > MAX_DELAY)
            want = f"integer delays 0…{MAX_DELAY} (or -1 for lost)"
        if bad.any():
            i = tuple(int(x) for x in np.argwhere(bad)[0])
            raise ConfigError.at("channel", f"a recording of {values}s holds {want}, got {float(a[i]):g} at index {i}")
        arr = arr[None] if arr.ndim == 1 else arr
        ch = cls(kind="trace", file="<array>", values=values, **kw)
        ch._data = arr.astype(bool) if values == "arrival" else np.where(arr < 0, LOST, arr).astype(np.int32)
        return ch

    def with_streams(self, streams: int) -> "TraceChannel":
        """The same replay of a recording with ``streams`` columns, each the first column (`netkf list` checks
        which estimators read a recording of as many columns as C has rows)."""
        rec = self.recording()
        data = np.repeat(rec[:1], int(streams), axis=0)
        if self.values == "delay":
            data = np.where(data == LOST, -1, data)
        return TraceChannel.from_array(data, self.values, mode=self.mode, offset=self.offset, stride=self.stride,
                                       buffer=self.buffer, convention=self.convention)

    def recording(self) -> np.ndarray:
        if self._data is None:
            self._data = read_recording(Path(self.file), self.values)
        return self._data

    def sensors_count(self) -> int:
        return int(self.recording().shape[0])

    def rows(self, runs: int, horizon: int) -> np.ndarray:
        """Row index of every (step, run): (horizon, runs)."""
        L = self.recording().shape[1]
        start = self.offset + self.stride * np.arange(runs)
        idx = start[None, :] + np.arange(horizon)[:, None]
        if self.mode == "once":
            self._check_length(runs, horizon)
            return idx
        return idx % L

    def _check_length(self, runs: int, horizon: int) -> None:
        """Mode once: the recording holds every run's rows."""
        L = self.recording().shape[1]
        need = self.offset + horizon + self.stride * (runs - 1)
        if self.mode == "once" and need > L:
            what = "offset + horizon" + (" + stride·(runs − 1)" if self.stride and runs > 1 else "")
            raise ConfigError.at("channel.file", f"mode once needs {need} rows ({what}), the recording has {L}; "
                                                 "use mode: cycle or a shorter horizon")

    def check_montecarlo(self, montecarlo) -> None:
        """The scenario's check (`netkf validate`): the rows ``montecarlo`` replays exist (mode once)."""
        self._check_length(int(montecarlo.runs), int(montecarlo.horizon))

    def loss_rate(self) -> float:
        rec = self.recording()
        return float(1 - rec.mean()) if self.values == "arrival" else float((rec == LOST).mean())

    def sample_trace(self, rng, runs: int, horizon: int) -> Trace:
        rec = self.recording()
        idx = self.rows(runs, horizon)
        data = np.ascontiguousarray(rec[:, idx])  # (S, horizon, runs)
        if self.values == "arrival":
            return Trace(runs, horizon, arrival=data, meta={"source": self.file})
        return Trace(runs, horizon, delay=data, arrival=data == 0,
                     meta={"source": self.file, "buffer": self.buffer, "convention": self.convention})

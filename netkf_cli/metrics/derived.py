"""Tables derived from a generic metric's table over an ``over`` grid, so claims can read one row each.

A claim in ``experiments/<topic>/published.yaml`` selects rows of a CSV and checks one column
(``every_row`` for "at every point"). Statements that compare two numbers — a Monte Carlo mean
against a closed-form bound, one estimator against another on the same traces, a value at one grid
point against another — read these derived tables, written beside the main table:

* ``pairs`` — at each over point, for each (quantity, M), every ordered pair (a, b) of rows where a is
  a Monte Carlo row, or a and b belong to the same estimator: ``a``, ``b``, ``diff`` = a − b,
  ``ratio`` = a / b, ``stderr`` = √(se_a² + se_b²) (a closed form has none; for two Monte Carlo rows of
  the same traces this is conservative: the paired error is smaller) and ``z`` = diff / max(stderr,
  PSD_TOL · max(|a|, |b|)) (a deterministic Monte Carlo, e.g. on a loss-free channel, differs from its
  closed form by round-off only: :data:`netkf_cli.core.tolerances.PSD_TOL` relative).
* ``trend`` — along each over path p, for every two grid points that differ only in p (``from`` <
  ``to`` in grid order), every row present at both: ``diff`` = value(to) − value(from).

Columns name the rows by the table's own keys (``estimator``, ``series``, ``source``, ``quantity``,
``M``) and carry the other over columns, so ``select: {path: channel.buffer, from: 5, to: 10, …}``
picks one number.
"""

from __future__ import annotations

import numpy as np
from netkf_cli.core.lazy import pandas as pd

from netkf_cli.core.tolerances import PSD_TOL

KEYS = ["estimator", "series", "source"]


def _group_cols(t: pd.DataFrame) -> list[str]:
    return [c for c in ("quantity", "M") if c in t.columns]


def _key(df: pd.DataFrame, cols: list[str]) -> pd.Series:
    return df[cols].apply(lambda r: "\x1f".join(str(v) for v in r.tolist()), axis=1)


def _cells(df: pd.DataFrame, cols) -> dict[str, list]:
    """``{c: [df.iat[i, position of c] for each row i]}`` of a frame with a RangeIndex: the scalars ``df.at``
    returns (the same lookup without the label step, pandas' unboxing included), read once per cell instead of
    once per derived row that repeats it."""
    return {c: [df.iat[i, pos] for i in range(len(df))]
            for c in dict.fromkeys(cols) for pos in [df.columns.get_loc(c)]}


def pairs(t: pd.DataFrame, over: list[str]) -> pd.DataFrame:
    """Every (a, b) comparison at one over point (see the module docstring)."""
    cols = [c for c in over if c in t.columns]
    grp = _group_cols(t)
    out = []
    t = t.assign(_M=t["M"].fillna(-1.0)) if "M" in t.columns else t.assign(_M=-1.0)
    by = cols + [c if c != "M" else "_M" for c in grp]
    for _, g in t.groupby(by, sort=False, dropna=False) if by else [(None, t)]:
        g = g.reset_index(drop=True)
        se = g["stderr"].astype(float).fillna(0.0).to_numpy()
        val = g["value"].astype(float).to_numpy()
        mc = (g["source"] == "monte_carlo").to_numpy()
        est = g["estimator"].astype(str).to_numpy()
        cell = _cells(g, cols + grp + ["series", "source"])
        for i in range(len(g)):
            for j in range(len(g)):
                if i == j or not (mc[i] or est[i] == est[j]):
                    continue
                with np.errstate(divide="ignore", invalid="ignore"):
                    diff = val[i] - val[j]
                    s = float(np.hypot(se[i], se[j]))
                    floor = PSD_TOL * max(abs(val[i]), abs(val[j])) if np.isfinite(diff) else 0.0
                    row = {c: cell[c][i] for c in cols + grp}
                    row.update(a_estimator=est[i], a_series=cell["series"][i], a_source=cell["source"][i],
                               b_estimator=est[j], b_series=cell["series"][j], b_source=cell["source"][j],
                               a=val[i], b=val[j], diff=diff, ratio=val[i] / val[j] if val[j] != 0 else np.nan,
                               stderr=s, z=diff / max(s, floor) if max(s, floor) > 0 else
                               (0.0 if diff == 0 else np.sign(diff) * np.inf))
                out.append(row)
    return pd.DataFrame(out, columns=cols + grp + ["a_estimator", "a_series", "a_source", "b_estimator", "b_series",
                                                   "b_source", "a", "b", "diff", "ratio", "stderr", "z"])


def trend(t: pd.DataFrame, over: list[str]) -> pd.DataFrame:
    """Differences along each over path between grid points that differ only in that path."""
    cols = [c for c in over if c in t.columns]
    ident = KEYS + _group_cols(t)
    out = []
    t = t.reset_index(drop=True)
    key = _key(t, ident)
    cell = _cells(t, cols + ident + ["value"])
    for p in cols:
        others = [c for c in cols if c != p]
        order = list(dict.fromkeys(t[p].tolist()))  # grid order of p's values
        rank = {v: i for i, v in enumerate(order)}
        groups = t.groupby(others, sort=False, dropna=False) if others else [(None, t)]
        for _, g in groups:
            vals = {}  # (identity, p value) -> row index
            for idx, (k, v) in zip(g.index, zip(key[g.index], g[p])):
                vals[(k, v)] = idx
            same = {}  # identity -> [(p value, row index)] in the order of vals
            for (k, v), idx in vals.items():
                same.setdefault(k, []).append((v, idx))
            for (k, v_from), i_from in vals.items():
                for v_to, i_to in same[k]:
                    if rank[v_to] <= rank[v_from]:
                        continue
                    a, b = float(cell["value"][i_from]), float(cell["value"][i_to])
                    row = {"path": p, "from": v_from, "to": v_to}
                    row.update({c: cell[c][i_from] for c in others + ident})
                    with np.errstate(invalid="ignore"):
                        row.update(value_from=a, value_to=b, diff=b - a)
                    out.append(row)
    return pd.DataFrame(out, columns=["path", "from", "to"] + [c for c in cols] + ident + ["value_from", "value_to",
                                                                                          "diff"])


def tables(t: pd.DataFrame, over: list[str]) -> dict[str, pd.DataFrame]:
    """The derived tables of a metric's table over the grid ``over`` (extra tables of the artefact)."""
    return {"pairs": pairs(t, over), "trend": trend(t, over)}

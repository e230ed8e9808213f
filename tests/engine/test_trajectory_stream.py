"""state_error trajectories draw from a reserved stream, never a Monte Carlo chunk's numbers.

Chunk i of stream s draws from SeedSequence(seed, spawn_key=(s, i)); under ``streams: independent`` the
``over`` point j runs on stream j. The trajectories used to take stream s + 1 — the next point's Monte Carlo
stream, so the "one run" drawn beside point 0 was run 0 of point 1. With one run per point (runs = chunk = 1)
the Monte Carlo's per-step ``empirical`` value IS that run's squared error, which makes a collision visible
bit for bit: the positive control shows that trajectories on a chunk's stream reproduce it exactly.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import yaml
from typer.testing import CliRunner

from netkf_cli.app import api
from netkf_cli.engine import state
from netkf_cli.app.cli import app
from netkf_cli.metrics.common import needs
from netkf_cli.metrics.state_error import TRAJECTORY_STREAM

# two points whose scenarios are the same in effect (kf from P̄ does not use λ; u < 0.6 vs u < 0.600000001 differ
# with probability ~6e-9) but are told apart by the table's channel.arrival column
A0, A1 = 0.6, 0.600000001  # the CSV keeps 10 significant digits
DOC = {"name": "ts", "system": {"A": 0.9, "C": 1, "Q": 1, "R": 1}, "channel": {"kind": "bernoulli", "arrival": A0},
       "estimator": {"kind": "kf"},
       "analysis": {"kind": "state_error", "trajectories": 1, "over": {"channel.arrival": [A0, A1]},
                    "streams": "independent"},
       "montecarlo": {"runs": 1, "horizon": 6, "seed": 2, "chunk": 1, "burn_in": 2}}
K = list(range(1, 7))


def _traj_e2(tr: pd.DataFrame) -> np.ndarray:
    x = tr[tr.series == "true"].set_index("k").value
    xh = tr[tr.series == "kf"].set_index("k").value
    return np.array([(x[k] - xh[k]) ** 2 for k in K])


def test_trajectories_do_not_reuse_the_next_points_stream(tmp_path):
    p = tmp_path / "ts.yaml"
    p.write_text(yaml.safe_dump(DOC), encoding="utf-8")
    res = CliRunner().invoke(app, ["run", str(p), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    t = pd.read_csv(tmp_path / "out" / "ts.csv")
    tr = pd.read_csv(tmp_path / "out" / "ts_trajectories.csv")
    assert TRAJECTORY_STREAM >= 2**30 > 10_000  # beyond any over grid / sweep (≤ 10 000 points) and critical's λ streams
    emp = {a: t[(t.series == "empirical") & np.isclose(t["channel.arrival"], a, rtol=0, atol=1e-12)]
              .set_index("k").value.loc[K].to_numpy() for a in (A0, A1)}
    traj = {a: _traj_e2(tr[np.isclose(tr["channel.arrival"], a, rtol=0, atol=1e-12)]) for a in (A0, A1)}
    assert not np.allclose(emp[A0], emp[A1])  # the points are on independent streams
    for a in (A0, A1):  # no trajectory is any point's Monte Carlo run
        for b in (A0, A1):
            assert not np.allclose(traj[a], emp[b]), (a, b)

    # positive control: trajectories on the chunk's own stream (the old stream 0 + 1 of point 0) are point 1's run
    sc = api.load(DOC)
    old = state.trajectories(needs(sc, "system"), needs(sc, "channel"), needs(sc, "estimators"), runs=1, steps=K,
                             horizon=6, seed=2, stream=1, quantity=("filtered",))
    x = old["traj_x"][0, :, 0]
    xh = old["traj_0"][0, :, 0]  # column 0: kf, filtered
    np.testing.assert_allclose((x[K] - xh) ** 2, emp[A1], rtol=1e-9, atol=0)  # the CSV: 10 significant digits

"""Sample channels, estimators and systems for the engine's matrix tests, taken from the configs."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]


def _block(config: str, key: str) -> dict:
    return yaml.safe_load((ROOT / "configs" / config).read_text(encoding="utf-8"))[key]


def sample_channels(tmp: Path) -> dict[str, dict]:
    rec = tmp / "arrivals.csv"
    rec.write_text("gamma\n" + "\n".join("1" if (i * 7) % 10 < 7 else "0" for i in range(97)) + "\n", encoding="utf-8")
    return {
        "bernoulli": {"kind": "bernoulli", "arrival": 0.8},
        "delay": {"kind": "delay", "delay": {"kind": "poisson", "mean": 1}, "buffer": 3},
        "gilbert_elliott": _block("smoothing/burstiness.yaml", "channel"),
        "retransmission": _block("smoothing/retransmission.yaml", "channel"),
        "multi": _block("fusion/fig1.yaml", "channel"),
        "markov_modes": _block("markov/example1.yaml", "channel"),
        "fading": _block("fading/fig6.yaml", "channel"),
        "trace": {"kind": "trace", "file": str(rec), "mode": "cycle", "stride": 13},
    }


SCALAR = {"A": 1.2, "C": 1, "Q": 1, "R": 1}


def candidate_systems() -> list[dict]:
    """Systems tried in order for a pair: the first one the pair validates on is used."""
    out = [SCALAR]
    for cfg in ("markov/example1.yaml", "fading/fig6.yaml", "fig9.yaml", "fusion/fig1.yaml"):
        s = _block(cfg, "system")
        if s not in out:
            out.append(s)
    return out


def sample_estimators() -> dict[str, dict]:
    from netkf_cli.config.scenario import kinds
    from netkf_cli.core.spec import EstimatorModel

    from_configs = {"fusion": _block("fusion/fig1.yaml", "estimators"), "markov_lmi": _block("markov/example2_exact.yaml", "estimator")}
    special = {"buffered": {"kind": "buffered", "packet": "measurement"}, "smoother": {"kind": "smoother", "lag": 1},
               "receiver": {"kind": "receiver", "scenario": 2, "threshold": {"value": 2, "unit": "linear"}}}
    out = {}
    for k, cls in kinds(EstimatorModel).items():
        spec = special.get(k) or from_configs.get(k) or {"kind": k}
        if isinstance(spec, list):
            spec = spec[0]
        out[k] = spec
    return out


@pytest.fixture(scope="session")
def samples(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("engine-samples")
    return {"channels": sample_channels(tmp), "estimators": sample_estimators(), "systems": candidate_systems(),
            "tmp": tmp}

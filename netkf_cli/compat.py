"""Cross-block checks of a scenario: what makes sense together (channel × estimator × analysis).

Run by the loader after the schema validation, so ``netkf validate`` rejects everything
``netkf run`` would: an estimator that cannot read the channel's traces (the message names
the compatible channel kinds), a system the estimator cannot work with, an analysis that
needs another channel or estimator, ``burn_in ≥ horizon``.
"""

from __future__ import annotations

from dataclasses import replace

from netkf_cli.errors import ConfigError, Problem


def compatible_channels(estimator_cls) -> list[str]:
    """Channel kinds whose traces this estimator class accepts."""
    from netkf_cli.scenario import kinds
    from netkf_cli.spec import ChannelModel

    acc = getattr(estimator_cls, "accepts", frozenset())
    return sorted(k for k, c in kinds(ChannelModel).items() if getattr(c, "trace_kinds", frozenset()) & acc)


def compatible_estimators(channel_cls) -> list[str]:
    """Estimator kinds that accept this channel class's traces."""
    from netkf_cli.scenario import kinds
    from netkf_cli.spec import EstimatorModel

    tk = getattr(channel_cls, "trace_kinds", frozenset())
    return sorted(k for k, c in kinds(EstimatorModel).items() if getattr(c, "accepts", frozenset()) & tk)


def check_pair(channel, estimator, path: str = "estimator.kind", strict: bool = True) -> None:
    """Refuse an estimator that cannot read this channel's traces.

    ``strict`` (the generic metrics and the engine): both must declare what they produce and
    read. Paper recipes that drive their own kernels pass ``strict=False``: only a declared
    mismatch is refused there.
    """
    acc = getattr(estimator, "accepts", frozenset())
    tk = getattr(channel, "trace_kinds", frozenset())
    if strict and not tk:
        raise ConfigError.at(path.replace("estimator", "channel", 1) if path.startswith("estimator") else "channel.kind",
                             f"channel {channel.kind!r} does not sample traces for the generic metrics")
    if strict and not acc:
        raise ConfigError.at(path, f"estimator {estimator.kind!r} reports no per-run error covariance, so the generic "
                                   f"metrics cannot use it (only its paper analysis)")
    if acc and tk and not (acc & tk):
        raise ConfigError.at(
            path,
            f"estimator {estimator.kind!r} needs a channel providing {'/'.join(sorted(acc))}, but channel "
            f"{channel.kind!r} provides {'/'.join(sorted(tk))}; compatible channels: "
            f"{', '.join(compatible_channels(type(estimator))) or 'none'}")


def check_scenario(scenario) -> None:
    """Raise one ConfigError with every cross-block problem of a validated scenario."""
    problems: list[Problem] = []

    def collect(fn, *args):
        try:
            fn(*args)
        except ConfigError as exc:
            problems.extend(exc.problems)

    mc = scenario.montecarlo
    if mc.burn_in >= mc.horizon:
        problems.append(Problem("montecarlo.burn_in", f"must be < horizon = {mc.horizon}, got {mc.burn_in}"))
    ch, ests = scenario.channel, scenario.estimator_list()
    many = bool(scenario.estimators)
    if many and scenario.estimator is not None:
        problems.append(Problem("estimators", "give either `estimator:` (one) or `estimators:` (a list), not both"))
    system = None
    if scenario.system is not None:
        try:
            system = scenario.system.build()
        except ConfigError:
            system = None  # reported by the loader already
    for i, es in enumerate(ests):
        if ch is None:
            break
        path = f"estimators[{i}]" if many else "estimator"
        before = len(problems)
        collect(check_pair, ch, es, f"{path}.kind", _generic(scenario.analysis))
        if len(problems) == before and system is not None:
            try:
                es.check(system, ch)
            except ConfigError as exc:
                problems.extend(replace(p, path=p.path.replace("estimator", path, 1)) if many else p
                                for p in exc.problems)
    check = getattr(scenario.analysis, "check", None)
    if callable(check):
        collect(check, scenario)
    if problems:
        raise ConfigError(problems)


def _generic(analysis) -> bool:
    from netkf_cli.kinds import GENERIC_METRICS

    return getattr(analysis, "kind", None) in GENERIC_METRICS

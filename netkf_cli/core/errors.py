"""Domain exceptions. The library raises these; only ``cli.py`` turns them into messages.

A :class:`ConfigError` carries one or more :class:`Problem` (dotted field path + message),
optionally the file and line, so the CLI can print one line per problem::

    configs/x.yaml:12 channel.delay.mean: must be >= 0, got -1
"""

from __future__ import annotations

from dataclasses import dataclass, replace


class NetkfError(Exception):
    """Base class of every error netkf reports to a user."""


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a scenario: where (dotted path, file, line) and what."""

    path: str
    message: str
    file: str | None = None
    line: int | None = None

    def render(self) -> str:
        where = ""
        if self.file:
            where = self.file + (f":{self.line}" if self.line else "") + " "
        path = f"{self.path}: " if self.path else ""
        return f"{where}{path}{self.message}"


class ConfigError(NetkfError, ValueError):
    """Bad user input: a scenario, an option, or a value a theorem cannot accept."""

    def __init__(self, problems: list[Problem] | str, file: str | None = None):
        if isinstance(problems, str):
            problems = [Problem("", problems)]
        if file is not None:
            problems = [p if p.file else replace(p, file=file) for p in problems]
        self.problems: list[Problem] = list(problems)
        super().__init__("\n".join(p.render() for p in self.problems))

    @classmethod
    def at(cls, path: str, message: str) -> "ConfigError":
        """A single problem at a dotted field path, e.g. ``ConfigError.at("analysis.M", "...")``."""
        return cls([Problem(path, message)])

    def prefixed(self, prefix: str) -> "ConfigError":
        """The same problems with ``prefix.`` in front of every path (used for nested blocks)."""
        probs = [replace(p, path=f"{prefix}.{p.path}" if p.path else prefix) for p in self.problems]
        return ConfigError(probs)


class TheoremConditionError(ConfigError):
    """A value outside what a theorem needs (e.g. ``M`` below ``M̄`` in Thm 3.8)."""


class ResultExistsError(NetkfError):
    """The result folder exists and ``--force`` was not given."""


class OutputError(NetkfError):
    """The result folder cannot be written or may not be replaced (not netkf's, read-only …)."""


class BusyError(NetkfError):
    """Another netkf run holds the lock of the same result folder or resume cache."""

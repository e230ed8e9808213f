"""What every artefact recipe receives and returns: :mod:`netkf_cli.core.artefact` (re-exported here)."""

from netkf_cli.core.artefact import Artefact, RunContext

__all__ = ["Artefact", "RunContext"]

"""What every artefact recipe receives and returns: :mod:`netkf_cli.artefact` (re-exported here)."""

from netkf_cli.artefact import Artefact, RunContext

__all__ = ["Artefact", "RunContext"]

"""The core layer: errors, tolerances, the one statistics module, the plant, the trace, the
pydantic building blocks and what every analysis receives and returns. Imports nothing of netkf
above it (import-linter layers contract, pyproject.toml)."""

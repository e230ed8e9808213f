"""YAML → Scenario: the pydantic scenario, its cross-block checks, sweeps, and what `netkf list`
shows. Built on recipes/, metrics/ and every layer below."""

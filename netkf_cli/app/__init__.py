"""The application layer: one run (runner), `netkf mind`, goldens, REPORT.md, `netkf reproduce`,
the Python API and the CLI. The top of the import graph."""

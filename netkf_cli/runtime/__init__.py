"""How runs execute and where results go: worker processes, chunked reproducible Monte Carlo,
atomic result folders, the shared figure style. Built on linalg/ and core/."""

"""The Kalman core: batched linear algebra, the one Kalman recursion (numpy reference and the
kernels generated per system), Riccati maps and the compiled reductions. Built on core/ only."""

"""Generic metrics over any compatible (channel, estimator) pair: distribution, mean_vs_time, compare."""

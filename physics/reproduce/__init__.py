"""Reproductions of the paper's results (benchmarks, not tests): Fig. 2 and Fig. 3."""

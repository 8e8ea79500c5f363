"""physfuse estimator: reading logs, the smoother, streaming and outputs."""

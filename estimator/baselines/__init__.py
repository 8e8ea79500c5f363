"""What users would otherwise run: Kalman filters with the physics forward dynamics as process
model, on the smoother's knots, sensors and noise settings."""

from estimator.baselines.filters import filter_estimate as filter_estimate

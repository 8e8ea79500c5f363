"""Residual-based contact diagnostics: where and when the physics does not add up.

    est, _ = estimate(config, log.measurements, settings)
    diagnosis = diagnose(config, log.measurements, est, settings)
    for event in diagnosis.events: ...

Stages: `unmodeled` (the physics residual of the estimate → per knot and body, the
information about an unmodeled force on it), `detect` (windowed likelihood-ratio test
calibrated on the log's own residuals → events: interval, body, force), `report` (events.json,
the terminal table, the estimate MCAP's /diagnostics topics).
"""

from estimator.diagnose.detect import Detection, DetectorSettings, Event, detect
from estimator.diagnose.diagnosis import Diagnosis, diagnose
from estimator.diagnose.unmodeled import UnmodeledForces, unmodeled_forces

__all__ = [
    "Detection",
    "DetectorSettings",
    "Diagnosis",
    "Event",
    "UnmodeledForces",
    "detect",
    "diagnose",
    "unmodeled_forces",
]

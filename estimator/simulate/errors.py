"""The simulator's user-facing error (a `PhysfuseError`: the CLI prints it as one line)."""

from estimator.errors import PhysfuseError


class SimulationError(PhysfuseError):
    """A scenario, its settings or its output cannot be used; the message names the value."""

"""Errors raised by the physics engine; each message names the bad value and what was expected."""


class PhysicsError(Exception):
    """Root of the physics engine's errors."""


class UnsupportedModelError(PhysicsError):
    """The model uses an option the analytic inverse cannot support."""


class InvalidStateError(PhysicsError):
    """A state (qpos, qvel, qacc, ctrl) is malformed: wrong shape, NaN or Inf."""

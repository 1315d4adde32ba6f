"""Error types of cdmp_ros. Every domain error derives from :class:`CdmpError`."""


class CdmpError(Exception):
    """Base class of every error raised by cdmp_ros on purpose."""


class ValidationError(CdmpError, ValueError):
    """An input (array, parameter, message field) is malformed; the message names it."""


class PrimitiveFileError(ValidationError):
    """A primitive file or message is malformed or violates its schema."""


class ConstraintSetError(ValidationError):
    """A constraint set is malformed or violates its schema."""


class Cancelled(CdmpError):
    """A long computation was asked to stop (e.g. an adaptation at node shutdown).

    An adaptation that was cancelled says where it was: ``state`` (its
    :class:`~cdmp_ros.core.adaptation.config.SolverState`: the best point of the inner loop it
    was in, with its multipliers; None when it had not started) and ``n_evaluations`` (of the
    Lagrangian, so far). A solve can resume from that state (the adapter's refinements,
    :mod:`cdmp_ros.core.adaptation.warm`)."""

    def __init__(self, message: str = '', state=None, n_evaluations: int = 0):
        super().__init__(message)
        self.state = state
        self.n_evaluations = int(n_evaluations)

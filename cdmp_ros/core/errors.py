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
    """A long computation was asked to stop (e.g. an adaptation at node shutdown)."""

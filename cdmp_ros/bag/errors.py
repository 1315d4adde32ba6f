"""Errors of the bag layer; all derive from :class:`cdmp_ros.core.errors.CdmpError`."""
from cdmp_ros.core.errors import CdmpError


class BagError(CdmpError):
    """A bag cannot be written or read as asked (missing directory, unknown topic, ...)."""


class BagFormatError(BagError):
    """The bag's bytes are not a valid MCAP / rosbag2 bag (bad magic, malformed record).

    Attributes
    ----------
    offset : int or None
        Byte offset in the ``.mcap`` file where the problem was found.
    """

    def __init__(self, message: str, offset=None):
        super().__init__(message)
        self.offset = offset


class BagTruncatedError(BagFormatError):
    """The file ends inside a record or before the footer (for example a crashed recording).

    ``cdmp bag recover`` turns such a file into a readable bag.
    """


class BagCrcError(BagFormatError):
    """A chunk, data-section or summary CRC does not match the bytes: the file is corrupted."""

"""The one exception type for mistakes a user can make (bad town, density, file, ...)."""


class BidError(Exception):
    """A user-facing error: its message is one line that names the fix.

    The CLI prints it as ``error: <message>`` and exits with status 2.
    """

"""The one exception type for mistakes a user can make (bad town, density, file, ...)."""


class BidError(Exception):
    """A user-facing error: its message is one line that names the fix.

    The CLI prints it as ``error: <message>`` and exits with status 2.
    """


def reason(e: BaseException) -> str:
    """Why a task failed, for a list of failures: a BidError's message as it is, anything
    else (a bug, a crashed worker) with its type."""
    return str(e) if isinstance(e, BidError) else f"{type(e).__name__}: {e}"

"""User-facing errors."""


class MCRLError(Exception):
    """A user-facing error: one line naming the problem and the fix."""


def one_line(exc: BaseException) -> str:
    """`exc` as one short line for an MCRLError message: ``Type: message``."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"[:130]

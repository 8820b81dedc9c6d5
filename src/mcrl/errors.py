"""User-facing errors."""


class MCRLError(Exception):
    """A user-facing error: one line naming the problem and the fix."""

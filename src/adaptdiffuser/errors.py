"""Errors a user can act on, reported by the CLI as one line and exit code 2 instead of a traceback."""


class StageError(ValueError):
    """A stage cannot go on with its inputs (for example, no behaviour policy scored inside its band); says why."""

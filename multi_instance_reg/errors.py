"""The one error type for bad input: its message names the problem and what to do."""


class InputError(ValueError):
    """Bad input from a user or a file. Tools print it as one line and exit non-zero."""

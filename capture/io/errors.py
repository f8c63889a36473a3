"""User-facing errors.

Every problem a user can fix (bad input, missing file, wrong option) raises :class:`CaptureError`
with a one-line message that says what is wrong and what to do. The command line prints the
message without a traceback and exits with a non-zero status; anything else is a bug.
"""


class CaptureError(Exception):
    """A problem with the user's input, reported as one line, exit status 2."""

    exit_code = 2

    def __init__(self, message: str):
        if "\n" in message:
            raise ValueError("CaptureError messages are one line")
        super().__init__(message)


class Interrupted(CaptureError):
    """The user interrupted a long job (Ctrl-C or SIGTERM) after its progress was saved."""

    exit_code = 130

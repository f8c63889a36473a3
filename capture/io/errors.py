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


def read_text_file(path, what: str) -> str:
    """The UTF-8 text of a user's file; one line when it is missing, a folder, unreadable or not UTF-8.

    ``what`` names the file for the user ("region file", "forehead file").
    """
    from pathlib import Path

    path = Path(path)
    if path.is_dir():
        raise CaptureError(f"{what} {path} is a folder; give the file")
    if not path.is_file():
        raise CaptureError(f"{what} {path} does not exist; check the path")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise CaptureError(f"{what} {path} is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except OSError as exc:
        raise CaptureError(f"cannot read {what} {path}: {exc.strerror or exc.__class__.__name__}") from None

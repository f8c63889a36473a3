"""The ``capture`` command line: one program, one sub-command per job.

Each sub-command is a thin module of :mod:`capture.commands` (``calib.cli`` for calibration) that parses
options and calls one function of its package; all are registered here. :func:`main` turns :class:`~capture.io.errors.CaptureError` into a one-line message
and a non-zero exit status, and an interrupt (Ctrl-C) into exit status 130 with a hint to resume.
Usage errors (a missing option, ``--seed abc``) and the OS errors a user can fix (disk full, read-only
or forbidden folder) are one line with exit status 2 as well. Library log output and warnings are
silenced (:mod:`capture.io.quiet`) unless ``--verbose`` is given anywhere on the command line.
"""

from __future__ import annotations

import errno
import sys
import warnings

import typer
from typer._click import exceptions as click_exceptions

from calib.cli import calibrate_command
from capture.commands.actor import actor_app
from capture.commands.batch import batch_command
from capture.commands.demo import demo_command
from capture.commands.detect import detect_command
from capture.commands.embed import embed_command
from capture.commands.fit3d import fit3d_command
from capture.commands.live import live_command
from capture.commands.retarget import retarget_command
from capture.commands.run import run_command
from capture.commands.synth import synth_command
from capture.io.errors import CaptureError

app = typer.Typer(
    name="capture",
    help="Monocular video face capture with anatomically constrained implicit face models (AIM).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
actor_app.command("embed")(embed_command)
app.add_typer(actor_app, name="actor")
app.command("calibrate")(calibrate_command)
app.command("synth")(synth_command)
app.command("run")(run_command)
app.command("detect")(detect_command)
app.command("fit3d")(fit3d_command)
app.command("demo")(demo_command)
app.command("retarget")(retarget_command)
app.command("batch")(batch_command)
app.command("live")(live_command)


#: OS errors that are the user's to fix (disk full, read-only or forbidden folder), reported as one line.
USER_OS_ERRORS = {errno.ENOSPC: "no space left on device: free some space", errno.EDQUOT: "disk quota exceeded: "
                  "free some space", errno.EROFS: "read-only file system: choose a folder you can write to",
                  errno.EACCES: "permission denied: choose a folder you can write to",
                  errno.EPERM: "operation not permitted: choose a folder you can write to",
                  errno.ENOTDIR: "a path component is a file, not a folder: choose another path"}


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 success, 2 user error, 130 interrupted)."""
    from capture.io.quiet import configure

    args = list(sys.argv[1:] if argv is None else argv)
    verbose = "--verbose" in args  # accepted anywhere on the line: `capture run ... --verbose`
    configure(verbose)
    try:
        with warnings.catch_warnings():
            if not verbose:  # libraries' warnings (torch, trimesh, ...) are noise to a user; --verbose shows them
                warnings.simplefilter("ignore")
            code = app(args=[a for a in args if a != "--verbose"], prog_name="capture", standalone_mode=False)
        return code if isinstance(code, int) else 0
    except click_exceptions.NoArgsIsHelpError as exc:
        print(exc.ctx.get_help() if exc.ctx is not None else "", file=sys.stderr)
        return 2
    except click_exceptions.ClickException as exc:  # a usage error: one line, like every other error
        where = f"capture {' '.join(exc.ctx.command_path.split()[1:])}".strip() if getattr(exc, "ctx", None) else "capture"
        message = " ".join(exc.format_message().split()).rstrip(".")
        print(f"capture: error: {message}; see '{where} --help'", file=sys.stderr)
        return exc.exit_code if exc.exit_code else 2
    except typer.Abort:
        print("capture: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except typer.Exit as exc:
        return exc.exit_code
    except CaptureError as exc:
        print(f"capture: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:
        if exc.errno not in USER_OS_ERRORS:
            raise
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"capture: error: {USER_OS_ERRORS[exc.errno]}{where}, then run the same command again (finished "
              f"work is kept)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("capture: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except SystemExit as exc:  # click's standalone mode ends every command with sys.exit
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return 0


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    run()

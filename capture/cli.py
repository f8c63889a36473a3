"""The ``capture`` command line: one program, one sub-command per job.

Each sub-command is a thin module of :mod:`capture.commands` (``calib.cli`` for calibration) that parses
options and calls one function of its package; all are registered here. :func:`main` turns :class:`~capture.io.errors.CaptureError` into a one-line message
and a non-zero exit status, and an interrupt (Ctrl-C) into exit status 130 with a hint to resume.
"""

from __future__ import annotations

import sys

import typer

from calib.cli import calibrate_command
from capture.commands.actor import actor_app
from capture.commands.batch import batch_command
from capture.commands.demo import demo_command
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
app.add_typer(actor_app, name="actor")
app.command("calibrate")(calibrate_command)
app.command("synth")(synth_command)
app.command("run")(run_command)
app.command("fit3d")(fit3d_command)
app.command("demo")(demo_command)
app.command("retarget")(retarget_command)
app.command("batch")(batch_command)
app.command("live")(live_command)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 success, 2 user error, 130 interrupted)."""
    try:
        app(args=argv, prog_name="capture", standalone_mode=True)
    except CaptureError as exc:
        print(f"capture: error: {exc}", file=sys.stderr)
        return exc.exit_code
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

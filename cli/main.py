"""Entry point of the ``dbh`` command: the typer app, whose commands are imported on first use.

Lives here: the command table only. Each command lives in its own ``cli/*_cmd.py`` module, imported
when that command runs (or when ``dbh --help`` lists them), so ``dbh measure`` never loads the
calibration, evaluation or training commands.
"""
from __future__ import annotations

import importlib

import typer
from typer.core import TyperGroup

__all__ = ["app", "main", "COMMANDS"]

#: command name -> (module in this package, function), in the order ``dbh --help`` lists them
COMMANDS = {
    "synth": ("synth_cmd", "synth"),
    "calibrate": ("calibrate_cmd", "calibrate"),
    "calibrate-pose": ("calibrate_cmd", "calibrate_pose"),
    "marker": ("marker_cmd", "marker"),
    "measure": ("measure_cmd", "measure"),
    "summary": ("summary_cmd", "summary"),
    "reconstruct": ("reconstruct_cmd", "reconstruct"),
    "eval": ("eval_cmd", "evaluate"),
    "bench": ("eval_cmd", "bench"),
    "depth": ("depth_cmd", "depth"),
    "eval-depth": ("depth_cmd", "eval_depth"),
    "train": ("train_cmd", "train"),
    "export": ("train_cmd", "export"),
    "train-pack": ("train_cmd", "train_pack"),
    "train-blend": ("train_cmd", "train_blend"),
}


class _LazyGroup(TyperGroup):
    """A typer group that imports a command's module only when the command is looked up."""

    def list_commands(self, ctx) -> list[str]:
        return list(super().list_commands(ctx)) + [n for n in COMMANDS if n not in self.commands]

    def get_command(self, ctx, name: str):
        if name not in self.commands and name in COMMANDS:
            mod, attr = COMMANDS[name]
            fn = getattr(importlib.import_module(f"{__package__}.{mod}"), attr)
            one = typer.Typer(add_completion=False)
            one.command(name)(fn)
            self.commands[name] = typer.main.get_command(one)
        return super().get_command(ctx, name)


app = typer.Typer(cls=_LazyGroup, add_completion=False, no_args_is_help=True,
                  help="monodbh: tree DBH and a 3D scene from one photo.")


@app.callback()
def _root() -> None:
    """monodbh: tree DBH and a 3D scene from one photo."""


@app.command()
def version() -> None:
    """Print the version."""
    from importlib.metadata import version as _v
    typer.echo(_v("monodbh"))


def main() -> None:
    """``dbh``: run the command; every failure ends as one ``error: ...`` line on stderr.

    Exit status: 0 success, 1 a failure the command reports (bad photo, camera file, output path),
    2 a usage error (unknown option, bad value: click's own status), 130 interrupted; an
    exception nobody expected is reported on one line as an internal error, status 3, with no
    traceback (``MONODBH_TRACEBACK=1`` shows it).
    """
    import os
    import sys

    try:                        # typer >= 0.25 vendors click
        from typer._click import exceptions as click_exc
    except ImportError:         # pragma: no cover - older typer on click
        from click import exceptions as click_exc

    _one_line_warnings()
    try:
        rc = app(standalone_mode=False)
    except click_exc.UsageError as exc:
        if exc.format_message().strip():        # (empty after the help of a bare 'dbh')
            hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            _error(f"{exc.format_message()}{hint}")
        sys.exit(exc.exit_code)
    except (typer.Abort, getattr(click_exc, "Abort", typer.Abort)):
        _error("aborted")
        sys.exit(130)
    except click_exc.ClickException as exc:
        _error(exc.format_message())
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        _error("interrupted")
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the last net: one line, never a traceback
        from monodbh.calib.errors import MonodbhError

        if os.environ.get("MONODBH_TRACEBACK"):
            raise
        if isinstance(exc, MonodbhError):
            _error(str(exc))
            sys.exit(1)
        _error(f"internal error: {type(exc).__name__}: {exc} (please report it with the command; "
               f"MONODBH_TRACEBACK=1 shows where)")
        sys.exit(3)
    sys.exit(rc if isinstance(rc, int) else 0)


def _error(message: str) -> None:
    import sys

    from monodbh.toolkit.outputs.paths import printable

    text = " ".join(printable(message).split())
    sys.stderr.write(f"error: {text}\n")
    sys.stderr.flush()


def _one_line_warnings() -> None:
    """Library warnings (PIL, scikit-image, onnxruntime's Python side) as ``warning: <message>``
    on one line, without the source line that Python prints by default."""
    import sys
    import warnings

    def show(message, category, filename, lineno, file=None, line=None):
        from monodbh.toolkit.outputs.paths import printable

        out = file or sys.stderr
        try:
            out.write(f"warning: {' '.join(printable(message).split())}\n")
        except (OSError, ValueError):
            pass

    warnings.showwarning = show

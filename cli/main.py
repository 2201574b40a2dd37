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
    "reconstruct": ("reconstruct_cmd", "reconstruct"),
    "eval": ("eval_cmd", "evaluate"),
    "bench": ("eval_cmd", "bench"),
    "depth": ("depth_cmd", "depth"),
    "eval-depth": ("depth_cmd", "eval_depth"),
    "train": ("train_cmd", "train"),
    "export": ("train_cmd", "export"),
    "train-pack": ("train_cmd", "train_pack"),
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
    app()

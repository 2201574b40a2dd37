"""Entry point of the ``dbh`` command."""
import typer

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="monodbh: tree DBH and a 3D scene from one photo.")


@app.command()
def version() -> None:
    """Print the version."""
    from importlib.metadata import version as _v
    typer.echo(_v("monodbh"))


# --- training-data commands (lazy: the generator is a training-only extra) ---------------------
from .synth_cmd import synth as _synth  # noqa: E402  (module imports nothing heavy)

app.command("synth")(_synth)


def main() -> None:
    app()

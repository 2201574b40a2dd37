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


# --- calibration commands (issue 2; logic in cli/calibrate_cmd.py, heavy imports lazy) --------
from .calibrate_cmd import calibrate as _calibrate, calibrate_pose as _calibrate_pose  # noqa: E402

app.command("calibrate")(_calibrate)
app.command("calibrate-pose")(_calibrate_pose)
# --- end calibration commands ------------------------------------------------------------------


# --- measuring commands (issue 6; logic in cli/measure_cmd.py, reconstruct_cmd.py, eval_cmd.py;
# those modules import only typer at top level, everything heavy inside the commands) ----------
from .eval_cmd import bench as _bench, evaluate as _evaluate  # noqa: E402
from .measure_cmd import measure as _measure  # noqa: E402
from .reconstruct_cmd import reconstruct as _reconstruct  # noqa: E402

app.command("measure")(_measure)
app.command("reconstruct")(_reconstruct)
app.command("eval")(_evaluate)
app.command("bench")(_bench)
# --- end measuring commands --------------------------------------------------------------------


# --- depth maps (issue 5) ---------------------------------------------------------------------
from .depth_cmd import depth as _depth, eval_depth as _eval_depth  # noqa: E402

app.command("depth")(_depth)
app.command("eval-depth")(_eval_depth)


# --- training commands (training-only extra; imports inside the commands) ---------------------
from .train_cmd import export as _export, train as _train, train_pack as _train_pack  # noqa: E402

app.command("train")(_train)
app.command("export")(_export)
app.command("train-pack")(_train_pack)
# --- end training commands ---------------------------------------------------------------------


def main() -> None:
    app()

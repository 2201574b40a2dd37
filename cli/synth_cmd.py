"""``dbh synth``: render a synthetic dataset folder (training-only; needs the ``synth`` extra)."""
from __future__ import annotations

from pathlib import Path

import typer


def parse_size(text: str) -> tuple[int, int]:
    """``"512"`` -> (512, 512); ``"640x480"`` -> (640, 480)."""
    try:
        if "x" in text.lower():
            w, h = text.lower().split("x")
            size = int(w), int(h)
        else:
            size = int(text), int(text)
    except ValueError:
        raise typer.BadParameter(f"size must be N or WxH, got {text!r}")
    if min(size) < 16 or max(size) > 8192:
        raise typer.BadParameter(f"size {size[0]}x{size[1]} out of range 16..8192")
    return size


def synth(
    out: Path = typer.Argument(..., help="Output folder (created; finished samples are kept and skipped)."),
    count: int = typer.Option(100, "--count", "-n", min=0, help="Number of samples."),
    seed: int = typer.Option(0, "--seed", "-s", help="Dataset seed (sample i has seed (seed, i))."),
    size: str = typer.Option("512", "--size", help="N or WxH pixels, e.g. 512 or 1280x960."),
    start: int = typer.Option(0, "--start", min=0, help="First sample index."),
    workers: int = typer.Option(0, "--workers", "-j", min=0, help="Processes (0 = all cores)."),
    no_distortion: bool = typer.Option(False, "--no-distortion", help="Render through a pinhole camera."),
    contact: bool = typer.Option(False, "--contact-sheet", help="Also write OUT/contact_sheet.png (16 samples)."),
    marker: str = typer.Option("rope", "--marker", help="The 1.3 m marker: rope (5-15 mm, the default), strap "
                               "(a flat red strap 20-50 mm wide) or mixed (either)."),
    stand: str = typer.Option("forest", "--stand", help="forest (a closed stand, the default), park (open-grown "
                              "trees with dense crowns on a lawn, seen from 3-25 m) or mixed (either)."),
    foot: str = typer.Option("plain", "--foot", help="plain (the default); clutter: grass tufts round the "
                             "roped stem's foot on every scene and a low bush beside it on 40 %; hidden: tufts "
                             "0.05-0.6 m high and a bush in front of the foot on 35 % (stem-base training)."),
    view: str = typer.Option("level", "--view", help="level (the camera at about breast height, the "
                             "default), upward (from 1-5 m, up the trunk into the crown, 30-70 degrees up; trunk "
                             "training), mixed (upward on a third) or protocol (the photo README's \"Taking the "
                             "photo\" asks for: an 8-15 mm rope or the strap, knot toward or away from the camera, "
                             "2-6 m away, rope and foot in the frame)."),
    look: str = typer.Option("default", "--look", help="default; randomized: the same scenes with their colours, "
                             "texture contrast, light and camera response randomised (for training); or heldout: "
                             "the same scenes with textures cut from the real photos, another light and another "
                             "camera (for evaluation only: no training command accepts it; textures from "
                             "$MONODBH_REAL_TREES or $MONODBH_SHARED_DATA/real_trees)."),
) -> None:
    """Render procedural forest scenes with exact ground truth (depth, panoptic labels, rope, z1/z2, DBH)."""
    try:
        from monodbh.models.synthetic.dataset import contact_sheet, synthesize
    except ImportError as e:  # pragma: no cover - depends on the install
        typer.echo(f"error: dbh synth needs the 'synth' extra (pip install 'monodbh[synth]'): {e}", err=True)
        raise typer.Exit(1)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from monodbh.models.synthetic.scene import FEET, MARKERS, STANDS, VIEWS
    W, H = parse_size(size)
    if marker not in MARKERS:
        raise typer.BadParameter(f"expected {', '.join(MARKERS[:-1])} or {MARKERS[-1]}, got {marker!r}",
                                 param_hint="--marker")
    if stand not in STANDS:
        raise typer.BadParameter(f"expected {', '.join(STANDS[:-1])} or {STANDS[-1]}, got {stand!r}",
                                 param_hint="--stand")
    if foot not in FEET:
        raise typer.BadParameter(f"expected {' or '.join(FEET)}, got {foot!r}", param_hint="--foot")
    if view not in VIEWS:
        raise typer.BadParameter(f"expected {', '.join(VIEWS[:-1])} or {VIEWS[-1]}, got {view!r}",
                                 param_hint="--view")
    from monodbh.models.synthetic.looks import HELDOUT, LOOKS
    if look not in LOOKS:
        raise typer.BadParameter(f"expected one of {', '.join(LOOKS)}, got {look!r}", param_hint="--look")
    if look == HELDOUT:
        from monodbh.models.synthetic.looks import attribution_text, photo_textures
        try:
            tex = photo_textures()
        except FileNotFoundError as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(1)
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "ATTRIBUTION.md").write_text(attribution_text(tex))
    with Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), transient=True) as prog:
        task = prog.add_task(f"rendering {W}x{H}", total=count)
        res = synthesize(out, count, seed, (W, H), start=start, workers=workers or None,
                         distortion=not no_distortion, marker=marker, look=look, stand=stand, foot=foot,
                         view=view, progress=lambda r: prog.advance(task))
    typer.echo(f"{res['count']} samples in {res['seconds']:.1f} s ({res['samples_per_s']:.2f} samples/s) -> {out}",
               err=True)
    if contact:
        png = contact_sheet(out, Path(out) / "contact_sheet.png")
        typer.echo(f"contact sheet: {png}", err=True)

"""The ``pattern`` and ``inspect`` subcommands (see :mod:`lightfield_jax.app.cli`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightfield_jax.app.arguments import arg, positive_int, positive_scale
from lightfield_jax.app.cli import command
from lightfield_jax.app.messages import about_capture, command_progress, say, shown_path, warn
from lightfield_jax.app.outputs import check_command_outputs

# --------------------------------------------------------------------------- pattern


@command(
    "pattern",
    "write the projector's stripe images and a capture.yaml template for them",
    arg("--width", type=positive_int, required=True, help="projector width (pixels)"),
    arg("--height", type=positive_int, required=True, help="projector height (pixels)"),
    arg(
        "--period",
        type=positive_int,
        default=6,
        help="stripe period in projector pixels (%(default)s)",
    ),
    arg(
        "--lit",
        type=positive_int,
        default=3,
        help="lit projector rows per period (%(default)s)",
    ),
    arg(
        "--camera-px-per-projector-px",
        type=positive_scale,
        default=1.0,
        metavar="S",
        help="the stripes' size on the camera over their size on the projector, measured "
        "on the medium (default %(default)g): capture.yaml's period and lit are in camera "
        "pixels, the model's unit",
    ),
    arg("--shifts", type=positive_int, help="shifted images (default: the period)"),
    arg(
        "--orientation",
        choices=("rows", "columns"),
        default="rows",
        help="stripes along projector rows or columns (%(default)s)",
    ),
    arg(
        "--out",
        metavar="DIR",
        required=True,
        help="output folder (created; its stripe, white and black images replaced; one "
        "holding a capture.yaml is refused)",
    ),
)
def _pattern(args: argparse.Namespace) -> None:
    """Write into DIR the images to project, 8-bit PNG of WIDTHxHEIGHT:

      stripe_XX.png  the shifted stripes: in stripe_XX, projector row r (column, with
                     --orientation columns) is white iff (r + phase) mod period < lit;
                     phases spread evenly over the period
      white.png      all white (finds the medium; with black.png, the black level)
      black.png      all black (the projector's black level)
      capture.yaml   a capture file for the camera's images of them: replace the
                     camera_*.tif names by your files; the ROI, entry wall,
                     direction, stripe phases and black level are measured from the
                     images (auto); every key is explained in a comment

    Nothing is written unless the whole command succeeds."""
    from lightfield_jax.app.outputs import OutputError
    from lightfield_jax.capture.pattern import (
        camera_stripes,
        check_size,
        pattern_memory,
        pattern_phases,
        write_patterns,
    )
    from lightfield_jax.files import atomic_directory
    from lightfield_jax.runtime.memory import check_memory

    check_command_outputs(
        folders=[args.out],
        folder_names=("stripe_*.png", "white.png", "black.png", "capture.yaml"),
        marker="capture.yaml",  # without its template, a folder's frames are a camera's
        writer="pattern",
    )
    out = Path(args.out)
    if (out / "capture.yaml").exists():
        # A capture file is edited by hand (its image names, keys): never a template's.
        raise OutputError(
            f"{out / 'capture.yaml'}: exists (a capture file, maybe edited); choose another "
            "folder, or move it away to write the template"
        )
    check_size(args.width, args.height, args.period)
    phases = pattern_phases(args.period, args.lit, args.shifts)
    scale = args.camera_px_per_projector_px
    camera_period, camera_lit = camera_stripes(args.period, args.lit, scale)
    check_memory(
        pattern_memory(args.width, args.height, len(phases)),
        f"pattern: {len(phases) + 2} images of {args.width}x{args.height}",
    )
    with atomic_directory(out) as staging:
        files = write_patterns(
            staging,
            args.width,
            args.height,
            args.period,
            args.lit,
            args.shifts,
            args.orientation,
            scale,
        )
    say(
        args,
        f"wrote {len(files)} files to {shown_path(out)}: {len(phases)} stripe images (period "
        f"{args.period}, lit {args.lit}, phases {list(phases)}, {args.orientation}), white.png, "
        "black.png, capture.yaml"
        + (
            f" (period {camera_period}, lit {camera_lit} camera px at {scale:g} camera px per "
            "projector px)"
            if scale != 1
            else ""
        ),
    )


# --------------------------------------------------------------------------- inspect


@command(
    "inspect",
    "show what the pipeline sees in a capture before fitting it",
    arg("capture", metavar="CAPTURE.yaml", help="a capture file (see README)"),
    arg("--plot", metavar="FIG.png", help="also write the figure"),
    arg("--json", metavar="FILE", help="also write the findings as JSON"),
    arg(
        "--response",
        metavar="FILE.csv",
        help="exposure brackets: write the camera response the merge used (e.g. recovered "
        "by response: auto), a table that response: FILE.csv reads",
    ),
)
def _inspect_command(args: argparse.Namespace) -> int | None:
    """Load a capture (measuring what it leaves auto), separate it, and print: the
    medium's ROI, the entry wall, the light's direction, the stripe phases, the black
    level, the masked pixels and, per channel, the direct light's SNR along the beam.
    --plot draws the frame with the ROI, entry wall and direction, the separated direct
    and multiple images, the saturation mask and the SNR along the beam; for exposure
    brackets also a merged image, the response curve and the clipped samples. Exit
    status 1, with a warning, when a channel is unusable for a fit (no direct light at
    the entry wall, or its SNR never usable)."""
    from lightfield_jax.app.outputs import staged_files
    from lightfield_jax.capture.inspect import inspect_capture
    from lightfield_jax.capture.loading import load_capture
    from lightfield_jax.capture.paths import capture_files
    from lightfield_jax.files import atomic_write_json

    check_command_outputs(
        files=[args.plot, args.json, args.response],
        inputs=capture_files(args.capture),
        plots=[args.plot] if args.plot else [],
        json=[("--json", args.json, " (the figure: --plot FIG.png)")],
    )
    plot = Path(args.plot) if args.plot else None
    out = Path(args.json) if args.json else None
    response = Path(args.response) if args.response else None
    if response is not None and response.suffix.lower() == ".npy":
        # The table is text; response: FILE.npy would read it back as a NumPy array.
        raise ValueError(
            f"--response: {response}: the table is written as text (CSV), which a .npy "
            "name would have read back as a NumPy array; name it .csv"
        )
    capture = load_capture(args.capture)
    if response is not None and capture.brackets is None:
        raise ValueError(f"--response: {args.capture} has no exposure brackets")
    with (
        command_progress(args, "inspect") as stage,
        about_capture(capture),
        staged_files() as write,
    ):
        stage("separate")
        inspection = inspect_capture(capture)
        if plot is not None:
            stage("plot")
            from lightfield_jax.viz import plot_inspect

            plot_inspect(inspection, write(plot))
        if out is not None:
            atomic_write_json(write(out), inspection.to_dict())
        if response is not None:
            from lightfield_jax.capture.response import write_response

            write_response(write(response), capture.brackets.response, capture.channel_names)
    say(args, inspection.summary())
    written = [f for f in (plot, out, response) if f is not None]
    if written:
        say(args, f"wrote {', '.join(shown_path(f) for f in written)}")
    problems = inspection.problems()
    for problem in problems:
        warn(args, f"{capture.source}: {problem}")
    return 1 if problems else None

"""The ``render`` and ``experiment`` subcommands (see :mod:`lightfield_jax.app.cli`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lightfield_jax.app.arguments import arg, dask_arguments, positive_int
from lightfield_jax.app.cli import command
from lightfield_jax.app.messages import command_progress, say, shown_path, warn
from lightfield_jax.app.outputs import check_command_outputs

# --------------------------------------------------------------------------- render

# The names render writes into its folder (see its help).
RENDER_FILES = ("bounces.npy", "bounces.exr", "lightfield.npy", "render.json", "*.png")


@command(
    "render",
    "render a fitted medium's per-bounce images and light fields in its capture's geometry",
    arg("results", metavar="RESULTS.json", help="a results file of lightfield-jax fit"),
    arg(
        "--out",
        metavar="DIR",
        required=True,
        help="output folder (created; a rerun replaces its files; a folder holding "
        "files render would replace that it did not write is refused)",
    ),
    arg(
        "--plot",
        action="store_true",
        help="also write the paper's figures: bounce_images.png, bounce_profiles.png, "
        "lightfield.png",
    ),
    arg(
        "--compact",
        action="store_true",
        help="write bounces.npy and render.json only (no bounces.exr, no lightfield.npy)",
    ),
)
def _render_command(args: argparse.Namespace) -> None:
    """Render the medium a fit recovered (RESULTS.json names its capture, whose entry
    wall and light direction are used) under full illumination, on the fit's model
    (its region of the medium ROI, theta bins, bounces, geometry), and write into DIR
    (one subfolder per channel when the results hold several):

      bounces.npy     float32 [K, H, W] per-bounce images (index k-1 holds I_k),
                      fitted gain included
      bounces.exr     channels I1..IK (not with --compact)
      lightfield.npy  float32 [K+1, H, W, n_theta] L_0..L_K, radiance per radian
                      (left out, with a warning, above 5e7 floats; not with --compact)
      render.json     the medium, model region, illumination; fit_converged (false,
                      with fit_warning, for a fit that did not converge: rendered
                      all the same, with a warning)
      *.png           with --plot: the bounce images, each bounce's profile along
                      the light, the light fields with direction glyphs

    Nothing is written unless the whole command succeeds."""
    from lightfield_jax.capture.views import (
        read_results,
        render_folders,
        render_inputs,
        render_results,
    )
    from lightfield_jax.files import atomic_directory

    data, source = read_results(args.results)
    # Each channel's subfolder is checked like DIR: another command's outputs there
    # (simulate's bounces.npy beside its metadata.json) would be replaced, and so would
    # the capture's own files (a stack named lightfield.npy).
    check_command_outputs(
        folders=[args.out, *render_folders(data, source, Path(args.out))],
        inputs=[args.results, *render_inputs(data, source)],
        folder_names=RENDER_FILES,
        marker="render.json",
        writer="render",  # a folder without render.json holds the user's own files
    )
    out = Path(args.out)
    with command_progress(args, "render") as stage, atomic_directory(out) as staging:
        files, notes = render_results(
            data,
            source,
            staging,
            plot=args.plot,
            stage=stage,
            warn=lambda t: warn(args, t),
            compact=args.compact,
        )
    for note in notes:
        warn(args, note)
    say(args, f"wrote {len(files)} files to {shown_path(out)}: {', '.join(map(shown_path, files))}")


# --------------------------------------------------------------------------- experiment


@command(
    "experiment",
    "run a config-driven experiment (experiments/NAME.py with configs/NAME.yaml)",
    arg("config", metavar="CONFIG.yaml", help="an experiment config (configs/)"),
    arg("--out", metavar="DIR", help="results folder (default: results/NAME)"),
    arg("--reduced", action="store_true", help="the config's reduced size (as the tests run)"),
    arg(
        "--max-cells",
        type=positive_int,
        default=None,
        metavar="N",
        help="the most cells (units of work: the product of the config's lists' lengths) "
        "a run may sweep (default: 10000); a larger config is refused before it starts",
    ),
    *dask_arguments("parallel sweeps"),
)
def _experiment(args: argparse.Namespace) -> None:
    """Run an experiment: it writes data (JSON/CSV) and figures (PNG) into DIR, plus
    summary.json with the config, software versions, machine and date. The config is
    checked whole before any work; a run that fails publishes nothing into DIR (exit
    status 1 when the experiment itself fails, 2 for a bad config). A rerun into the
    same DIR resumes from the work already stored in DIR/cache."""
    from lightfield_jax.app.experiment import (
        ExperimentError,
        load_experiment_config,
        run_experiment,
    )
    from lightfield_jax.app.experiment_config import MAX_CELLS, check_cells
    from lightfield_jax.app.messages import PROG, one_line

    config = Path(args.config)  # a config inside DIR named like an output is kept
    data = load_experiment_config(config, args.reduced)
    limit = MAX_CELLS if args.max_cells is None else args.max_cells
    cells = check_cells(data, args.config, limit)  # refused here, before any work
    out = args.out
    if out is None:  # the default folder is checked like one given
        out = str(Path("results") / str(data["experiment"]))
    check_command_outputs(
        folders=[out],
        inputs=[config] if config.is_file() else [],
        folder_names=("*.json", "*.csv", "*.png", "*.npz"),
        marker="summary.json",
        writer="experiment",  # a folder without summary.json holds the user's own files
    )
    say(args, f"experiment {data['experiment']}: about {cells} cells of work")
    try:
        with command_progress(args, "experiment") as stage:
            record = run_experiment(
                args.config,
                out,
                reduced=args.reduced,
                progress=stage,
                max_cells=limit,
                scheduler=args.scheduler,
                workers=args.workers,
                allow_large=args.allow_large,
                say=lambda m: say(args, m),
            )
    except ExperimentError as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {args.config}: {one_line(str(e))}", file=sys.stderr)
        return 1
    say(args, json.dumps(record["summary"], indent=1, default=str)[:4000])
    say(args, f"experiment {record['experiment']} done in {record['seconds']:.1f} s")

"""The ``fit`` subcommand (see :mod:`lightfield_jax.app.cli`)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from lightfield_jax.app.arguments import (
    XLA_CACHE_HELP,
    arg,
    dask_arguments,
    positive_int,
    positive_seconds,
    use_xla_cache,
)
from lightfield_jax.app.cli import command
from lightfield_jax.app.fit_report import (
    TWO_STEP_CAVEAT,
    TWO_STEP_METHODS,
    channel_summary,
    figure_names,
    fit_figures,
    fit_record,
    fit_summary,
    say_above_progress,
    truth_lines,
    truth_phase_note,
)
from lightfield_jax.app.messages import (
    PROG,
    about_capture,
    command_progress,
    say,
    shown_path,
    warn,
)
from lightfield_jax.app.outputs import check_command_outputs
from lightfield_jax.app.signals import TIME_LIMIT_STATUS, stop_after

# The fit's memory estimate (fit_memory) and its constants, named here as before.
from lightfield_jax.runtime.memory import FIT_N_THETA as FIT_N_THETA
from lightfield_jax.runtime.memory import RENDER_CELLS_PER_PIXEL as RENDER_CELLS_PER_PIXEL


def _max_steps(text: str) -> int:
    """``--max-steps``: a positive integer within the solvers' count (else the refusal
    named the capture file, after its load, for the command line's value)."""
    from lightfield_jax.inverse.settings import MAX_ITERATIONS

    value = positive_int(text)
    if value > MAX_ITERATIONS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_ITERATIONS:.0e}, got {text!r}")
    return value


@command(
    "fit",
    "recover sigma_t, sigma_s and g from a stripe capture",
    arg(
        "capture",
        nargs="+",
        metavar="CAPTURE.yaml",
        help="a capture file (see README); several, or a folder of them, are fitted in "
        "parallel on Dask (--out is then a folder)",
    ),
    arg(
        "--method",
        choices=("joint", "gradient", "grid"),
        default="joint",
        help="joint: raw images (default); gradient/grid: the paper's two-step method",
    ),
    arg(
        "--channel",
        action="append",
        metavar="NAME",
        help="fit only this channel of those the capture file's channel key loads "
        "(repeatable; default: all of them)",
    ),
    arg(
        "--out",
        metavar="FILE",
        help="JSON results (default: results.json); for several captures a folder "
        "(default: results/) with one FILE per capture, summary.csv and summary.json",
    ),
    arg(
        "--plot",
        metavar="FIG.png",
        help="also write the profiles and residual figure; with several channels FIG.png "
        "shows sigma_t, sigma_s, g per channel and FIG_<channel>.png each one's profiles",
    ),
    arg(
        "--phase",
        choices=("paper", "normalized"),
        help="phase convention of the model (default: the capture file's fit.phase, else "
        "normalized: energy-conserving, for every medium; paper: the paper's own, which "
        "has no answer for forward media of high albedo such as milk)",
    ),
    arg(
        "--max-steps",
        type=_max_steps,
        metavar="N",
        help="iteration limit of the solves (default: the fit setting max_steps)",
    ),
    arg(
        "--time-limit",
        type=positive_seconds,
        metavar="SECONDS",
        help="stop the fit after this long (from its start, after loading), exit status "
        f"{TIME_LIMIT_STATUS}, nothing written (default: no limit); for several captures "
        "each capture's limit (one past it is reported failed)",
    ),
    arg("--no-xla-cache", action="store_true", help=XLA_CACHE_HELP),
    *dask_arguments("several captures"),
)
def _fit(args: argparse.Namespace) -> int | None:
    """Fit a capture and write FILE (keys: sigma_t, sigma_s, sigma_a, g, albedo, gain,
    black_level, uncertainty, correlation, method, converged, iterations, residual,
    seconds, model; per channel when several). Exit status 1, with the results
    written and a warning, when a solve does not converge."""
    from lightfield_jax.app.outputs import staged_files
    from lightfield_jax.capture.keys import fit_phase
    from lightfield_jax.capture.loading import load_capture
    from lightfield_jax.capture.paths import capture_files
    from lightfield_jax.files import atomic_write_json
    from lightfield_jax.inverse.capture_fit import fit_capture
    from lightfield_jax.inverse.options import FitOptions
    from lightfield_jax.runtime.memory import check_memory, fit_memory

    if len(args.capture) > 1 or Path(args.capture[0]).is_dir():
        from lightfield_jax.app.cmd_batch import fit_batch

        return fit_batch(args)
    _single_only(args)
    args.capture = args.capture[0]
    args.out = "results.json" if args.out is None else args.out
    inputs = capture_files(args.capture)
    check_command_outputs(
        files=[args.out, args.plot],
        inputs=inputs,
        plots=[args.plot] if args.plot else [],
        json=[("--out", args.out, " (the figure: --plot FIG.png)")],
    )
    out = Path(args.out)
    use_xla_cache(args)
    capture = load_capture(args.capture)
    channels = args.channel or capture.channel_names
    figures = figure_names(Path(args.plot), channels) if args.plot else []
    check_command_outputs(files=[out, *figures], inputs=inputs)
    args.phase = args.phase or fit_phase(capture)
    if capture.truth and (note := truth_phase_note(capture, args.phase)) is not None:
        warn(args, note)
    h, w = capture.shape
    defaults = FitOptions(**capture.fit_options)
    check_memory(
        fit_memory(capture.images.size, capture.n_images, h, w, defaults.model),
        f"{capture.source}: the fit",
    )
    # What loading measured or doubted (a pattern.lit the stripes contradict makes the
    # fit slow and wrong): said before the fit's minutes, not after.
    for note in capture.notes:
        say(args, f"note: {note}")
    with command_progress(args, f"fit ({args.method})") as stage, about_capture(capture):
        limits = {} if args.max_steps is None else {"max_steps": args.max_steps}
        doing, fit_notes = [""], []

        def staged(message: str) -> None:
            if message.startswith("note: ") or re.match(r"\[[^]]*\] note: ", message):
                fit_notes.append(message)  # said with the summary: the display is erased
                return
            doing[0] = message.strip()
            stage(message)

        shown = []

        def finished(name: str, r) -> None:
            # Each channel's result when it is there (an RGB fit runs for minutes per
            # channel), with the notes said while it was fitted.
            if len(channels) < 2:
                return
            say_above_progress(args, [*fit_notes, channel_summary(name, r)])
            fit_notes.clear()
            shown.append(name)

        with stop_after(args.time_limit, PROG, "the fit", lambda: doing[0]):
            fit = fit_capture(
                capture,
                args.method,
                channels=args.channel,
                progress=staged,
                on_result=finished,
                phase=args.phase,
                **limits,
            )
        figures = figure_names(Path(args.plot), fit.channels) if args.plot else []
        result, compared = fit_record(capture, fit, args.method, args.phase)
        try:
            with staged_files() as write:
                if figures:
                    stage("plot")
                    fit_figures(capture, fit, figures, write)
                atomic_write_json(write(out), result)
        except OSError:
            # A full disk must not lose the fit's minutes: its values on the screen.
            say(args, f"not written: {shown_path(out)}; the fit:\n{fit_summary(fit)}", always=True)
            raise
    for note in fit_notes:
        say(args, note)
    if not shown:
        say(args, fit_summary(fit))
    for line in truth_lines(fit, compared):
        say(args, line)
    if args.method in TWO_STEP_METHODS:
        say(args, f"note: {TWO_STEP_CAVEAT}")
    say(args, f"wrote {', '.join(shown_path(f) for f in [out, *figures])}")
    if not fit.converged:  # its reasons too (the summary has them, but -q silences it)
        why = "; ".join(
            f"[{name}] {'; '.join(r.reasons) or r.message}"
            for name, r in zip(fit.channels, fit.results, strict=True)
            if not r.converged
        )
        warn(
            args,
            f"the fit did not converge ({why}): results were written with converged: false",
        )
        return 1
    return None


def _single_only(args: argparse.Namespace) -> None:
    """The options of a batch (several captures) refused for one capture file."""
    for option, value in (
        ("--scheduler", args.scheduler),
        ("--workers", args.workers),
        ("--allow-large", args.allow_large or None),
    ):
        if value is not None:
            raise ValueError(f"{option}: for several captures (or a folder of them) only")

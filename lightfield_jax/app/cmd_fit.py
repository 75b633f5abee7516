"""The ``fit`` and ``demo`` subcommands (see :mod:`lightfield_jax.app.cli`)."""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Sequence
from pathlib import Path

from lightfield_jax.app.arguments import (
    XLA_CACHE_HELP,
    arg,
    dask_arguments,
    positive_int,
    positive_seconds,
    use_xla_cache,
    xla_cache_folder,
)
from lightfield_jax.app.cli import DEMO_CONFIG, command
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

# --------------------------------------------------------------------------- fit


def fit_summary(fit) -> str:
    return "\n".join(
        _channel_summary(name, r) for name, r in zip(fit.channels, fit.results, strict=True)
    )


def _channel_summary(name: str, r) -> str:
    """One channel's result line."""
    from lightfield_jax.inverse.trust import CONSISTENCY_P
    from lightfield_jax.scene.geometry import describe_geometry

    u = r.uncertainty
    split = [k for k, v in r.consistency.items() if v["p"] < CONSISTENCY_P]
    limited = ""
    if r.model_limited:
        limited = "; model-limited (± is mostly the model's error" + (
            f": the capture's {' and '.join(split)} parts disagree)" if split else ")"
        )
    return (
        f"[{name}] {r.method}: sigma_t {r.sigma_t:.5g} ± {u.get('sigma_t', float('nan')):.2g}, "
        f"sigma_s {r.sigma_s:.5g} ± {u.get('sigma_s', float('nan')):.2g}, "
        f"g {r.g:.4f} ± {u.get('g', float('nan')):.2g} (per px; albedo {r.albedo:.3f}, "
        f"rho {r.rho:.3f}); {'converged' if r.converged else 'NOT CONVERGED: ' + r.message}"
        f"{limited} in {r.iterations} iterations, {r.seconds['total']:.1f} s "
        f"(compile {r.seconds['compile']:.1f} s); model {describe_geometry(r.model)}, "
        f"{r.model['width']}x{r.model['height']}, n_theta {r.model['n_theta']}, "
        f"K {r.model['bounces']}"
    )


def _say_above_progress(args: argparse.Namespace, lines: list[str]) -> None:
    """``lines`` on stdout now (flushed: a log file shows them while the fit goes on),
    clearing a progress bar on the terminal first."""
    import sys

    if args.quiet or not lines:
        return
    from tqdm import tqdm

    with tqdm.external_write_mode(file=sys.stdout):
        print("\n".join(lines), flush=True)


def _against_truth(capture, fit, phase: str) -> list[dict]:
    """Per fitted channel, each parameter the capture's truth gives: the error (σt, σs
    in %, g absolute) and in units of the reported total 1σ. A σt or σs whose truth is
    0 (no relative error) gets its absolute error, marked ``"absolute": true``. A σs
    whose truth is in another phase convention than the fit's ``phase`` is not compared
    (:func:`_truth_phase_note`)."""
    from lightfield_jax.capture.keys import truth_for

    out = []
    for name, r in zip(fit.channels, fit.results, strict=True):
        truth = truth_for(capture.truth, capture.channel_names.index(name)) or {}
        e = {}
        for k in ("sigma_t", "sigma_s", "g"):
            if k not in truth or (k == "sigma_s" and truth.get("phase", phase) != phase):
                continue
            value, true, sd = getattr(r, k), truth[k], r.uncertainty.get(k, float("nan"))
            diff = value - true
            absolute = k == "g" or true == 0
            e[k] = {
                "error": diff if absolute else 100 * diff / true,
                "sigmas": diff / sd if sd and sd == sd else float("nan"),
            }
            if absolute and k != "g":
                e[k]["absolute"] = True
        out.append(e)
    return out


def _truth_phase_note(capture, phase: str) -> str | None:
    """What to say where the capture's truth is in another phase convention than the
    fit's: its σs is not compared (``fit --phase normalized`` of a ``paper`` truth
    would print σs -38 %, -186 sigma, for a fit that found the medium)."""
    from lightfield_jax.capture.keys import truth_for

    phases = {
        (truth_for(capture.truth, i) or {}).get("phase", phase)
        for i in range(len(capture.channel_names))
    }
    others = sorted(str(p) for p in phases - {phase})
    if not others:
        return None
    return (
        f"{capture.source}: truth.phase is {', '.join(others)}, the fit's --phase {phase}: "
        "sigma_s is not compared with the truth (the conventions' sigma_s differ by the "
        "phase function's integral)"
    )


def _error_unit(k: str, v: dict) -> str:
    """The unit of an ``_against_truth`` error: % (relative), per px (absolute: the truth
    is 0) or none (g)."""
    if k == "g":
        return ""
    return " per px (truth 0)" if v.get("absolute") else " %"


def _figure_names(plot: Path, channels: Sequence[str]) -> list[Path]:
    """FIG.png for one channel; FIG.png and FIG_<channel>.png each for several."""
    if len(channels) == 1:
        return [plot]
    from lightfield_jax.checks import one_path_part

    for name in channels:  # else pathlib's "Invalid name 'fit_a/b.png'", naming nothing
        if not one_path_part(name):
            raise ValueError(
                f"--plot: the images' channel {name!r} cannot name a figure "
                f"{plot.stem}_<channel>{plot.suffix} (a path separator); fit without --plot, "
                "or one channel (--channel) at a time"
            )
    return [plot] + [plot.with_name(f"{plot.stem}_{name}{plot.suffix}") for name in channels]


def _fit_figures(capture, fit, figures: list[Path], write) -> None:
    """FIG.png: the profiles and residuals of the fit; with several channels, FIG.png
    holds σt, σs, g per channel and FIG_<channel>.png each channel's profiles. Each
    figure is written to ``write(target)`` (a staged temporary)."""
    from lightfield_jax.capture.keys import truth_for
    from lightfield_jax.viz import plot_channels, plot_fit

    if len(fit.channels) == 1:
        i = capture.channel_names.index(fit.channels[0])
        plot_fit(
            capture.images[..., i],
            capture.pattern,
            fit.results[0],
            write(figures[0]),
            **_shown(capture, i),
        )
        return
    truth = None
    if capture.truth:
        truth = [truth_for(capture.truth, capture.channel_names.index(n)) for n in fit.channels]
    plot_channels(fit, write(figures[0]), pixel_size_mm=capture.pixel_size_mm, truth=truth)
    for name, result, target in zip(fit.channels, fit.results, figures[1:], strict=True):
        i = capture.channel_names.index(name)
        plot_fit(
            capture.images[..., i], capture.pattern, result, write(target), **_shown(capture, i)
        )


def _shown(capture, i: int) -> dict:
    """What plot_fit shows beside the fit: channel i's mask and the capture's truth."""
    from lightfield_jax.capture.keys import truth_for
    from lightfield_jax.inverse.capture_fit import _channel_mask

    return {"mask": _channel_mask(capture, i), "truth": truth_for(capture.truth, i)}


# The two-step methods separate the direct light first; on stripe captures the
# separation is biased (the multiple light is not the same under every shift), and
# their ± (the noise's spread) says nothing of it.
TWO_STEP_METHODS = ("grid", "gradient")
TWO_STEP_CAVEAT = (
    "the two-step methods (grid, gradient) carry the separation bias on stripe "
    "captures: their ± are statistical only (noise), not the error, which can be far "
    "larger; use --method joint (the raw images) for unbiased estimates"
)


def _label_two_step(method: str, result: dict) -> dict:
    """``result`` with, for a two-step method, the caveat and what its ± mean."""
    if method in TWO_STEP_METHODS:
        result["uncertainty_kind"] = "statistical only (separation bias not included)"
        result["caveat"] = TWO_STEP_CAVEAT
    else:  # joint: the noise ⊕ the model's error (uncertainty_statistical, _model)
        result["uncertainty_kind"] = "total (statistical and the model's error)"
    return result


def _roi_record(capture) -> dict:
    """results.json's ``medium_roi``: the ROI, where it came from, how each edge was
    found (wall, frame, faded) and what was done about a faded far edge."""
    det = capture.detected
    measured = det is not None and "roi" not in det.given
    given = "given" if capture.roi is not None else "whole frame"
    return {
        "roi": None if capture.roi is None else list(capture.roi),
        "source": "auto" if measured else given,
        "edges": det.edges if measured else None,
        "faded": det.faded if measured else None,
        "note": det.fade_note() if measured and det.faded else None,
    }


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
        type=positive_int,
        metavar="N",
        help="iteration limit of the solves (default: FitOptions.max_steps)",
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
    from lightfield_jax.capture.keys import capture_files, fit_phase
    from lightfield_jax.capture.loading import load_capture
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
    figures = _figure_names(Path(args.plot), channels) if args.plot else []
    check_command_outputs(files=[out, *figures], inputs=inputs)
    args.phase = args.phase or fit_phase(capture)
    if capture.truth and (note := _truth_phase_note(capture, args.phase)) is not None:
        warn(args, note)
    h, w = capture.shape
    defaults = FitOptions(**capture.fit_options)
    check_memory(
        fit_memory(capture.images.size, capture.n_images, h, w, defaults),
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
            _say_above_progress(args, [*fit_notes, _channel_summary(name, r)])
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
        figures = _figure_names(Path(args.plot), fit.channels) if args.plot else []
        result, compared = fit_record(capture, fit, args.method, args.phase)
        try:
            with staged_files() as write:
                if figures:
                    stage("plot")
                    _fit_figures(capture, fit, figures, write)
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


def fit_record(capture, fit, method: str, phase: str) -> tuple[dict, list[dict]]:
    """results.json of ``fit`` of ``capture`` (one file or one of a batch), and its
    errors against the capture's truth (empty without one)."""
    result = _label_two_step(method, fit.to_dict())
    result["capture"] = os.path.abspath(capture.source)  # render finds it from anywhere
    result["response"] = capture.response_record()
    compared = _against_truth(capture, fit, phase) if capture.truth else []
    if capture.truth:
        result["truth"] = capture.truth
        result["truth_error"] = compared[0] if len(compared) == 1 else compared
    result["medium_roi"] = _roi_record(capture)
    return result, compared


def truth_lines(fit, compared: list[dict]) -> list[str]:
    """Each channel's errors against the truth (none without a truth)."""
    if not compared:
        return []
    return [
        f"[{name}] against the truth: "
        + ", ".join(
            f"{k} {v['error']:+.3g}{_error_unit(k, v)} ({v['sigmas']:+.1f} sigma)"
            for k, v in e.items()
        )
        for name, e in zip(fit.channels, compared, strict=True)
    ]


def _single_only(args: argparse.Namespace) -> None:
    """The options of a batch (several captures) refused for one capture file."""
    for option, value in (
        ("--scheduler", args.scheduler),
        ("--workers", args.workers),
        ("--allow-large", args.allow_large or None),
    ):
        if value is not None:
            raise ValueError(f"{option}: for several captures (or a folder of them) only")


# --------------------------------------------------------------------------- demo


@command(
    "demo",
    "simulate the paper's milk capture and recover it with every method",
    arg("--out", default="demo_out", metavar="DIR", help="output folder (%(default)s)"),
    arg("--methods", default="grid,gradient,joint", help="comma-separated (%(default)s)"),
    arg("--no-xla-cache", action="store_true", help=XLA_CACHE_HELP),
)
def _demo(args: argparse.Namespace) -> int | None:
    """Simulate the paper's milk (sigma_t 0.2051, sigma_s 0.0366, g 0.4 per pixel) as a
    six-shift stripe capture with shot and read noise (gain 400: about 20000 photons
    at image value 1) and a projector black level of 0.01, write it to DIR as a
    capture, fit it with each method, print a table (truth, each method, error,
    time) and write DIR/results.json and
    DIR/demo_fit.png (the joint fit's profiles and residuals)."""
    from lightfield_jax.app.cmd_simulate import SIMULATE_FILES
    from lightfield_jax.app.outputs import CAPTURE_MARKER
    from lightfield_jax.capture.loading import load_capture
    from lightfield_jax.checks import repeated
    from lightfield_jax.files import atomic_directory, atomic_write_json, naming_output
    from lightfield_jax.forward.simulate import simulate_capture, write_simulation
    from lightfield_jax.forward.simulate_config import parse_simulation_config
    from lightfield_jax.inverse.capture_fit import fit_capture

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in ("grid", "gradient", "joint"):
            raise ValueError(f"--methods: unknown method {m!r} (grid, gradient, joint)")
    if not methods:
        raise ValueError(f"--methods: names no method (grid, gradient, joint): {args.methods!r}")
    twice = repeated(methods)
    if twice:  # else fitted twice, the table's rows twice, results.json's once
        raise ValueError(f"--methods: names {', '.join(twice)} more than once: {args.methods!r}")
    check_command_outputs(
        folders=[args.out],
        folder_names=(*SIMULATE_FILES, "results.json", "demo_fit.png"),
        marker=CAPTURE_MARKER,  # the demo's folder is a simulated capture
        writer="simulate",
    )
    out = Path(args.out)
    config = parse_simulation_config(DEMO_CONFIG, source="demo config")
    use_xla_cache(args)
    with command_progress(args, "demo") as stage:
        stage("simulate the capture")
        sim = simulate_capture(config, stage=stage)
        # The capture, results.json and the figure are written into one staging folder
        # and published together at the end: a demo stopped or failing in its fit
        # leaves no capture in DIR, and a failed rerun the previous run's files whole
        # (the capture is not published before the fits: an interrupted demo would leave
        # it, a failed rerun the old results.json beside the new capture).
        with atomic_directory(out) as staging:
            write_simulation(sim, staging)
            capture = load_capture(staging / "capture.yaml")
            truth = sim.truth()
            rows, results, again = [], {}, {}
            for method in methods:
                stage(f"fit: {method}")
                fit = fit_capture(capture, method, progress=stage).results[0]
                results[method] = _label_two_step(method, fit.to_dict())
                rows.append((method, fit))
                # The same fit once more: the programs compiled above are reused, as
                # for another channel or the next capture of this size in one process.
                stage(f"fit again: {method}")
                again[method] = fit_capture(capture, method).results[0].seconds["total"]
            if "joint" in results:
                stage("plot")
                from lightfield_jax.viz import plot_fit

                with naming_output(out / "demo_fit.png"):
                    plot_fit(
                        capture.images[..., 0],
                        capture.pattern,
                        dict(rows)["joint"],
                        staging / "demo_fit.png",
                    )
            with naming_output(out / "results.json"):
                atomic_write_json(staging / "results.json", {"truth": truth, "fits": results})
    if "joint" not in results and (out / "demo_fit.png").exists():
        # An earlier run's figure (kept: this run did not write it), not this run's fits.
        warn(
            args,
            f"{out / 'demo_fit.png'} is an earlier run's figure, not of this run's capture "
            "(drawn for a joint fit, which this run has not)",
        )
    head = (
        f"{'method':<9} {'sigma_t':>9} {'err':>7} {'sigma_s':>9} {'err':>7} {'g':>7} "
        f"{'err':>7} {'time s':>7} {'again s':>7} {'conv':>5}"
    )
    lines = [
        "paper's milk, 128x96, 6 shifted stripes (period 6), shot + read noise",
        head,
        f"{'truth':<9} {truth['sigma_t']:>9.5f} {'':>7} {truth['sigma_s']:>9.5f} {'':>7} "
        f"{truth['g']:>7.3f}",
    ]
    for method, r in rows:
        lines.append(
            f"{method:<9} {r.sigma_t:>9.5f} {100 * (r.sigma_t / truth['sigma_t'] - 1):>+6.1f}% "
            f"{r.sigma_s:>9.5f} {100 * (r.sigma_s / truth['sigma_s'] - 1):>+6.1f}% "
            f"{r.g:>7.3f} {r.g - truth['g']:>+7.3f} {r.seconds['total']:>7.1f} "
            f"{again[method]:>7.2f} {'yes' if r.converged else 'NO':>5}"
        )
    folder = None if args.no_xla_cache else xla_cache_folder()
    if any(m in TWO_STEP_METHODS for m in methods):
        lines.append(f"note: {TWO_STEP_CAVEAT}")
    lines.append("again: the same fit once more in this process (its compiled programs reused)")
    lines.append(
        "time: wall clock, XLA compilation included"
        + (
            f" (compiled programs cached in {folder}: a second run loads them)"
            if folder is not None
            else " (no compilation cache)"
        )
    )
    say(args, "\n".join(lines))
    say(
        args,
        f"wrote {shown_path(out)}/ (capture, results.json"
        + (", demo_fit.png)" if "joint" in results else ")"),
    )
    return None if all(r.converged for _, r in rows) else 1

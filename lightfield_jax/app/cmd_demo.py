"""The ``demo`` subcommand (see :mod:`lightfield_jax.app.cli`): simulate the paper's milk
and fit it with each method."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightfield_jax.app.arguments import (
    XLA_CACHE_HELP,
    arg,
    use_xla_cache,
    xla_cache_folder,
)
from lightfield_jax.app.cli import DEMO_CONFIG, command
from lightfield_jax.app.fit_report import (
    TWO_STEP_CAVEAT,
    TWO_STEP_METHODS,
    label_two_step,
)
from lightfield_jax.app.messages import (
    command_progress,
    say,
    shown_path,
    warn,
)
from lightfield_jax.app.outputs import check_command_outputs
from lightfield_jax.checks import repeated

# The fit's memory estimate (fit_memory) and its constants, named here as before.
from lightfield_jax.runtime.memory import FIT_N_THETA as FIT_N_THETA
from lightfield_jax.runtime.memory import RENDER_CELLS_PER_PIXEL as RENDER_CELLS_PER_PIXEL


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
    from lightfield_jax.files import atomic_directory, atomic_write_json, naming_output
    from lightfield_jax.forward.simulate import simulate_capture, write_simulation
    from lightfield_jax.forward.simulate_config import parse_simulation_config
    from lightfield_jax.inverse.capture_fit import fit_capture
    from lightfield_jax.inverse.method_base import METHOD_NAMES

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in METHOD_NAMES:
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
                results[method] = label_two_step(method, fit.to_dict())
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

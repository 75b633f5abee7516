"""The ``simulate`` and ``bench`` subcommands (see :mod:`lightfield_jax.app.cli`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightfield_jax.app.arguments import arg, positive_int
from lightfield_jax.app.cli import DEMO_CONFIG, command
from lightfield_jax.app.messages import command_progress, say, shown_path, warn
from lightfield_jax.app.outputs import check_command_outputs

# --------------------------------------------------------------------------- simulate


# The names simulate writes into its folder (see its help).
SIMULATE_FILES = (
    "bounces*.npy",
    "bounces*.exr",
    "total.exr",
    "shift_*.exr",
    "capture.yaml",
    "dark.exr",
    "lightfield.npy",
    "metadata.json",
)


@command(
    "simulate",
    "render a config into per-bounce and captured images",
    arg(
        "config",
        metavar="CONFIG.yaml",
        help="a simulate config (see lightfield_jax.forward.simulate_config)",
    ),
    arg(
        "--out",
        metavar="DIR",
        required=True,
        help="output folder (created; its files replaced; another command's folder refused)",
    ),
    arg(
        "--lightfield",
        action="store_true",
        help="also write lightfield.npy, L_0..L_K (memory: (K+1)*P*H*W*n_theta floats)",
    ),
    arg(
        "--plot",
        metavar="FIGDIR",
        help="also write the paper's figures of the scene into FIGDIR (created; files "
        "replaced): bounce_images.png, bounce_profiles.png, lightfield.png",
    ),
    arg(
        "--compact",
        action="store_true",
        help="leave out the per-bounce images (bounces.npy, bounces*.exr): the captured "
        "images, capture.yaml and metadata.json only",
    ),
)
def _simulate(args: argparse.Namespace) -> None:
    """Render a simulate config and write into DIR:

      bounces.npy     float32 per-bounce images [K, H, W] (index k-1 holds I_k);
                      stripes: [P, K, H, W], one row per phase
      bounces.exr     channels I1..IK (beam, full)
      bounces_XX.exr  channels I1..IK of shift XX (stripes)
      total.exr       channel Y: the captured image, sum of the bounces (beam, full)
      shift_XX.exr    channel Y: the captured image of shift XX (stripes)
      capture.yaml    the shifts as a capture file, input of the inverse pipeline
                      (stripes)
      dark.exr        channel Y: dark frame (when the config has dark_level)
      lightfield.npy  with --lightfield: float32 [K+1, H, W, n_theta], L_0..L_K in
                      radiance per radian; stripes: [P, K+1, H, W, n_theta]
      metadata.json   config, K, rho, convergence, n_theta, refine, timings, versions

    --compact leaves out bounces.npy and bounces*.exr (most of the bytes).

    Per-bounce images and light fields include the gain and (stripes) the black level;
    captured images add the dark level and noise. Nothing is written unless the whole
    command succeeds.
    """
    from lightfield_jax.app.outputs import CAPTURE_MARKER
    from lightfield_jax.files import atomic_directory
    from lightfield_jax.forward.simulate import simulate_capture, write_simulation
    from lightfield_jax.forward.simulate_config import load_simulation_config

    check_command_outputs(
        folders=[args.out],
        inputs=[args.config],
        folder_names=(*SIMULATE_FILES, "*.png"),
        marker=CAPTURE_MARKER,
        writer="simulate",
    )
    if args.plot:  # a figures folder: its figures are replaced (no capture there)
        check_command_outputs(folders=[args.plot], inputs=[args.config], folder_names=("*.png",))
    config = load_simulation_config(args.config)
    out = Path(args.out)
    plot = Path(args.plot) if args.plot else None
    with command_progress(args, "simulate") as stage:
        sim = simulate_capture(config, lightfield=args.lightfield, stage=stage)
        stage("write files")
        # The figures are drawn inside the output's staging: a failure publishes neither.
        with atomic_directory(out) as staging:
            files = write_simulation(
                sim, staging, extra_metadata={"warnings": args.warnings}, compact=args.compact
            )
            if plot is not None:
                from lightfield_jax.capture.views import plot_simulation

                with atomic_directory(plot) as figures_staging:
                    figures, notes = plot_simulation(sim, figures_staging, stage=stage)
        if plot is not None:
            for note in notes:
                warn(args, note)
            say(args, f"wrote {', '.join(figures)} to {shown_path(plot)}")
    converges = "converges" if sim.converges else "DOES NOT CONVERGE (truncated)"
    say(
        args,
        f"wrote {len(files)} files to {shown_path(out)}: K = {sim.n_bounces} bounces, rho = "
        f"{sim.rho:.4f} ({converges}), n_theta = {sim.n_theta}, refine = {sim.refine}; "
        f"compile {sim.timing['compile']:.2f} s, run {sim.timing['run']:.2f} s",
    )


# --------------------------------------------------------------------------- bench


def _grid_sizes(text: str) -> tuple[tuple[int, int, int], ...]:
    """``64x64x32,128x128x64`` → ((64, 64, 32), (128, 128, 64)), validated as grids."""
    from lightfield_jax.scene.grid import Grid

    sizes = []
    for item in text.split(","):
        parts = item.strip().lower().split("x")
        try:
            size = tuple(int(p) for p in parts)
        except ValueError:
            size = ()
        if len(size) != 3:
            raise argparse.ArgumentTypeError(
                f"{item.strip()!r} is not WIDTHxHEIGHTxN_THETA (e.g. 64x64x32)"
            )
        try:
            Grid(*size)
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"{item.strip()!r}: {e}") from None
        if size in sizes:  # else measured twice, two rows of one size in the results
            raise argparse.ArgumentTypeError(f"{item.strip()!r} is given twice")
        sizes.append(size)
    return tuple(sizes)


# Timed runs per measurement (with --fits: processes per method, each a fresh fit): a
# median of more is no steadier, and --repeats 1000000000 ran for days.
MAX_REPEATS = 1000


def _repeats(text: str) -> int:
    value = positive_int(text)
    if value > MAX_REPEATS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_REPEATS}, got {text!r}")
    return value


def _fit_methods(text: str) -> tuple[str, ...]:
    from lightfield_jax.inverse.method_base import METHOD_NAMES

    names = tuple(x.strip() for x in text.split(","))
    bad = [x for x in names if x not in METHOD_NAMES]
    if bad or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"must be distinct names among {', '.join(METHOD_NAMES)}, comma-separated, got {text!r}"
        )
    return names


@command(
    "bench",
    "time the forward model on a few grid sizes",
    arg(
        "--sizes",
        type=_grid_sizes,
        default="64x64x32,128x128x64,256x256x128",
        metavar="WxHxN,...",
        help="grid sizes WIDTHxHEIGHTxN_THETA (default: %(default)s)",
    ),
    arg(
        "--repeats",
        type=_repeats,
        default=None,
        help="timed runs per measurement (default 5; with --fits 3 processes per method; "
        "at most 1000)",
    ),
    arg("--out", default="bench.json", metavar="FILE", help="JSON results (default: %(default)s)"),
    arg(
        "--slab",
        action="store_true",
        help="instead: the slab geometry against the plane on a 128x128 6-phase stripe "
        "capture (forward, one derivative column, a joint fit each)",
    ),
    arg("--no-fits", action="store_true", help="with --slab: skip the joint fits"),
    arg(
        "--fits",
        action="store_true",
        help="instead: each fit method on the demo's capture (128x96, 6 stripes), each fit "
        "in a fresh process with no compilation cache, then once more warm (--repeats "
        "processes per method, default 3 here)",
    ),
    arg(
        "--methods",
        type=_fit_methods,
        default="grid,gradient,joint",
        metavar="M,...",
        help="with --fits: the fit methods, in turn (default: %(default)s)",
    ),
)
def _bench(args: argparse.Namespace) -> None:
    """Measure compile time, time per bounce, gradient time and peak memory of the
    forward model (a single beam, float32) for each grid size, print a line per size
    and write all numbers to a JSON file. Asserts nothing. With ``--slab``: the slab
    model against the plane (forward, derivative, joint fit). With ``--fits``: the fit
    methods' wall time, cold (a fresh process) and warm."""
    from lightfield_jax.app.bench import bench_fits, bench_slab, run_benchmark
    from lightfield_jax.files import atomic_write_json

    check_command_outputs(files=[args.out], json=[("--out", args.out, "")])
    out = Path(args.out)
    if args.fits and args.slab:
        raise ValueError("bench: --fits and --slab are separate benchmarks: give one")
    if args.fits:
        with command_progress(args, "bench", 1) as stage:
            stage("fit methods, each in a fresh process")
            result = bench_fits(
                DEMO_CONFIG,
                methods=args.methods,
                repeats=args.repeats or 3,
                progress=lambda m: say(args, m),
            )
        atomic_write_json(out, result)
        say(args, f"wrote {shown_path(out)}")
        return
    if args.slab:
        with command_progress(args, "bench", 3) as stage:
            stage("slab vs plane")
            result = bench_slab(
                repeats=args.repeats or 5, fits=not args.no_fits, progress=lambda m: say(args, m)
            )
        atomic_write_json(out, result)
        say(args, f"wrote {shown_path(out)}")
        return
    sizes = args.sizes
    from lightfield_jax.runtime.memory import check_memory, render_bytes

    for w, h, n in sizes:
        # value_and_grad keeps the forward pass's fields of its 10 bounces.
        check_memory(render_bytes(10, h, w, n), f"bench --sizes {w}x{h}x{n}")
    with command_progress(args, "bench", len(sizes)) as stage:
        names = iter(f"{w}x{h}x{n}" for w, h, n in sizes[1:])
        stage(f"{sizes[0][0]}x{sizes[0][1]}x{sizes[0][2]}")

        def report(line: str) -> None:
            say(args, line)
            following = next(names, None)
            if following is not None:
                stage(following)

        result = run_benchmark(sizes, args.repeats or 5, progress=report)
    atomic_write_json(out, result)
    say(args, f"wrote {shown_path(out)}")

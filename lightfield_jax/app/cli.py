"""The ``lightfield-jax`` command line.

Each subcommand is one function decorated with :func:`command`, which registers its
name, one-line help and arguments; its docstring is the command's ``--help`` text. The
function receives the parsed arguments (with the common options ``quiet``, ``debug``
and a ``warnings`` list of the warnings issued so far) and returns an exit status
(``None`` for 0). Adding a subcommand is that one function::

    @command("inspect", "summarise a capture file", arg("capture", metavar="CAPTURE.yaml"))
    def _inspect(args: argparse.Namespace) -> int | None:
        \"\"\"Print what a capture holds.\"\"\"
        ...

Conventions every command keeps:

- Errors in the user's input (a bad config or capture, a missing file, an invalid
  value: the :data:`USER_ERRORS`) print one line, ``lightfield-jax: error: ...``, on
  stderr and exit with status 2, without a traceback (``--debug`` shows it). Command
  line syntax errors exit 2 the same way.
- Validate every input before the long work starts: check every output path against
  the inputs and each other with :func:`~lightfield_jax.app.outputs.check_outputs`, and
  the memory the work needs with :func:`~lightfield_jax.app.memory.check_memory`. Write
  output folders through :func:`~lightfield_jax.capture.io.atomic_directory` and single files
  through :func:`~lightfield_jax.app.outputs.staged_files`, so a failure leaves no
  partial output and replaces no existing file.
- SIGINT (Ctrl-C) and SIGTERM end a command within a moment, with status 130 or 143
  and nothing written (:mod:`lightfield_jax.app.signals`).
- Warnings print as ``lightfield-jax: warning: ...`` and are collected in
  ``args.warnings`` (e.g. for a metadata file).
- Long work reports its stages through :func:`_progress`: a display on stderr that
  appears when stderr is a terminal and the work takes more than two seconds.
- Results and summaries go to stdout (silenced by ``--quiet``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from lightfield_jax.app.progress import progress

PROG = "lightfield-jax"
USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,  # ConfigError, CaptureError and every validation error are ValueErrors
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
)

Handler = Callable[[argparse.Namespace], "int | None"]
_COMMANDS: dict[str, tuple[str, tuple, Handler]] = {}


def arg(*flags: str, **options: Any) -> tuple[tuple[str, ...], dict[str, Any]]:
    """One argument of a subcommand, as :meth:`argparse.ArgumentParser.add_argument`
    takes it."""
    return flags, options


def command(name: str, help: str, *arguments: tuple[tuple[str, ...], dict[str, Any]]):
    """Register the decorated function as subcommand ``name`` (see the module docstring)."""

    def register(handler: Handler) -> Handler:
        if name in _COMMANDS:
            raise ValueError(f"subcommand {name!r} is registered twice")
        _COMMANDS[name] = (help, arguments, handler)
        return handler

    return register


class _Parser(argparse.ArgumentParser):
    """An argument parser whose syntax errors are one line on stderr, status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The parser of every registered subcommand."""
    from lightfield_jax import __version__

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-q", "--quiet", action="store_true", help="no progress display and no summary"
    )
    common.add_argument(
        "--debug", action="store_true", help="show a traceback for errors in the input"
    )
    common.add_argument(
        "--max-memory",
        type=_memory_size,
        metavar="SIZE",
        help="memory the command may use (e.g. 16G; default: the machine's available "
        "memory); work estimated to need more is refused before it starts",
    )
    parser = _Parser(
        prog=PROG,
        description="Light transport in thin scattering media (Mukaigawa, Raskar & Yagi, "
        "CVPR 2010): simulate, separate and fit.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (help_text, arguments, handler) in _COMMANDS.items():
        p = sub.add_parser(
            name,
            help=help_text,
            description=handler.__doc__,
            parents=[common],
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        for flags, options in arguments:
            p.add_argument(*flags, **options)
        p.set_defaults(handler=handler)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 success, 2 bad input)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help, --version, syntax errors
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    from lightfield_jax.app.memory import memory_limit
    from lightfield_jax.app.signals import stop_on_signals

    args.warnings = []
    try:
        with (
            _warnings_to_stderr(args.warnings),
            stop_on_signals(PROG),
            memory_limit(args.max_memory),
        ):
            status = args.handler(args)
    except USER_ERRORS as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {_describe(e)}", file=sys.stderr)
        return 2
    except (RecursionError, OverflowError, MemoryError) as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {_describe_limit(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return 0 if status is None else int(status)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _memory_size(text: str) -> int:
    from lightfield_jax.app.memory import parse_size

    try:
        return parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _describe_limit(error: BaseException) -> str:
    """A resource limit met despite the checks, as one line (no traceback)."""
    if isinstance(error, RecursionError):
        return "an input is nested too deeply to process (RecursionError)"
    if isinstance(error, OverflowError):
        return f"a value in the input is too large ({_one_line(error)[:200]})"
    return "out of memory (MemoryError): reduce the input's size, or free memory"


def _describe(error: BaseException) -> str:
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return _one_line(f"{error.filename}: {error.strerror}")
    return _one_line(str(error)) or type(error).__name__


@contextlib.contextmanager
def _warnings_to_stderr(collected: list[str]) -> Iterator[None]:
    """Show the package's warnings as one line each on stderr, every time, and collect
    them; other warnings keep the filters in force."""
    from lightfield_jax.capture.capture import CaptureWarning
    from lightfield_jax.forward.render import DivergentSeriesWarning

    def show(message, category, filename, lineno, file=None, line=None):
        text = _one_line(str(message))
        collected.append(text)
        print(f"{PROG}: warning: {text}", file=sys.stderr)

    with warnings.catch_warnings():
        for category in (DivergentSeriesWarning, CaptureWarning):
            warnings.simplefilter("always", category)
        warnings.showwarning = show
        yield


def _warn(args: argparse.Namespace, text: str) -> None:
    """A warning of the command itself: one line on stderr, collected like the
    package's, whatever the Python warning filters are (``-W error`` must not turn an
    exit status 1 into a traceback)."""
    text = _one_line(text)
    args.warnings.append(text)
    print(f"{PROG}: warning: {text}", file=sys.stderr)


def _progress(args: argparse.Namespace, desc: str, total: int | None = None):
    """The stage display of a command (off with ``--quiet``)."""
    return progress(desc, total, enabled=False if args.quiet else None)


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text)


# ------------------------------------------------------------------ compilation cache

XLA_CACHE_ENV = "LIGHTFIELD_JAX_XLA_CACHE"
_XLA_CACHE_HELP = (
    "do not use the persistent XLA compilation cache (also: "
    f"{XLA_CACHE_ENV}=off; {XLA_CACHE_ENV}=DIR moves it)"
)


def xla_cache_folder(environ=None) -> Path | None:
    """Where ``fit`` and ``demo`` keep compiled XLA programs: ``$LIGHTFIELD_JAX_XLA_CACHE``,
    else ``$XDG_CACHE_HOME/lightfield_jax/xla`` (``~/.cache/lightfield_jax/xla``);
    ``None`` when that variable is ``off``, ``0`` or empty."""
    import os

    env = os.environ if environ is None else environ
    value = env.get(XLA_CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "no", "false") else Path(value)
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lightfield_jax" / "xla"


def _use_xla_cache(args: argparse.Namespace) -> None:
    """Turn on JAX's persistent compilation cache (every program, however small or
    quick to compile) unless ``--no-xla-cache`` or the environment turns it off. A fit
    spends most of its time on a CPU compiling; a later fit of a capture of the same
    shape and model size loads the programs instead (a warm start). A folder that cannot
    be created leaves the cache off, with a warning."""
    folder = None if args.no_xla_cache else xla_cache_folder()
    if folder is None:
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        _warn(args, f"XLA compilation cache off: cannot create {folder} ({e.strerror})")
        return
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    compilation_cache.reset_cache()  # set up once per process, at the first compilation


def _outputs(files=(), folders=(), inputs=(), plots=(), folder_names=()) -> None:
    """Check every output of a command before its work (see
    :func:`~lightfield_jax.app.outputs.check_outputs`); ``plots`` are figures among
    ``files``, whose format is checked too; ``folder_names``: the names written into
    ``folders``."""
    from lightfield_jax.app.outputs import check_outputs, check_plot_format

    for plot in plots:
        check_plot_format(plot)
    check_outputs([f for f in files if f], [d for d in folders if d], inputs, folder_names)


@contextlib.contextmanager
def _about(capture) -> Iterator[None]:
    """Errors of the work on ``capture`` name its file, and a numerical library's
    failure (a singular or non-finite solve) is said in the user's terms."""
    import equinox as eqx
    import numpy as np

    from lightfield_jax.capture.io import CaptureError

    source = str(capture.source)
    try:
        with np.errstate(all="ignore"):
            yield
    except (eqx.EquinoxRuntimeError, np.linalg.LinAlgError, FloatingPointError) as e:
        raise CaptureError(
            f"{source}: the solve met a singular or non-finite system: the images do not "
            "determine sigma_t, sigma_s and g (check the capture with lightfield-jax "
            "inspect; --debug shows the library's message)"
        ) from e
    except ValueError as e:
        if source in str(e):
            raise
        raise CaptureError(f"{source}: {_one_line(e)}") from e


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
    arg("config", metavar="CONFIG.yaml", help="a simulate config (see lightfield_jax.app.config)"),
    arg("--out", metavar="DIR", required=True, help="output folder (created; files replaced)"),
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

    Per-bounce images and light fields include the gain and (stripes) the black level;
    captured images add the dark level and noise. Nothing is written unless the whole
    command succeeds.
    """
    from lightfield_jax.app.config import load_simulation_config
    from lightfield_jax.capture.io import atomic_directory
    from lightfield_jax.forward.simulate import simulate_capture, write_simulation

    _outputs(
        folders=[args.out, args.plot],
        inputs=[args.config],
        folder_names=(*SIMULATE_FILES, "*.png"),
    )
    config = load_simulation_config(args.config)
    out = Path(args.out)
    plot = Path(args.plot) if args.plot else None
    with _progress(args, "simulate") as stage:
        sim = simulate_capture(config, lightfield=args.lightfield, stage=stage)
        stage("write files")
        with atomic_directory(out) as staging:
            files = write_simulation(sim, staging, extra_metadata={"warnings": args.warnings})
        if plot is not None:
            from lightfield_jax.capture.views import plot_simulation

            with atomic_directory(plot) as staging:
                figures, notes = plot_simulation(sim, staging, stage=stage)
            for note in notes:
                _warn(args, note)
            _say(args, f"wrote {', '.join(figures)} to {plot}")
    converges = "converges" if sim.converges else "DOES NOT CONVERGE (truncated)"
    _say(
        args,
        f"wrote {len(files)} files to {out}: K = {sim.n_bounces} bounces, rho = {sim.rho:.4f} "
        f"({converges}), n_theta = {sim.n_theta}, refine = {sim.refine}; "
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
        sizes.append(size)
    return tuple(sizes)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


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
        type=_positive_int,
        default=None,
        help="timed runs per measurement (default 5; with --fits 3 processes per method)",
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
)
def _bench(args: argparse.Namespace) -> None:
    """Measure compile time, time per bounce, gradient time and peak memory of the
    forward model (a single beam, float32) for each grid size, print a line per size
    and write all numbers to a JSON file. Asserts nothing. With ``--slab``: the slab
    model against the plane (forward, derivative, joint fit). With ``--fits``: the fit
    methods' wall time, cold (a fresh process) and warm."""
    from lightfield_jax.app.bench import bench_fits, bench_slab, run_benchmark
    from lightfield_jax.capture.io import atomic_write_json

    _outputs(files=[args.out])
    out = Path(args.out)
    if args.fits and args.slab:
        raise ValueError("bench: --fits and --slab are separate benchmarks: give one")
    if args.fits:
        with _progress(args, "bench", 1) as stage:
            stage("fit methods, each in a fresh process")
            result = bench_fits(
                DEMO_CONFIG, repeats=args.repeats or 3, progress=lambda m: _say(args, m)
            )
        atomic_write_json(out, result)
        _say(args, f"wrote {out}")
        return
    if args.slab:
        with _progress(args, "bench", 3) as stage:
            stage("slab vs plane")
            result = bench_slab(
                repeats=args.repeats or 5, fits=not args.no_fits, progress=lambda m: _say(args, m)
            )
        atomic_write_json(out, result)
        _say(args, f"wrote {out}")
        return
    sizes = args.sizes
    from lightfield_jax.app.memory import check_memory, render_bytes

    for w, h, n in sizes:
        # value_and_grad keeps the forward pass's fields of its 10 bounces.
        check_memory(render_bytes(10, h, w, n), f"bench --sizes {w}x{h}x{n}")
    with _progress(args, "bench", len(sizes)) as stage:
        names = iter(f"{w}x{h}x{n}" for w, h, n in sizes[1:])
        stage(f"{sizes[0][0]}x{sizes[0][1]}x{sizes[0][2]}")

        def report(line: str) -> None:
            _say(args, line)
            following = next(names, None)
            if following is not None:
                stage(following)

        result = run_benchmark(sizes, args.repeats or 5, progress=report)
    atomic_write_json(out, result)
    _say(args, f"wrote {out}")


# --------------------------------------------------------------------------- fit


def _fit_summary(fit) -> str:
    from lightfield_jax.scene.geometry import describe_geometry

    lines = []
    for name, r in zip(fit.channels, fit.results, strict=True):
        u = r.uncertainty
        lines.append(
            f"[{name}] {r.method}: sigma_t {r.sigma_t:.5g} ± {u.get('sigma_t', float('nan')):.2g}, "
            f"sigma_s {r.sigma_s:.5g} ± {u.get('sigma_s', float('nan')):.2g}, "
            f"g {r.g:.4f} ± {u.get('g', float('nan')):.2g} (per px; albedo {r.albedo:.3f}, "
            f"rho {r.rho:.3f}); {'converged' if r.converged else 'NOT CONVERGED: ' + r.message}"
            f" in {r.iterations} iterations, {r.seconds['total']:.1f} s "
            f"(compile {r.seconds['compile']:.1f} s); model {describe_geometry(r.model)}, "
            f"{r.model['width']}x{r.model['height']}, n_theta {r.model['n_theta']}, "
            f"K {r.model['bounces']}"
        )
    return "\n".join(lines)


def _figure_names(plot: Path, channels: Sequence[str]) -> list[Path]:
    """FIG.png for one channel; FIG.png and FIG_<channel>.png each for several."""
    if len(channels) == 1:
        return [plot]
    return [plot] + [plot.with_name(f"{plot.stem}_{name}{plot.suffix}") for name in channels]


def _fit_figures(capture, fit, figures: list[Path], write) -> None:
    """FIG.png: the profiles and residuals of the fit; with several channels, FIG.png
    holds σt, σs, g per channel and FIG_<channel>.png each channel's profiles. Each
    figure is written to ``write(target)`` (a staged temporary)."""
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
    plot_channels(fit, write(figures[0]), pixel_size_mm=capture.pixel_size_mm)
    for name, result, target in zip(fit.channels, fit.results, figures[1:], strict=True):
        i = capture.channel_names.index(name)
        plot_fit(
            capture.images[..., i], capture.pattern, result, write(target), **_shown(capture, i)
        )


def _shown(capture, i: int) -> dict:
    """What plot_fit shows beside the fit: channel i's mask and the capture's truth."""
    return {"mask": capture.mask[..., i], "truth": capture.truth}


# Direction bins assumed for a fit's memory estimate: the fewest the fit chooses
# (g <= 0.5); more are capped by FitOptions.max_cells.
FIT_N_THETA = 32
# Cells per pixel of the largest primal render a fit may make (a forward medium's
# error-term model: 128 θ bins at refinement 2); more are capped at twice
# FitOptions.max_render_cells.
RENDER_CELLS_PER_PIXEL = 128 * 2**2


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
    else:
        result["uncertainty_kind"] = "statistical"
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


def _shown(capture, i: int) -> dict:
    """What plot_fit shows beside the fit: channel i's mask and the capture's truth."""
    return {"mask": capture.mask[..., i], "truth": capture.truth}


@command(
    "fit",
    "recover sigma_t, sigma_s and g from a stripe capture",
    arg("capture", metavar="CAPTURE.yaml", help="a capture file (see README)"),
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
        help="fit only this channel (repeatable; default: the capture's channel key)",
    ),
    arg("--out", default="results.json", metavar="FILE", help="JSON results (%(default)s)"),
    arg(
        "--plot",
        metavar="FIG.png",
        help="also write the profiles and residual figure; with several channels FIG.png "
        "shows sigma_t, sigma_s, g per channel and FIG_<channel>.png each one's profiles",
    ),
    arg(
        "--phase",
        choices=("paper", "normalized"),
        default="paper",
        help="phase convention of the model (default: %(default)s)",
    ),
    arg(
        "--max-steps",
        type=_positive_int,
        metavar="N",
        help="iteration limit of the solves (default: FitOptions.max_steps)",
    ),
    arg("--no-xla-cache", action="store_true", help=_XLA_CACHE_HELP),
)
def _fit(args: argparse.Namespace) -> int | None:
    """Fit a capture and write FILE (keys: sigma_t, sigma_s, sigma_a, g, albedo, gain,
    black_level, uncertainty, correlation, method, converged, iterations, residual,
    seconds, model; per channel when several). Exit status 1, with the results
    written and a warning, when a solve does not converge."""
    from lightfield_jax.app.memory import check_memory, correction_bytes, fit_bytes
    from lightfield_jax.app.outputs import staged_files
    from lightfield_jax.capture.capture import capture_files, load_capture
    from lightfield_jax.capture.io import atomic_write_json
    from lightfield_jax.inverse.capture_fit import fit_capture
    from lightfield_jax.inverse.options import FitOptions

    inputs = capture_files(args.capture)
    _outputs(files=[args.out, args.plot], inputs=inputs, plots=[args.plot] if args.plot else [])
    out = Path(args.out)
    _use_xla_cache(args)
    capture = load_capture(args.capture)
    channels = args.channel or capture.channel_names
    figures = _figure_names(Path(args.plot), channels) if args.plot else []
    _outputs(files=[out, *figures], inputs=inputs)
    h, w = capture.shape
    defaults = FitOptions(**capture.fit_options)
    cells = min(h * w * FIT_N_THETA, defaults.max_cells)
    rendered = min(h * w * RENDER_CELLS_PER_PIXEL, 2 * defaults.max_render_cells)
    check_memory(
        max(
            fit_bytes(capture.images.size, capture.n_images, cells),
            correction_bytes(capture.images.size, capture.n_images, rendered),
        ),
        f"{capture.source}: the fit",
    )
    with _progress(args, f"fit ({args.method})") as stage, _about(capture):
        limits = {} if args.max_steps is None else {"max_steps": args.max_steps}
        fit = fit_capture(
            capture,
            args.method,
            channels=args.channel,
            progress=stage,
            phase=args.phase,
            **limits,
        )
        figures = _figure_names(Path(args.plot), fit.channels) if args.plot else []
        result = _label_two_step(args.method, fit.to_dict())
        result["capture"] = str(capture.source)
        if capture.truth:
            result["truth"] = capture.truth
        result["medium_roi"] = _roi_record(capture)
        with staged_files() as write:
            if figures:
                stage("plot")
                _fit_figures(capture, fit, figures, write)
            atomic_write_json(write(out), result)
    for note in capture.notes:
        _say(args, f"note: {note}")
    _say(args, _fit_summary(fit))
    if args.method in TWO_STEP_METHODS:
        _say(args, f"note: {TWO_STEP_CAVEAT}")
    _say(args, f"wrote {', '.join(str(f) for f in [out, *figures])}")
    if not fit.converged:
        _warn(args, "the fit did not converge: results were written with converged: false")
        return 1
    return None


# --------------------------------------------------------------------------- demo

DEMO_CONFIG = {
    "grid": {"width": 128, "height": 96},
    "medium": {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "phase": "paper"},
    "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
    "bounces": "auto",
    "gain": 400.0,
    "black_level": 0.01,
    "noise": {"photons": 20000.0, "read": 0.0005, "seed": 0},
}


@command(
    "demo",
    "simulate the paper's milk capture and recover it with every method",
    arg("--out", default="demo_out", metavar="DIR", help="output folder (%(default)s)"),
    arg("--methods", default="grid,gradient,joint", help="comma-separated (%(default)s)"),
    arg("--no-xla-cache", action="store_true", help=_XLA_CACHE_HELP),
)
def _demo(args: argparse.Namespace) -> int | None:
    """Simulate the paper's milk (sigma_t 0.2051, sigma_s 0.0366, g 0.4 per pixel) as a
    six-shift stripe capture with shot and read noise (gain 400: about 20000 photons
    at image value 1) and a projector black level of 0.01, write it to DIR as a
    capture, fit it with each method, print a table (truth, each method, error,
    time) and write DIR/results.json and
    DIR/demo_fit.png (the joint fit's profiles and residuals)."""
    from lightfield_jax.app.config import parse_simulation_config
    from lightfield_jax.capture.capture import load_capture
    from lightfield_jax.capture.io import atomic_directory, atomic_write_json
    from lightfield_jax.forward.simulate import simulate_capture, write_simulation
    from lightfield_jax.inverse.capture_fit import fit_capture

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in ("grid", "gradient", "joint"):
            raise ValueError(f"--methods: unknown method {m!r} (grid, gradient, joint)")
    _outputs(folders=[args.out])
    out = Path(args.out)
    config = parse_simulation_config(DEMO_CONFIG, source="demo config")
    _use_xla_cache(args)
    with _progress(args, "demo") as stage:
        stage("simulate the capture")
        sim = simulate_capture(config, stage=stage)
        with atomic_directory(out) as staging:
            write_simulation(sim, staging)
        capture = load_capture(out / "capture.yaml")
        truth = sim.truth()
        rows, results, again = [], {}, {}
        for method in methods:
            stage(f"fit: {method}")
            fit = fit_capture(capture, method, progress=stage).results[0]
            results[method] = _label_two_step(method, fit.to_dict())
            rows.append((method, fit))
            # The same fit once more: the programs compiled above are reused, as for
            # another channel or the next capture of this size in one process.
            stage(f"fit again: {method}")
            again[method] = fit_capture(capture, method).results[0].seconds["total"]
        atomic_write_json(out / "results.json", {"truth": truth, "fits": results})
        if "joint" in results:
            stage("plot")
            from lightfield_jax.viz import plot_fit

            joint = dict(rows)["joint"]
            plot_fit(capture.images[..., 0], capture.pattern, joint, out / "demo_fit.png")
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
    _say(args, "\n".join(lines))
    _say(
        args,
        f"wrote {out}/ (capture, results.json" + (", demo_fit.png)" if "joint" in results else ")"),
    )
    return None if all(r.converged for _, r in rows) else 1


# --------------------------------------------------------------------------- pattern


@command(
    "pattern",
    "write the projector's stripe images and a capture.yaml template for them",
    arg("--width", type=_positive_int, required=True, help="projector width (pixels)"),
    arg("--height", type=_positive_int, required=True, help="projector height (pixels)"),
    arg("--period", type=_positive_int, default=6, help="stripe period (%(default)s)"),
    arg("--lit", type=_positive_int, default=3, help="lit rows per period (%(default)s)"),
    arg("--shifts", type=_positive_int, help="shifted images (default: the period)"),
    arg(
        "--orientation",
        choices=("rows", "columns"),
        default="rows",
        help="stripes along projector rows or columns (%(default)s)",
    ),
    arg("--out", metavar="DIR", required=True, help="output folder (created; files replaced)"),
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
    from lightfield_jax.app.memory import check_memory
    from lightfield_jax.capture.io import atomic_directory
    from lightfield_jax.capture.pattern import (
        check_size,
        pattern_memory,
        pattern_phases,
        write_patterns,
    )

    _outputs(folders=[args.out])
    out = Path(args.out)
    check_size(args.width, args.height, args.period)
    phases = pattern_phases(args.period, args.lit, args.shifts)
    check_memory(
        pattern_memory(args.width, args.height, len(phases)),
        f"pattern: {len(phases) + 2} images of {args.width}x{args.height}",
    )
    with atomic_directory(out) as staging:
        files = write_patterns(
            staging, args.width, args.height, args.period, args.lit, args.shifts, args.orientation
        )
    _say(
        args,
        f"wrote {len(files)} files to {out}: {len(phases)} stripe images (period {args.period}, "
        f"lit {args.lit}, phases {list(phases)}, {args.orientation}), white.png, black.png, "
        "capture.yaml",
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
    from lightfield_jax.capture.capture import capture_files, load_capture
    from lightfield_jax.capture.inspect import inspect_capture
    from lightfield_jax.capture.io import atomic_write_json

    _outputs(
        files=[args.plot, args.json, args.response],
        inputs=capture_files(args.capture),
        plots=[args.plot] if args.plot else [],
    )
    plot = Path(args.plot) if args.plot else None
    out = Path(args.json) if args.json else None
    response = Path(args.response) if args.response else None
    capture = load_capture(args.capture)
    if response is not None and capture.brackets is None:
        raise ValueError(f"--response: {args.capture} has no exposure brackets")
    with _progress(args, "inspect") as stage, _about(capture), staged_files() as write:
        stage("separate")
        inspection = inspect_capture(capture)
        if plot is not None:
            stage("plot")
            from lightfield_jax.viz import plot_inspect

            plot_inspect(inspection, write(plot))
        if out is not None:
            atomic_write_json(write(out), inspection.to_dict())
        if response is not None:
            from lightfield_jax.capture.hdr import write_response

            write_response(write(response), capture.brackets.response, capture.channel_names)
    _say(args, inspection.summary())
    written = [f for f in (plot, out, response) if f is not None]
    if written:
        _say(args, f"wrote {', '.join(str(f) for f in written)}")
    problems = inspection.problems()
    for problem in problems:
        _warn(args, f"{capture.source}: {problem}")
    return 1 if problems else None


# --------------------------------------------------------------------------- render


@command(
    "render",
    "render a fitted medium's per-bounce images and light fields in its capture's geometry",
    arg("results", metavar="RESULTS.json", help="a results file of lightfield-jax fit"),
    arg("--out", metavar="DIR", required=True, help="output folder (created; files replaced)"),
    arg(
        "--plot",
        action="store_true",
        help="also write the paper's figures: bounce_images.png, bounce_profiles.png, "
        "lightfield.png",
    ),
)
def _render_command(args: argparse.Namespace) -> None:
    """Render the medium a fit recovered (RESULTS.json names its capture, whose entry
    wall and light direction are used) under full illumination, on the fit's model
    (its region of the medium ROI, theta bins, bounces, geometry), and write into DIR
    (one subfolder per channel when the results hold several):

      bounces.npy     float32 [K, H, W] per-bounce images (index k-1 holds I_k),
                      fitted gain included
      bounces.exr     channels I1..IK
      lightfield.npy  float32 [K+1, H, W, n_theta] L_0..L_K, radiance per radian
                      (left out, with a warning, above 5e7 floats)
      render.json     the medium, model region, illumination
      *.png           with --plot: the bounce images, each bounce's profile along
                      the light, the light fields with direction glyphs

    Nothing is written unless the whole command succeeds."""
    from lightfield_jax.capture.io import atomic_directory
    from lightfield_jax.capture.views import render_results

    _outputs(
        folders=[args.out],
        inputs=[args.results],
        folder_names=("bounces.npy", "bounces.exr", "lightfield.npy", "render.json", "*.png"),
    )
    out = Path(args.out)
    with _progress(args, "render") as stage, atomic_directory(out) as staging:
        files, notes = render_results(args.results, staging, plot=args.plot, stage=stage)
    for note in notes:
        _warn(args, note)
    _say(args, f"wrote {len(files)} files to {out}: {', '.join(files)}")


# --------------------------------------------------------------------------- experiment


@command(
    "experiment",
    "run a config-driven experiment (experiments/NAME.py with configs/NAME.yaml)",
    arg("config", metavar="CONFIG.yaml", help="an experiment config (configs/)"),
    arg("--out", metavar="DIR", help="results folder (default: results/NAME)"),
    arg("--reduced", action="store_true", help="the config's reduced size (as the tests run)"),
)
def _experiment(args: argparse.Namespace) -> None:
    """Run an experiment: it writes data (JSON/CSV) and figures (PNG) into DIR, plus
    summary.json with the config, software versions, machine and date. A rerun into
    the same DIR resumes from the work already stored in DIR/cache."""
    from lightfield_jax.app.experiment import run_experiment

    _outputs(folders=[args.out])
    with _progress(args, "experiment") as stage:
        record = run_experiment(args.config, args.out, reduced=args.reduced, progress=stage)
    _say(args, json.dumps(record["summary"], indent=1, default=str)[:4000])
    _say(args, f"experiment {record['experiment']} done in {record['seconds']:.1f} s")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

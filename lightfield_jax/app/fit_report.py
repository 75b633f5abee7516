"""What ``fit`` and ``fit --batch`` report of a fit: its summary lines, the comparison
with a capture's truth, its JSON record and its figures."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from lightfield_jax.checks import one_path_part

# The fit's memory estimate (fit_memory) and its constants, named here as before.
from lightfield_jax.runtime.memory import FIT_N_THETA as FIT_N_THETA
from lightfield_jax.runtime.memory import RENDER_CELLS_PER_PIXEL as RENDER_CELLS_PER_PIXEL


def fit_summary(fit) -> str:
    return "\n".join(
        channel_summary(name, r) for name, r in zip(fit.channels, fit.results, strict=True)
    )


def channel_summary(name: str, r) -> str:
    """One channel's result line."""
    from lightfield_jax.inverse.budget import CONSISTENCY_P
    from lightfield_jax.scene.geometry_spec import describe_geometry

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


def say_above_progress(args: argparse.Namespace, lines: list[str]) -> None:
    """``lines`` on stdout now (flushed: a log file shows them while the fit goes on),
    clearing a progress bar on the terminal first."""

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
    (:func:`truth_phase_note`)."""
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


def truth_phase_note(capture, phase: str) -> str | None:
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


def figure_names(plot: Path, channels: Sequence[str]) -> list[Path]:
    """FIG.png for one channel; FIG.png and FIG_<channel>.png each for several."""
    if len(channels) == 1:
        return [plot]

    for name in channels:  # else pathlib's "Invalid name 'fit_a/b.png'", naming nothing
        if not one_path_part(name):
            raise ValueError(
                f"--plot: the images' channel {name!r} cannot name a figure "
                f"{plot.stem}_<channel>{plot.suffix} (a path separator); fit without --plot, "
                "or one channel (--channel) at a time"
            )
    return [plot] + [plot.with_name(f"{plot.stem}_{name}{plot.suffix}") for name in channels]


def fit_figures(capture, fit, figures: list[Path], write) -> None:
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
    from lightfield_jax.inverse.capture_fit import channel_mask

    return {"mask": channel_mask(capture, i), "truth": truth_for(capture.truth, i)}


# The two-step methods separate the direct light first; on stripe captures the
# separation is biased (the multiple light is not the same under every shift), and
# their ± (the noise's spread) says nothing of it.
TWO_STEP_METHODS = ("grid", "gradient")


TWO_STEP_CAVEAT = (
    "the two-step methods (grid, gradient) carry the separation bias on stripe "
    "captures: their ± are statistical only (noise), not the error, which can be far "
    "larger; use --method joint (the raw images) for unbiased estimates"
)


def label_two_step(method: str, result: dict) -> dict:
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


def fit_record(capture, fit, method: str, phase: str) -> tuple[dict, list[dict]]:
    """results.json of ``fit`` of ``capture`` (one file or one of a batch), and its
    errors against the capture's truth (empty without one)."""
    result = label_two_step(method, fit.to_dict())
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

"""``lightfield-jax fit A.yaml B.yaml ... --out DIR``: several captures (or folders of
them) fitted in parallel on Dask (see :mod:`lightfield_jax.app.distributed`).

``DIR`` gets one results file per capture (``NAME.json``, the single fit's results.json
plus a ``batch`` record), written as each fit completes, and ``summary.csv`` /
``summary.json`` (one row per capture and channel) at the end. A rerun into ``DIR``
fits only the captures without a stored result of the same capture files and options.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

from lightfield_jax.app.arguments import xla_cache_folder
from lightfield_jax.app.messages import say, warn
from lightfield_jax.app.outputs import check_command_outputs

SUMMARY_COLUMNS = (
    "name",
    "capture",
    "channel",
    "status",
    "sigma_t",
    "sigma_t_sd",
    "sigma_s",
    "sigma_s_sd",
    "g",
    "g_sd",
    "albedo",
    "iterations",
    "seconds",
    "results",
    "error",
)
# A rough time of one fit at the demo's size (128x96 pixels, 6 images) on one core;
# other sizes scale with their pixel count (only for the estimate said before a batch).
DEMO_FIT_SECONDS, DEMO_VALUES = 30.0, 128 * 96 * 6


def capture_list(given: Sequence[str]) -> list[Path]:
    """The capture files of the arguments: a file as given; a folder's ``*.yaml`` and
    ``*/capture.yaml`` (what ``simulate`` writes). A file given twice is refused."""
    paths: list[Path] = []
    for text in given:
        path = Path(text)
        if path.is_dir():
            found = sorted({*path.glob("*.yaml"), *path.glob("*.yml")})
            found += sorted(path.glob("*/capture.yaml"))
            if not found:
                raise ValueError(f"{text}: a folder without capture files (*.yaml, */capture.yaml)")
            paths += found
        else:
            paths.append(path)
    seen: dict[str, Path] = {}
    for path in paths:
        real = os.path.realpath(path)
        if real in seen:
            raise ValueError(f"{path}: the same capture file as {seen[real]}, given twice")
        seen[real] = path
    return paths


def result_names(paths: Sequence[Path]) -> list[str]:
    """Each capture's results name: its file's stem, or ``FOLDER_STEM`` where stems
    repeat (``a/capture.yaml``, ``b/capture.yaml``) or one is ``summary``."""
    stems = [p.stem for p in paths]
    names = [
        s if stems.count(s) == 1 and s != "summary" else f"{p.parent.name}_{s}"
        for p, s in zip(paths, stems, strict=True)
    ]
    for name, path in zip(names, paths, strict=True):
        if names.count(name) > 1 or name == "summary":
            raise ValueError(f"{path}: its results would be named {name}.json like another's")
    return names


def _batch_key(files: Sequence[Path], args: argparse.Namespace) -> str:
    """What a stored result must match to be reused: the capture's files (path, size,
    modification time) and the fit's options."""
    stats = []
    for f in files:
        st = os.stat(f)
        stats.append([os.path.abspath(f), st.st_size, st.st_mtime_ns])
    options = [args.method, args.channel, args.phase, args.max_steps]
    text = json.dumps([stats, options], default=str)
    return hashlib.sha1(text.encode()).hexdigest()


def batch_fit(
    path: str,
    key: str,
    method: str,
    channels: list[str] | None,
    phase: str | None,
    max_steps: int | None,
    xla_folder: str | None,
) -> dict:
    """One capture's fit on a worker: its results.json record, with ``batch`` (the key,
    the summary lines, the notes and the package's warnings of the fit)."""
    import warnings

    from lightfield_jax.app.fit_report import fit_record, fit_summary, truth_lines
    from lightfield_jax.app.messages import about_capture
    from lightfield_jax.capture.capture import CaptureWarning
    from lightfield_jax.capture.keys import fit_phase
    from lightfield_jax.capture.loading import load_capture
    from lightfield_jax.forward.render import DivergentSeriesWarning
    from lightfield_jax.inverse.capture_fit import fit_capture
    from lightfield_jax.inverse.programs import use_compilation_cache

    notes: list[str] = []
    if xla_folder is not None:  # (once per worker process: nothing after the first)
        try:
            use_compilation_cache(Path(xla_folder))
        except OSError as e:  # a worker elsewhere, its home laid out otherwise
            notes.append(f"note: XLA compilation cache off on this worker: {e}")

    def staged(message: str) -> None:
        if message.startswith("note: ") or re.match(r"\[[^]]*\] note: ", message):
            notes.append(message)

    limits = {} if max_steps is None else {"max_steps": max_steps}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("ignore", CaptureWarning)  # said when the batch checked it
        warnings.simplefilter("always", DivergentSeriesWarning)
        capture = load_capture(path)
        phase = phase or fit_phase(capture)  # --phase, else each capture's own
        with about_capture(capture):
            fit = fit_capture(
                capture, method, channels=channels, progress=staged, phase=phase, **limits
            )
    result, compared = fit_record(capture, fit, method, phase)
    result["batch"] = {
        "key": key,
        "summary": [fit_summary(fit), *truth_lines(fit, compared)],
        "notes": notes,
        "warnings": [" ".join(str(w.message).split()) for w in caught],
    }
    return result


def _rows(name: str, path: Path, record: dict | None, error: str | None) -> list[dict]:
    """The summary rows of one capture: one per channel fitted."""
    base = {"name": name, "capture": str(path), "results": f"{name}.json"}
    if record is None:
        return [{**base, "status": "failed", "error": error, "results": ""}]
    per = record.get("per_channel") or {record.get("channel"): record}
    rows = []
    for channel, r in per.items():
        u = r.get("uncertainty", {})
        rows.append(
            {
                **base,
                "channel": channel,
                "status": "ok" if r["converged"] else "not converged",
                **{k: r[k] for k in ("sigma_t", "sigma_s", "g", "albedo", "iterations")},
                **{f"{k}_sd": u.get(k) for k in ("sigma_t", "sigma_s", "g")},
                "seconds": r["seconds"]["total"],
            }
        )
    return rows


def fit_batch(args: argparse.Namespace) -> int | None:
    """``fit`` of several captures (see the module docstring); exit status 1 when a fit
    failed or did not converge (the others' results written)."""
    from lightfield_jax.app.distributed import (
        Task,
        check_count,
        check_workers,
        default_workers,
        run_tasks,
        scheduler_address,
    )
    from lightfield_jax.app.experiment_records import provenance, write_csv
    from lightfield_jax.capture.loading import load_capture
    from lightfield_jax.capture.paths import capture_files
    from lightfield_jax.files import atomic_write_json
    from lightfield_jax.inverse.options import FitOptions
    from lightfield_jax.runtime.memory import check_memory, fit_memory

    if args.plot:
        raise ValueError("--plot: one capture at a time (several write results and summaries)")
    paths = capture_list(args.capture)
    check_count(len(paths), args.allow_large, "captures")
    if scheduler_address(args.scheduler) is None:  # a local cluster: before the loads
        check_workers(args.workers)
    out = Path("results" if args.out is None else args.out)
    if out.suffix.lower() == ".json":
        raise ValueError(
            f"--out {args.out}: several captures write a folder (one results file per "
            "capture, summary.csv, summary.json), not a .json file"
        )
    names = result_names(paths)
    files = [capture_files(p) for p in paths]
    check_command_outputs(
        folders=[out],
        inputs=[f for fs in files for f in fs],
        folder_names=("*.json", "*.csv"),
        marker="summary.json",
    )
    # Every capture read once here: a bad one is refused (exit 2) before any fit.
    values = []
    for path in paths:
        capture = load_capture(path)
        unknown = sorted(set(args.channel or ()) - set(capture.channel_names))
        if unknown:
            raise ValueError(
                f"{path}: --channel {', '.join(unknown)}: not among its channels "
                f"({', '.join(capture.channel_names)})"
            )
        h, w = capture.shape
        options = FitOptions(**capture.fit_options)
        check_memory(
            fit_memory(capture.images.size, capture.n_images, h, w, options.model),
            f"{capture.source}: the fit",
        )
        for note in capture.notes:
            say(args, f"note: {path}: {note}")
        values.append(capture.images.size)
        del capture
    xla = None if args.no_xla_cache else xla_cache_folder()
    if xla is not None:
        try:
            xla.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            warn(args, f"XLA compilation cache off: cannot create {xla} ({e.strerror})")
            xla = None
    keys = [_batch_key(fs, args) for fs in files]
    tasks = [
        Task(
            key,
            str(path),
            batch_fit,
            (
                os.path.abspath(path),  # a worker of a cluster may run elsewhere
                key,
                args.method,
                args.channel,
                args.phase,
                args.max_steps,
                None if xla is None else str(xla),
            ),
        )
        for path, key in zip(paths, keys, strict=True)
    ]
    where = {t.key: (name, path) for t, name, path in zip(tasks, names, paths, strict=True)}

    def load(task: Task):
        try:
            stored = json.loads((out / f"{where[task.key][0]}.json").read_text())
        except (OSError, ValueError):
            return None
        batch = stored.get("batch") if isinstance(stored, dict) else None
        return stored if isinstance(batch, dict) and batch.get("key") == task.key else None

    def save(task: Task, record: dict) -> None:
        # made at the first result: a cluster that cannot start leaves no empty folder
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / f"{where[task.key][0]}.json", record)

    workers = args.workers if args.workers is not None else default_workers()
    memory = None if args.max_memory is None else max(1, args.max_memory // workers)
    mean = sum(values) / len(values)
    report = run_tasks(
        tasks,
        load=load,
        save=save,
        scheduler=args.scheduler,
        workers=workers,
        memory_limit=memory,
        timeout=args.time_limit,
        seconds_per_task=max(5.0, DEMO_FIT_SECONDS * mean / DEMO_VALUES),
        allow_large=True,  # counted above
        what="captures",
        say=lambda m: say(args, m),
        show_progress=False if args.quiet else None,
        desc="fits",
    )
    rows, captures = [], []
    for task in tasks:
        name, path = where[task.key]
        record = report.results.get(task.key)
        error = report.failures.get(task.key)
        rows += _rows(name, path, record, error)
        captures.append(
            {
                "name": name,
                "capture": str(path),
                "results": f"{name}.json" if record is not None else None,
                "status": "failed"
                if record is None
                else ("ok" if record["converged"] else "not converged"),
                "error": error,
                "computed": task.key in report.computed,
            }
        )
        if record is not None and task.key in report.computed:
            for line in record["batch"]["notes"]:
                say(args, f"{path}: {line}")
            for line in record["batch"]["warnings"]:
                warn(args, f"{path}: {line}")
    out.mkdir(parents=True, exist_ok=True)
    write_csv(
        out / "summary.csv",
        SUMMARY_COLUMNS,
        ([row.get(c, "") for c in SUMMARY_COLUMNS] for row in rows),
    )
    atomic_write_json(
        out / "summary.json",
        {
            "command": "fit",
            "method": args.method,
            "phase": args.phase,
            "captures": captures,
            "rows": rows,
            "fits": len(tasks),
            "computed": len(report.computed),
            "failed": len(report.failures),
            "workers": report.workers,
            "seconds": report.seconds,
            **provenance(),
        },
    )
    for row in rows:
        if row["status"] != "failed":
            say(
                args,
                f"{row['name']} [{row['channel']}]: sigma_t {row['sigma_t']:.5g}, sigma_s "
                f"{row['sigma_s']:.5g}, g {row['g']:.4f} ({row['status']})",
            )
    say(args, f"wrote {len(report.results)} results, summary.csv and summary.json to {out}")
    for task in tasks:
        if task.key in report.failures:
            warn(args, f"failed: {report.failures[task.key]}")
    bad = [c for c in captures if c["status"] == "not converged"]
    if bad:
        warn(
            args,
            f"{len(bad)} fit(s) did not converge ({', '.join(c['name'] for c in bad)}): "
            "their results were written with converged: false",
        )
    return 1 if report.failures or bad else None

"""The ``rollingstar`` command line (typer). Bad input exits 2 with a one-paragraph message.

The commands import the library inside their bodies: ``main`` sets the BLAS thread count before
numpy is first imported, and ``rollingstar --help`` or ``--version`` stays instant.
"""
from __future__ import annotations

import errno
import functools
import importlib
import json
import sys
import warnings
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rollingstar import __version__
from rollingstar.config import find_config
from rollingstar.errors import UserError
from rollingstar.outputs import write_text

app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, no_args_is_help=True,
                  help="Star-tracker estimation with rolling-shutter CMOS sensors.")
out = Console(width=None if sys.stdout.isatty() else 200)  # no truncated cells when piped
err = Console(stderr=True)


def _print_version(value: bool) -> None:
    if value:
        print(f"rollingstar {__version__}")
        raise typer.Exit()


_state = {"debug": False}


@app.callback()
def _options(version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                          help="print the version and exit"),
             debug: bool = typer.Option(False, "--debug", help="on an error, show the Python traceback "
                                                               "(for a bug report) instead of the message")):
    """Star-tracker estimation with rolling-shutter CMOS sensors."""
    _state["debug"] = debug


def _error_message(exc: BaseException) -> str:
    """One paragraph for an exception that reached the command line: what failed and what to do."""
    from rollingstar.config import excerpt
    from rollingstar.logs.errors import LogFormatError, LogWriteError

    if isinstance(exc, (UserError, LogFormatError, LogWriteError)):
        return str(exc)
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if exc.filename else ""
        advice = {errno.ENOSPC: " (the disk is full: free space and run the command again)",
                  errno.EROFS: " (a read-only file system: write the output somewhere else)",
                  errno.EACCES: " (no permission: choose a path you may write, or fix its permissions)"}
        return f"{where}{exc.strerror or exc}{advice.get(exc.errno, '')}"
    if isinstance(exc, MemoryError):
        return "ran out of memory: ask for fewer frames, a smaller image or fewer tasks"
    if isinstance(exc, RecursionError):
        return "an input is nested too deeply to read (a JSON or YAML value inside thousands of brackets)"
    if isinstance(exc, OverflowError):
        return f"a number in the input is too large: {excerpt(str(exc), 200)}"
    return (f"unexpected {type(exc).__name__}: {excerpt(str(exc), 300)}. This is a bug or an input rollingstar "
            "does not check yet; run the command again with --debug (rollingstar --debug ...) and report the "
            "traceback with the input that caused it")


def _guarded(fn):
    """The command line's one error boundary, put around every command by :func:`command`.

    Every exception becomes a one-paragraph message on stderr and exit code 2 (130 on Ctrl-C, after
    the message of what was kept); ``--debug`` shows the traceback instead. Exit code 1 is reserved
    for commands that ran fine but whose check failed (the regression gate, ``bench perf``).
    Warnings are printed as one line each, a repeated one once (a file opened by several steps
    warns each time it is opened)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("always")
                warnings.showwarning = _printer(set())
                return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt as exc:  # SIGINT: the output was finalised (pipelines/interrupt.py)
            err.print(str(exc) or "interrupted", highlight=False, soft_wrap=True)
            raise typer.Exit(130) from None
        except Exception as exc:
            if _state["debug"]:
                raise
            err.print(f"[bold red]error:[/] {escape(_error_message(exc))}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None

    return wrapper


def _printer(shown: set[str]):
    """A ``warnings.showwarning`` that prints each distinct message once, as one line on stderr."""
    def show(message, category, *args, **kwargs):
        if str(message) not in shown:
            shown.add(str(message))
            err.print(f"[yellow]warning:[/] {message}")
    return show


def _quiet():
    return typer.Option(False, "--quiet", "-q", help="no progress bars (none are drawn when the output is not a "
                        "terminal either)")


def _seed_in_range(value: int | None) -> int | None:
    if value is not None and not 0 <= value < 2**63:
        raise typer.BadParameter("a seed is an integer from 0 to 2^63 - 1")
    return value


def _seed(default: int | None = 1, help: str = "random seed: the same seed gives the same numbers"):
    return typer.Option(default, "--seed", callback=_seed_in_range, help=help)


_typer_display_type = typer.core.TyperOption.display_type_rich


def _display_type_without_flags(self, ctx):
    """typer (0.29) labels every flag ``<bool>`` in ``--help`` although a flag takes no value; a flag
    shows no type, every other option its own."""
    return None if self.is_flag else _typer_display_type(self, ctx)


typer.core.TyperOption.display_type_rich = _display_type_without_flags


def command(group: typer.Typer | None = None, name: str | None = None):
    """Register a command on ``group`` (default: the top-level app) inside the error boundary."""
    return lambda fn: (group or app).command(name)(_guarded(fn))


@command()
def simulate(scenario: str = typer.Argument(..., help="scenario YAML, or a shipped scenario's name (he2021b)"),
             output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
             frames: int = typer.Option(None, "--frames", min=1, help="override the scenario's frame count"),
             seed: int = _seed(None, "override the scenario's seed"),
             quiet: bool = _quiet()):
    """Simulate a recording from a scenario."""
    from rollingstar.pipelines.simulate import simulate_to_log
    from rollingstar.sensors.scenario import load_scenario

    path = find_config(scenario, "scenario")
    summary = simulate_to_log(load_scenario(path), output, frames=frames, seed=seed, show_progress=not quiet,
                              inputs=[path])
    out.print(f"wrote {summary.path}: {summary.frames} frames ({summary.level} level), "
              f"{summary.stars_per_frame_mean:.1f} stars per frame, {summary.duration_s:.2f} s")


@command()
def run(pipeline: str = typer.Argument(..., help="pipeline YAML, or a shipped pipeline's name (baseline)"),
        recording: Path = typer.Argument(..., help="input MCAP recording"),
        output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
        resume: bool = typer.Option(False, "--resume", help="continue from a partial output (killed or interrupted run)"),
        checkpoint_every: int = typer.Option(500, "--checkpoint-every", min=0,
                                             help="save the stages' state every N frames for --resume (0: never)"),
        with_images: bool = typer.Option(False, "--with-images", help="copy the recording's images into the output "
                                         "(/camera/image), so that it opens complete in Foxglove (docs/foxglove.md)"),
        quiet: bool = _quiet()):
    """Run a pipeline over a recording: estimates, their outcomes and (with truth) their errors, in one MCAP."""
    from rollingstar.pipelines.config import load_pipeline
    from rollingstar.pipelines.runner import run_pipeline

    pipeline = find_config(pipeline, "pipeline")
    cfg = load_pipeline(pipeline)
    s = run_pipeline(recording, cfg, output, pipeline_source=str(pipeline), show_progress=not quiet, resume=resume,
                     checkpoint_every=checkpoint_every, inputs=[pipeline], with_images=with_images)
    if resume:
        out.print(f"resumed from a checkpoint after {s.resumed_after_frames} frames" if s.resumed_after_frames else
                  "resumed: no usable checkpoint, every frame re-run from the first")
    out.print(f"wrote {s.output}: {s.outcomes.sentence()}", highlight=False)
    for hint in s.outcomes.hints():
        out.print(f"[bold yellow]hint[/]: {hint}", highlight=False)


@command()
def evaluate(log: Path = typer.Argument(..., help="output MCAP of `rollingstar run`"),
             as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of the tables"),
             skip_first: int = typer.Option(0, "--skip-first", min=0, metavar="FRAMES",
                                            help="leave the first FRAMES frames out of every metric (a filter's "
                                                 "start-up transient)"),
             skip_first_s: float = typer.Option(0.0, "--skip-first-s", min=0.0, metavar="SECONDS",
                                                help="leave out the frames that start within SECONDS of the first"),
             plots: Path = typer.Option(None, "--plots", metavar="DIR", file_okay=False,
                                        help="write attitude_error.png, centroid_residuals.png and rate_error.png "
                                             "(when the run has rates) into DIR")):
    """Metrics of an output log against the truth it carries, per camera axis, beside the Cramér–Rao bounds."""
    from rollingstar.pipelines.evaluate import evaluate_log

    metrics = evaluate_log(log, skip_first=skip_first, skip_first_s=skip_first_s, series=plots is not None)
    written = []
    if plots is not None:
        from rollingstar.logs.reader import LogReader
        from rollingstar.pipelines.plots import evaluation_plots

        sensor = LogReader(log).scenario("cannot plot without it").sensor
        written = evaluation_plots(metrics, plots, (sensor.width_px, sensor.height_px), label=log.stem, inputs=[log])
        metrics.pop("series")
    if as_json:
        print(json.dumps(metrics, indent=2))
    else:
        print_metrics(metrics, title=str(log))
    sys.stdout.flush()
    for path in written:
        err.print(f"wrote {path}", highlight=False)


def _f(v, fmt="{:.4g}"):
    return "n/a" if v is None else fmt.format(v)


def print_metrics(m: dict, title: str = "") -> None:
    """The tables of ``rollingstar evaluate``: errors, bounds and efficiency per camera axis, then the
    frame outcomes and the reason for every n/a."""
    f = _f
    table = Table(title=title or None, show_header=True)
    table.add_column("metric")
    for a in "xyz":
        table.add_column(a, justify="right")
    a, crb = m["attitude_error_arcsec"], m["attitude_crb_arcsec"]
    table.add_row("attitude error RMSE (arcsec)", f(a["x_rmse"]), f(a["y_rmse"]), f(a["z_rmse"]))
    table.add_row("attitude error max (arcsec)", f(a["x_max"]), f(a["y_max"]), f(a["z_max"]))
    pcrb, prcrb = m.get("pixel_crb_arcsec") or {}, m.get("pixel_rate_crb_deg_s") or {}
    table.add_row("attitude bound, centroid-level (given sigma) (arcsec)", f(crb["x"]), f(crb["y"]), f(crb["z"]))
    ucrb = m.get("attitude_crb_rate_unknown_arcsec") or {}
    table.add_row("attitude bound, centroid-level, rate unknown (arcsec)", *(f(ucrb.get(a)) for a in "xyz"))
    table.add_row("attitude bound, pixel-level (arcsec)", *(f(pcrb.get(a)) for a in "xyz"))
    r, rcrb = m["rate_error_deg_s"], m.get("rate_crb_deg_s") or {}
    has_rate = r.get("x_rmse") is not None
    if has_rate:
        table.add_row("rate error RMSE (deg/s)", f(r["x_rmse"]), f(r["y_rmse"]), f(r["z_rmse"]))
        table.add_row("rate bound, centroid-level (given sigma) (deg/s)", *(f(rcrb.get(a)) for a in "xyz"))
    if has_rate or prcrb.get("x") is not None:
        table.add_row("rate bound, pixel-level (deg/s)", *(f(prcrb.get(a)) for a in "xyz"))
    for key, level in (("efficiency", "centroid-level"), ("efficiency_pixel", "pixel-level")):
        eff = m.get(key) or {}
        table.add_row(f"efficiency: attitude RMSE / {level} bound", *(f(eff.get(f"attitude_{a}"), "{:.3g}") for a in "xyz"))
        if has_rate:
            table.add_row(f"efficiency: rate RMSE / {level} bound", *(f(eff.get(f"rate_{a}"), "{:.3g}") for a in "xyz"))
    out.print(table)
    axes = m.get("axes") or {}
    if axes:
        out.print("axes: " + "; ".join(f"{k} = {v}" for k, v in axes.items()), highlight=False)
    summary = Table(show_header=False)
    summary.add_column("k")
    summary.add_column("v", justify="right")
    outcomes = m.get("outcomes")
    if outcomes:
        from rollingstar.pipelines.outcomes import Outcomes

        o = Outcomes.from_dict(outcomes)
        skipped = m.get("skipped_frames") or 0
        summary.add_row("frames" + (f" (after skipping {skipped})" if skipped else ""), o.sentence())
    summary.add_row("update rate (Hz)", f(m["update_rate_hz"]))
    summary.add_row("identified stars per frame", f(m["identified_stars_per_frame"]))
    summary.add_row("centroid error RMSE / max (px)", f"{f(m['centroid_error_px']['rmse'])} / {f(m['centroid_error_px']['max'])}")
    p = m["star_pair_distance_error_px"]
    summary.add_row("star-pair distance error RMSE / max (px)", f"{f(p['rmse'])} / {f(p['max'])}")
    r = m["rate_error_deg_s"]
    summary.add_row("rate error RMSE / max (deg/s)", f"{f(r['rmse'])} / {f(r['max'])}")
    out.print(summary)
    for key, why in (m.get("notes") or {}).items():
        out.print(f"n/a {key}: {why}", highlight=False)
    if m.get("truth_convention"):
        out.print(f"[bold yellow]warning[/]: {m['truth_convention']}", highlight=False)


@command()
def info(log: Path = typer.Argument(..., help="MCAP file")):
    """Topics, message counts, time range, schemas and metadata of a log."""
    from rollingstar.logs.reader import LogReader

    reader = LogReader(log)
    s = reader.summary_info()
    span = "-" if s.start_ns is None else f"{s.start_ns * 1e-9:.6f} s to {s.end_ns * 1e-9:.6f} s"
    out.print(f"[bold]{log}[/]: format {s.format_version}, {s.message_count} messages, {span}"
              f"{' (TRUNCATED: complete messages only)' if s.truncated else ''}", highlight=False)
    table = Table()
    for col in ("topic", "schema", "encoding", "messages", "first (s)", "last (s)"):
        table.add_column(col, no_wrap=True)
    for t in s.topics.values():
        table.add_row(t.topic, t.schema_name, t.encoding, str(t.message_count),
                      f"{t.start_ns * 1e-9:.6f}" if t.start_ns is not None else "-",
                      f"{t.end_ns * 1e-9:.6f}" if t.end_ns is not None else "-")
    out.print(table)
    for name, record in reader.metadata().items():
        out.print(f"[bold]metadata {name}[/]")
        for k, v in record.items():
            text = v if len(v) < 2000 else v[:2000] + " ..."
            if "\n" in text.strip():  # a YAML document: indented under its key, as YAML nests it
                body = "\n".join(f"    {line}" for line in text.strip("\n").splitlines())
                out.print(f"  {k}: |\n{body}", highlight=False)
            else:
                out.print(f"  {k}: {text}", highlight=False)


@command()
def preview(log: Path = typer.Argument(..., help="MCAP file (a run's output, ideally written with --with-images)"),
            output: Path = typer.Option(..., "-o", "--output", help="PNG file to write"),
            layout: Path = typer.Option(None, "--layout", help="Foxglove layout JSON (default: the shipped "
                                        "configs/foxglove/run.json)"),
            frame: int = typer.Option(None, "--frame", min=0, help="image shown (default: the middle one)")):
    """A still picture of a log as a Foxglove layout shows it: the image with its overlays and every plot."""
    from rollingstar.pipelines.preview import DEFAULT_LAYOUT, render_preview

    path = render_preview(log, output, layout or DEFAULT_LAYOUT, frame)
    out.print(f"wrote {path}", highlight=False)


@command()
def plugins(name: str = typer.Argument(None, metavar="[KIND|ROLE]",
                                        help="show only this plugin kind (cog) or role (centroider)")):
    """Every registered plugin by role: each parameter's type, default, unit and meaning."""
    from rollingstar.pipelines.plugin_docs import parameters, summary
    from rollingstar.pipelines.registry import available_kinds, plugins_by_role

    kinds = {target: kind for kind, target in available_kinds().items()}
    shown = 0
    for role, classes in plugins_by_role().items():
        chosen = [c for c in classes if name in (None, role, kinds.get(f"{c.__module__}:{c.__name__}", c.name))]
        if not chosen:
            continue
        table = Table(title=f"role: {role}", title_justify="left", show_lines=False)
        for col, justify in (("kind", "left"), ("parameter", "left"), ("type", "left"), ("default", "right"),
                             ("unit", "left"), ("meaning", "left")):
            table.add_column(col, justify=justify, overflow="fold")
        for cls in chosen:
            kind = kinds.get(f"{cls.__module__}:{cls.__name__}", cls.name)
            table.add_row(f"[bold]{escape(kind)}[/]", "", "", "", "", f"[italic]{escape(summary(cls))}[/]")
            for p in parameters(cls):
                table.add_row("", p.name, escape(p.type), escape(p.default), p.unit, escape(p.description))
            table.add_section()
            shown += 1
        out.print(table)
    if not shown:
        raise UserError(f"plugins {name}: no plugin kind or role of that name; `rollingstar plugins` lists them all")


@command()
def demo(output: Path = typer.Option(Path("rollingstar-demo"), "-o", "--output", file_okay=False,
                                     help="folder for the recording, both runs and the plot (replaced as a whole)"),
         frames: int = typer.Option(None, "--frames", min=2, help="frames to simulate (default: the scenario's 100)"),
         quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bars")):
    """What modelling the rolling shutter gains: the embedded scenario through the baseline and the
    rolling-shutter bundle, side by side against the Cramér–Rao bound, with a plot."""
    from rollingstar.pipelines.demo import run_demo

    r = run_demo(output, frames, show_progress=not quiet)
    sc, m = r["scenario"], r["metrics"]
    base, rs = m["baseline"], m["rs-bundle"]
    readout_ms = sc.shutter.line_delay_us * sc.sensor.height_px * 1e-3
    out.print(f"[bold]rollingstar demo[/]: a star tracker ({sc.sensor.width_px} x {sc.sensor.height_px}, "
              f"{sc.shutter.exposure_ms:g} ms exposure, rolling shutter: the last row starts {readout_ms:.0f} ms after "
              f"the first) turning at {sc.motion.rate_deg_s[0]:g} deg/s about camera x; {r['simulated'].frames} frames, "
              f"{r['simulated'].stars_per_frame_mean:.1f} stars per frame.", highlight=False)
    out.print("What you are looking at: the same stars of every frame solved twice, by the [bold]baseline[/] "
              "(QUEST: the frame treated as one instant, as if the rate were zero) and by the [bold]rolling-shutter "
              "bundle[/] (one attitude and one body rate fitted to every star at its own row time). The bounds are "
              "the best any single-frame estimator can do with centroids of "
              f"{sc.noise.centroid_sigma_px:g} px: with the rate known, and with the rate unknown (one frame "
              "must find it too). The baseline's zero rate costs it little across the boresight (x, y) and "
              "biases its roll (z).", highlight=False)
    table = Table(title="attitude error RMSE per camera axis (arcsec)")
    for col in ("axis", "bound, rate known", "bound, rate unknown", "baseline", "rs-bundle", "baseline / rs-bundle",
                "rs-bundle / bound (rate unknown)"):
        table.add_column(col, justify="left" if col == "axis" else "right")
    words = {"x": "x (cross-boresight)", "y": "y (cross-boresight)", "z": "z (roll, about the boresight)"}
    for a in "xyz":
        known, unknown = base["attitude_crb_arcsec"][a], rs["attitude_crb_rate_unknown_arcsec"][a]
        e_base, e_rs = base["attitude_error_arcsec"][f"{a}_rmse"], rs["attitude_error_arcsec"][f"{a}_rmse"]
        ratio = "n/a" if e_base is None or not e_rs else f"{e_base / e_rs:.2f}x"
        table.add_row(words[a], _f(known, "{:.3g}"), _f(unknown, "{:.3g}"), _f(e_base, "{:.3g}"), _f(e_rs, "{:.3g}"),
                      ratio, _f(None if e_rs is None or not unknown else e_rs / unknown, "{:.2f}"))
    out.print(table)
    for name, metrics in m.items():
        from rollingstar.pipelines.outcomes import Outcomes

        out.print(f"{name}: {Outcomes.from_dict(metrics['outcomes']).sentence()}", highlight=False)
    rate = rs["rate_error_deg_s"]
    if rate["rmse"] is not None:
        out.print(f"rs-bundle also estimates the body rate: error RMSE {rate['rmse']:.3g} deg/s "
                  f"(bound per axis {', '.join(_f(rs['rate_crb_deg_s'][a], '{:.2g}') for a in 'xyz')} deg/s).",
                  highlight=False)
    out.print(f"plot: {r['plot']}", highlight=False)
    d = r["dir"]
    out.print("next (activate the environment first: . .venv/bin/activate):", highlight=False)
    for cmd, why in ((f"rollingstar evaluate {d}/rs-bundle.mcap --plots {d}-plots", "every metric, and its plots"),
                     (f"rollingstar info {d}/recording.mcap", "what a recording holds"),
                     ("rollingstar simulate he2021a -o rec.mcap --frames 30", "an image-level recording at 1 deg/s"),
                     ("rollingstar run high_dynamic rec.mcap -o out.mcap", "pixels to attitude, cold start included"),
                     ("rollingstar plugins", "every estimator you can put in a pipeline"),
                     ("rollingstar compare --help", "estimators side by side over scenarios and seeds")):
        out.print(f"  {cmd:62s} # {why}", highlight=False)


@command()
def reproduce(paper: str = typer.Argument(..., help="he2021a | he2021b | fu2022 | liu2013"),
              quick: bool = typer.Option(False, "--quick", help="the reduced version the test suite runs"),
              as_json: bool = typer.Option(False, "--json", help="print one JSON object {rows: [...]}"),
              plots: Path = typer.Option(None, "--plots", help="write the paper's figures redrawn from our runs here"),
              seed: int = _seed(),
              quiet: bool = _quiet()):
    """Reproduce a seed paper's experiment: paper value, ours (measured now), ratio."""
    from rollingstar.progress import silence
    from rollingstar.studies.reproduce import run_reproduction

    if quiet:
        silence()
    rows = run_reproduction(paper, quick=quick, plots_dir=plots, seed=seed)
    if as_json:
        print(json.dumps({"paper": paper, "quick": quick, "rows": [r.as_dict() for r in rows]}, indent=2))
        return
    table = Table(title=f"{paper}: paper vs ours{' (quick)' if quick else ''}")
    for col in ("quantity", "condition", "paper", "ours", "unit", "ratio", "trials", "source"):
        table.add_column(col)
    for r in rows:
        paper_txt = "-" if r.paper is None else (f"{r.paper:.4g}" if isinstance(r.paper, float) else str(r.paper))
        table.add_row(r.quantity, r.condition, paper_txt, "-" if r.ours is None else f"{r.ours:.4g}", r.unit,
                      "-" if r.ratio is None else f"{r.ratio:.2f}", "-" if r.trials is None else str(r.trials), r.source)
    out.print(table)
    for r in rows:
        if r.note:
            out.print(f"[dim]{r.quantity} ({r.condition}): {r.note}[/]")


@command()
def figures(name: str = typer.Argument("foundation", help="foundation | real-data | real-cameras | adversarial | "
                                        "centroid-covariance | covariance-weighting | wide-angle"),
            quick: bool = typer.Option(False, "--quick", help="the reduced sizes the test suite runs (minutes less, noisier figures)"),
            as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of the tables"),
            out_dir: Path = typer.Option(None, "--out", help="write <out>/<figure>.md, .json and img/*.png (where the set writes pages)"),
            seed: int = _seed(),
            repeats: int = typer.Option(3, "--repeats", min=1, help="real-data: timings are the minimum of this many calls")):
    """Measure a figure set: foundation (static vs Cramér–Rao bound, rolling shutter, image level);
    real-data (identification, per-lens calibration, vs astrometry.net); real-cameras (import + run
    on cameras the pipeline was not tuned on, vs a peer solver); adversarial (no false identification
    reported valid); centroid-covariance (the centroiders' 2 x 2 covariance on smeared images);
    covariance-weighting (attitude RMSE with scalar vs 2 x 2 star weights); wide-angle (the diagnosis
    naming the projection of lenses declared as pinholes)."""
    handlers = {
        "foundation": lambda: _foundation_figures(out_dir, seed, as_json, quick),
        "real-data": lambda: _study("figures", "real_data_figures")(out_dir, as_json, repeats=repeats),
        "real-cameras": lambda: _study("real_cameras", "real_cameras_figures")(quick, as_json, seed),
        "adversarial": lambda: _adversarial_figure(seed, as_json, quick),
        "centroid-covariance": lambda: _study("centroid_covariance", "centroid_covariance_figures")(out_dir, quick, seed, as_json),
        "covariance-weighting": lambda: _covariance_weighting_figure(out_dir, seed, as_json, quick),
        "wide-angle": lambda: _study("wide_angle", "wide_angle_figures")(quick, seed, as_json),
    }
    if name not in handlers:
        raise UserError(f"unknown figure set {name!r}; available: {', '.join(handlers)}")
    handlers[name]()


def _study(module: str, function: str):
    """``rollingstar.studies.<module>.<function>``, imported when the command runs (studies are the
    slowest imports of the package, and each figure set needs only its own)."""
    return getattr(importlib.import_module(f"rollingstar.studies.{module}"), function)


def _foundation_figures(out_dir: Path | None, seed: int, as_json: bool, quick: bool) -> None:
    """The foundation figures (studies/figures.py), printed and optionally written under ``out_dir``."""
    from rollingstar.studies.figures import foundation_markdown, run_foundation, write_foundation_docs

    result = run_foundation(quick=quick, seed=seed)
    command = f"rollingstar figures foundation{' --quick' if quick else ''} --out {out_dir or 'docs'} --seed {seed}"
    if out_dir is not None:
        write_foundation_docs(result, Path(out_dir), command)
    if as_json:
        print(json.dumps(result, indent=2))
    else:
        out.print(foundation_markdown(result, command), highlight=False)


def _covariance_weighting_figure(out_dir: Path | None, seed: int, as_json: bool, quick: bool) -> None:
    """Attitude RMSE per axis, scalar vs 2 x 2 star weighting (studies/covariance_weighting.py)."""
    from rollingstar.studies.covariance_weighting import (
        covariance_weighting_table,
        run_covariance_weighting,
        write_covariance_weighting,
    )

    result = run_covariance_weighting(quick=quick, seed=seed)
    command = f"rollingstar figures covariance-weighting{' --quick' if quick else ''} --seed {seed}"
    if out_dir is not None:
        write_covariance_weighting(result, Path(out_dir), command + f" --out {out_dir}")
    if as_json:
        print(json.dumps(result, indent=2))
    else:
        out.print(covariance_weighting_table(result), highlight=False)


def _adversarial_figure(seed: int, as_json: bool, quick: bool) -> None:
    """Every shipped identifier configuration on adversarial frames (studies/adversarial.py)."""
    from rollingstar.studies.adversarial import adversarial_table, run_adversarial

    result = run_adversarial(frames_per_case=25 if quick else 100, seed=seed, show_progress=not as_json)
    if as_json:
        print(json.dumps(result, indent=2))
    else:
        out.print(adversarial_table(result), highlight=False)


@command()
def diagnose(recording: Path = typer.Option(..., "--recording", help="MCAP recording to diagnose"),
             sim: str = typer.Option(None, "--sim", help="scenario YAML or shipped name (default: the sensor model the recording declares)"),
             pipeline: str = typer.Option(None, "--pipeline", help="pipeline YAML or shipped name (default: cog, lost-in-space starting from the declared attitude when there is one, quest)"),
             out_dir: Path = typer.Option(None, "-o", "--output", help="report directory (index.html, PNGs, scenario_updated.yaml)"),
             as_json: bool = typer.Option(False, "--json", help="print one JSON object"),
             seed: int = _seed(0, "held-out split and bootstrap seed"),
             reference_arcsec: float = typer.Option(None, "--reference-attitude-arcsec", min=0.0,
                                                    help="use the recording's /truth/attitude as a reference of this "
                                                         "accuracy per axis (arcsec): effects the attitude absorbs become testable"),
             mount_free: bool = typer.Option(False, "--reference-mount-free",
                                             help="the reference is not aligned with the camera (a second tracker, an "
                                                  "unsurveyed mount): fit its misalignment with every model"),
             quiet: bool = _quiet()):
    """Locate a simulation/recording mismatch, name the physics left out, model it, show the fit improve."""
    from rollingstar.pipelines.diagnose import (
        DiagnoseOptions,
        print_summary,
        run_diagnose,
    )

    sim = None if sim is None else find_config(sim, "scenario")
    pipeline = None if pipeline is None else find_config(pipeline, "pipeline")
    options = DiagnoseOptions(seed=seed, show_progress=not quiet and not as_json, reference_sigma_arcsec=reference_arcsec,
                              reference_mount_free=mount_free)
    result = run_diagnose(recording, sim, pipeline, out_dir, options)
    if as_json:
        print(json.dumps(result, indent=2))
    else:
        print_summary(result, out)


import_app = typer.Typer(
    no_args_is_help=True,
                         help="Import real recordings (images, astrometry.net corr tables, centroid CSVs) as MCAP logs.")


def _done(path: Path) -> None:
    from rollingstar.logs.importers.common import describe_log

    out.print(describe_log(path), highlight=False)


@command(import_app, "images")
def images(folder: Path = typer.Argument(..., help="folder of TIFF/PNG/JPEG frames (with an optional recording.yaml)"),
           output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
           camera: str = typer.Option(None, "--camera", help="camera.yaml or a shipped camera's name (required "
                                                             "when the folder has no recording.yaml with a camera)"),
           sidecar: Path = typer.Option(None, "--sidecar", help="recording.yaml kept outside the folder "
                                                                "(default: FOLDER/recording.yaml if present)"),
           quiet: bool = _quiet()):
    """A folder of 8/16-bit images -> an image-level recording (foxglove.RawImage frames)."""
    from rollingstar.logs.importers.images import import_images

    camera = None if camera is None else find_config(camera, "camera")
    _done(import_images(folder, output, camera=camera, sidecar=sidecar, show_progress=not quiet))


@command(import_app, "corr")
def corr(folder: Path = typer.Argument(..., help="folder with an astrometry.net corr *.fits and log.json, "
                                                 "or a folder of such folders"),
         output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
         centroids: str = typer.Option("table", "--centroids", help="table: astrometry.net's field_x, field_y; "
                                       "image: each star measured again on the table's image beside it (maximum "
                                       "likelihood, with its covariance)")):
    """astrometry.net corr tables -> a centroid-level recording of identified stars (one frame per table)."""
    from rollingstar.api import import_corr

    _done(import_corr(folder, output, centroids=centroids))


@command(import_app, "centroids")
def centroids(table: Path = typer.Argument(..., help="CSV: frame, t_ns or time_s, x, y, flux [, optional columns]"),
              output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
              camera: str = typer.Option(..., "--camera", help="camera.yaml or a shipped camera's name")):
    """A centroid CSV -> a centroid-level recording."""
    from rollingstar.logs.importers.centroids import import_centroids

    _done(import_centroids(table, output, find_config(camera, "camera")))


app.add_typer(import_app, name="import")

bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks that score an analysis against known truth.")
app.add_typer(bench_app, name="bench")


@command(bench_app, "discrepancy")
def bench_discrepancy(quick: bool = typer.Option(False, "--quick", help="the reduced set the test suite runs"),
                      as_json: bool = typer.Option(False, "--json", help="print one JSON object"),
                      seed: int = _seed(),
                      cases: int = typer.Option(None, "--cases", min=1, help="number of recordings (default 12 quick, 120 full)"),
                      out_md: Path = typer.Option(None, "--markdown", help="also write the results table here"),
                      quiet: bool = _quiet()):
    """Diagnose simulated recordings with concealed effects; score naming, nulls, parameters, held-out gain."""
    from rollingstar.studies.bench.discrepancy import format_markdown, run_benchmark

    result = run_benchmark(quick=quick, seed=seed, n_cases=cases, show_progress=not (as_json or quiet))
    if out_md is not None:
        write_text(out_md, format_markdown(result))
    if as_json:
        print(json.dumps(result, indent=2))
    else:
        out.print(format_markdown(result), highlight=False)


@command(bench_app, "perf")
def bench_perf(quick: bool = typer.Option(False, "--quick", help="tiny sizes (the test suite's run; ratios not meaningful)"),
               as_json: bool = typer.Option(False, "--json", help="print one JSON object"),
               only: list[str] = typer.Option(None, "--only", help="run only these lines (repeat the option): quest kf rate centroid chain replay compare diagnose"),
               markdown: bool = typer.Option(False, "--markdown", help="print the markdown table of docs/performance.md"),
               quiet: bool = _quiet()):
    """Hot paths side by side with a peer or the frame.sum() floor, as ratios; docs/performance.md."""
    from rollingstar.studies.bench.perf import format_markdown, render_table, run_perf

    result = run_perf(quick=quick, show_progress=not (as_json or markdown or quiet), only=only)
    if as_json:
        print(json.dumps(result, indent=2))
    elif markdown:
        print(format_markdown(result))
    else:
        out.print(render_table(result))
    if not result["checks_ok"]:
        raise typer.Exit(1)


@command()
def compare(config: str = typer.Argument(..., help="comparison YAML, or a shipped comparison's name (ci)"),
            output: Path = typer.Option(..., "-o", "--output", help="directory for results.json, results.md, report.html"),
            executor: str = typer.Option(None, "--executor", help="serial | dask (default: dask when --workers > 1)"),
            scheduler: str = typer.Option(None, "--scheduler", help="address of an existing dask scheduler, tcp://host:8786"),
            workers: int = typer.Option(1, "--workers", help="local dask workers (a LocalCluster)"),
            baseline: Path = typer.Option(None, "--baseline", help="results.json of an earlier run to compare against"),
            fail_on_regression: bool = typer.Option(False, "--fail-on-regression",
                                                    help="exit 1 naming every gated metric worse than --baseline"),
            resume: bool = typer.Option(False, "--resume", help="reuse the tasks an interrupted or failed run into "
                                                                "the same output finished (OUTPUT.partial/tasks/)"),
            quiet: bool = _quiet()):
    """Scenarios x pipelines x seeds: metrics, spread, CPU time, efficiency vs the bound; optional regression gate."""
    from rollingstar.pipelines.compare import run_compare

    if fail_on_regression and baseline is None:
        raise UserError("--fail-on-regression needs --baseline FILE")
    command = "rollingstar " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["compare"] else ""
    res = run_compare(find_config(config, "compare"), output, executor, workers, scheduler, baseline,
                      show_progress=not quiet, command=command, resume=resume)
    if resume:
        out.print(f"resumed: {res.resumed_tasks} of {res.results['run']['tasks']} task(s) reused from the earlier run")
    from rollingstar.pipelines.compare.report import terminal_tables

    for title, header, body in terminal_tables(res.results):
        table = Table(title=f"{title} (mean ± std over seeds)", title_justify="left")
        for k, col in enumerate(header):
            table.add_column(col, justify="left" if k < 2 else "right")
        for row in body:
            table.add_row(*map(escape, row))  # variant labels hold brackets: text, not markup
        out.print(table)
    run = res.results["run"]
    out.print(f"wrote {res.output}/results.json, results.md, report.html: {run['tasks']} simulations, "
              f"{run['pipeline_runs']} pipeline runs, {run['executor']}, {run['wall_time_s']:.1f} s wall", highlight=False)
    if baseline is not None:
        if res.regressions:
            err.print(f"[bold red]{len(res.regressions)} metric(s) worse than {baseline}:[/]", highlight=False)
            for line in res.regressions:
                err.print(f"  {line}", highlight=False, soft_wrap=True)
            if fail_on_regression:
                raise typer.Exit(1)
        else:
            out.print(f"no gated metric worse than {baseline}", highlight=False)


def main() -> None:
    # Single-threaded BLAS unless the user says otherwise: the estimators' matrices are small, and on
    # a shared 2-core machine OpenBLAS threads spinning against each other made ls-rate's 72 x 630
    # products 15-50x slower (measured: 106-363 ms vs 6-7 ms per frame, he2021b, 36 stars).
    # Set before numpy is first imported (the commands import it lazily).
    import os

    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    # Read by our log writer and, at import, by numpy.f2py (which numba loads): checked before both.
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch is not None and not epoch.strip().isdigit():
        err.print(f"[bold red]error:[/] SOURCE_DATE_EPOCH must be a whole number of seconds since 1970 "
                  f"(reproducible builds), got {epoch[:40]!r}; unset it or fix it", highlight=False, soft_wrap=True)
        sys.exit(2)
    return app()


if __name__ == "__main__":
    sys.exit(main())

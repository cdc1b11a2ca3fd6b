"""``rollingstar import images|corr|centroids``: thin typer wrappers over :mod:`logs.importers`."""
from __future__ import annotations

import functools
from pathlib import Path

import typer

import_app = typer.Typer(add_completion=False, no_args_is_help=True,
                         help="Import real recordings (images, astrometry.net corr tables, centroid CSVs) as MCAP logs.")


def _handled(fn):
    """``pipelines.cli.handle_errors`` applied at call time (that module imports this one)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from pipelines.cli import handle_errors

        return handle_errors(fn)(*args, **kwargs)

    return wrapper


def _done(path: Path) -> None:
    from logs.importers.common import describe_log
    from pipelines.cli import out

    out.print(describe_log(path), highlight=False)


@import_app.command("images")
@_handled
def images(folder: Path = typer.Argument(..., help="folder of TIFF/PNG/JPEG frames (with an optional recording.yaml)"),
           output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
           camera: Path = typer.Option(None, "--camera", help="camera.yaml (required when the folder has no "
                                                              "recording.yaml with a camera)"),
           sidecar: Path = typer.Option(None, "--sidecar", help="recording.yaml kept outside the folder "
                                                                "(default: FOLDER/recording.yaml if present)"),
           quiet: bool = typer.Option(False, "--quiet", "-q")):
    """A folder of 8/16-bit images -> an image-level recording (foxglove.RawImage frames)."""
    from logs.importers.images import import_images

    _done(import_images(folder, output, camera=camera, sidecar=sidecar, show_progress=not quiet))


@import_app.command("corr")
@_handled
def corr(folder: Path = typer.Argument(..., help="folder with an astrometry.net corr *.fits and log.json, "
                                                 "or a folder of such folders"),
         output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write")):
    """astrometry.net corr tables -> a centroid-level recording of identified stars (one frame per table)."""
    from logs.importers.corr import import_corr

    _done(import_corr(folder, output))


@import_app.command("centroids")
@_handled
def centroids(table: Path = typer.Argument(..., help="CSV: frame, t_ns or time_s, x, y, flux [, optional columns]"),
              output: Path = typer.Option(..., "-o", "--output", help="MCAP file to write"),
              camera: Path = typer.Option(..., "--camera", help="camera.yaml")):
    """A centroid CSV -> a centroid-level recording."""
    from logs.importers.centroids import import_centroids

    _done(import_centroids(table, output, camera))

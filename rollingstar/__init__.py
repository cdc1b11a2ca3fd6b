"""rollingstar: star-tracker estimation with rolling-shutter CMOS sensors.

The public Python API does what the command line does::

    import rollingstar as rs

    rec = rs.simulate("he2021b", "rec.mcap", frames=50, seed=1)
    out = rs.run("baseline", rec.path, "out.mcap")
    metrics = rs.evaluate(out.output)

See :mod:`rollingstar.api` for every function. The library itself lives in the sub-packages:

- :mod:`rollingstar.sensors`: camera, detector timing, sky, motion, gyro, the simulator, physics effects;
- :mod:`rollingstar.logs`: the MCAP recording format, its reader, writer and importers;
- :mod:`rollingstar.estimators`: one sub-package per plugin role, and the mismatch diagnosis;
- :mod:`rollingstar.pipelines`: configs, plugin registry, runner, evaluation, comparison;
- :mod:`rollingstar.studies`: paper reproductions, documentation figures, benchmarks (uses the
  library, never used by it).
"""
from rollingstar._version import __version__

_API = ("simulate", "run", "evaluate", "compare", "diagnose", "import_images", "import_corr",
        "import_centroids", "open_recording", "find_config")

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    # The API imports numpy, scipy and the rollingstar.estimators; loading it on first use keeps
    # ``import rollingstar.errors`` (used by every layer) and ``rollingstar --version`` light.
    if name in _API:
        from rollingstar import api

        return getattr(api, name)
    raise AttributeError(f"module 'rollingstar' has no attribute {name!r}")

"""Import real recordings into rollingstar logs (``rollingstar import``; docs/log-format.md).

- :func:`import_images`: a folder of TIFF/PNG/JPEG frames (+ ``recording.yaml`` sidecar) -> image-level log;
- :func:`import_corr`: astrometry.net corr tables + ``log.json`` -> centroid-level, identified log;
- :func:`import_centroids`: a centroid CSV (+ camera.yaml) -> centroid-level log.

Each returns the output path. Recoverable problems are emitted as
:class:`ImportDataWarning` (``warnings`` module; also stored in the log's ``import.warnings``
metadata, a JSON list); unusable input raises :class:`ImportDataError` (a ``UserError``: the CLI
exits 2 with the message, which names the file and the field or line).
"""
from rollingstar.logs.importers.centroids import import_centroids
from rollingstar.logs.importers.common import (
    ImportDataError,
    ImportDataWarning,
    import_warnings,
)
from rollingstar.logs.importers.corr import (
    boresight_offsets,
    import_corr,
    pointing_centres,
)
from rollingstar.logs.importers.images import import_images, read_image
from rollingstar.logs.importers.sidecar import (
    CameraSpec,
    RecordingSidecar,
    load_camera,
    load_sidecar,
)

__all__ = [
    "CameraSpec", "ImportDataError", "ImportDataWarning", "RecordingSidecar", "boresight_offsets",
    "import_centroids", "import_corr", "import_images", "import_warnings", "load_camera", "load_sidecar",
    "pointing_centres", "read_image",
]

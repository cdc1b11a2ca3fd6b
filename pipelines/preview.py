"""A still picture of a log as a Foxglove layout shows it (``rollingstar preview``): for a machine
without Foxglove (a CI job, a report), and as the check that a layout's panels find their data.

Panels drawn from the layout file (``configs/foxglove/run.json`` by default):

- ``Image``: one frame of its ``imageTopic`` with the circles and texts of its annotation topics at
  the same log time, in Foxglove's pixel convention (origin at the top-left corner of the top-left
  pixel);
- ``Plot``: every message path against log time (``/topic.field``, ``.a.b``, ``[i]``);
- ``3D``: the camera's boresight (its +z axis) on the sky from the pose topic, right ascension and
  declination against time.

Message paths are Foxglove's for JSON records; protobuf topics are read for images, annotations and
poses only. Other panels of the layout are left out. A layout that is not one, or whose panel names
a topic of another kind than the panel draws, is a :class:`~rollingstar.errors.UserError` naming the
file, the panel key and what was expected.
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rollingstar.config import CONFIGS, format_validation_error
from rollingstar.errors import UserError
from rollingstar.logs.reader import LogReader
from rollingstar.outputs import check_not_an_input, safe_output
from rollingstar.pipelines.plots import pyplot

DEFAULT_LAYOUT = CONFIGS / "foxglove" / "run.json"


class _Open(BaseModel):
    """A part of a Foxglove layout: the keys the preview reads are checked, the others kept."""

    model_config = ConfigDict(extra="allow")


class _ImageMode(_Open):
    imageTopic: str
    annotations: dict[str, Any] = {}


class _ImagePanel(_Open):
    title: str = "Image"
    imageMode: _ImageMode


class _PlotPath(_Open):
    value: str = Field(pattern=r"^/[^.\s]+\..+")  # a message path: /topic.field
    label: str | None = None


class _PlotPanel(_Open):
    title: str = "Plot"
    paths: list[_PlotPath] = []


class _PosePanel(_Open):
    title: str = "3D"
    topics: dict[str, Any] = {}


class _Layout(_Open):
    configById: dict[str, dict]


#: The panels the preview draws, by the kind that starts their Foxglove id (``Plot!rs-rate``).
PANELS = {"Image": _ImagePanel, "Plot": _PlotPanel, "3D": _PosePanel}


def read_layout(path: str | Path, reader: LogReader) -> list[tuple[str, _Open]]:
    """The (kind, config) of every panel of the layout at ``path`` the preview draws, in layout order,
    each checked against ``reader``'s topics."""
    source = str(path)
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{source}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); "
                        "expected a Foxglove layout") from None
    except UnicodeDecodeError:
        raise UserError(f"{source}: not UTF-8 text; expected a Foxglove layout (JSON)") from None
    if not isinstance(data, dict):
        raise UserError(f"{source}: expected a JSON object (a Foxglove layout) at the top level, "
                        f"got {type(data).__name__}")
    panels = []
    for pid, config in _validated(_Layout, data, source, ()).configById.items():
        kind = pid.split("!")[0]
        if kind in PANELS:
            panel = _validated(PANELS[kind], config, source, ("configById", pid))
            _check_panel_topics(panel, reader.topics(), f"{source}: configById.{pid}")
            panels.append((kind, panel))
    return panels


def _validated(model: type[_Open], data, source: str, where: tuple) -> _Open:
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise UserError(format_validation_error(source, err, prefix=where)) from None


def _check_panel_topics(panel: _Open, topics: dict[str, str], where: str) -> None:
    """Each topic a panel draws holds the messages it draws, when the log has that topic."""
    if isinstance(panel, _ImagePanel):
        wanted = [("imageMode.imageTopic", panel.imageMode.imageTopic, "foxglove.RawImage"),
                  *(("imageMode.annotations", t, "foxglove.ImageAnnotations") for t in panel.imageMode.annotations)]
    elif isinstance(panel, _PosePanel):
        wanted = [("topics", t, "foxglove.PoseInFrame") for t in panel.topics]
    else:
        wanted = []
    for key, topic, schema in wanted:
        if topics.get(topic, schema) != schema:
            raise UserError(f"{where}.{key}: {topic} holds {topics[topic]} messages, expected {schema}")


def _resolve(record: dict, path: str):
    value = record
    for name, index in re.findall(r"([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?", path):
        value = value[name]
        if index:
            value = value[int(index)]
    return value


def _series(reader: LogReader, path: str) -> tuple[np.ndarray, np.ndarray]:
    """Log time (s) and value of a message path over its topic's messages (values that are not
    numbers are left out)."""
    topic, field = path.split(".", 1)
    t, v = [], []
    for m in reader.messages(topic):
        try:
            value = _resolve(m.data, field)
        except (KeyError, IndexError, TypeError):
            continue
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            t.append(m.log_time_ns * 1e-9)
            v.append(float(value))
    return np.array(t), np.array(v)


def _image_panel(ax, reader: LogReader, cfg: _ImagePanel, frame: int | None) -> None:
    from rollingstar.logs.replay import image_from_raw

    mode = cfg.imageMode
    images = list(reader.messages(mode.imageTopic))
    if not images:
        ax.text(0.5, 0.5, f"no {mode.imageTopic} in this log", ha="center", transform=ax.transAxes)
        return
    msg = images[len(images) // 2 if frame is None else min(frame, len(images) - 1)]
    img = image_from_raw(msg).astype(float)
    lo, hi = np.percentile(img, [1.0, 99.7])
    ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, extent=(0, img.shape[1], img.shape[0], 0))
    for topic in mode.annotations:
        for ann in reader.messages(topic):
            if ann.log_time_ns != msg.log_time_ns:
                continue
            for c in ann.data.circles:
                ax.add_patch(pyplot().Circle((c.position.x, c.position.y), c.diameter / 2, fill=False, color="lime",
                                             lw=0.8))
            for tx in ann.data.texts:
                ax.text(tx.position.x, tx.position.y, tx.text, color="yellow", fontsize=6)
    ax.set_title(f"{cfg.title}\n{mode.imageTopic} at {msg.log_time_ns * 1e-9:.3f} s", fontsize=8)
    ax.set_axis_off()


def _plot_panel(ax, reader: LogReader, cfg: _PlotPanel) -> None:
    for p in cfg.paths:
        t, v = _series(reader, p.value)
        ax.plot(t, v, ".-", ms=2, lw=0.8, label=p.label or p.value)
    ax.set_title(cfg.title, fontsize=8)
    ax.set_xlabel("log time (s)", fontsize=7)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6, loc="best")
    ax.grid(alpha=0.3)


def _pose_panel(ax, reader: LogReader, cfg: _PosePanel) -> None:
    from scipy.spatial.transform import Rotation

    for topic in cfg.topics:
        t, q = [], []
        for m in reader.messages(topic):
            o = m.data.pose.orientation
            t.append(m.log_time_ns * 1e-9)
            q.append([o.x, o.y, o.z, o.w])
        if not q:
            continue
        z = Rotation.from_quat(np.array(q)).apply([0.0, 0.0, 1.0])  # the boresight in ICRS
        ra = np.degrees(np.arctan2(z[:, 1], z[:, 0])) % 360.0
        dec = np.degrees(np.arcsin(np.clip(z[:, 2], -1.0, 1.0)))
        ax.plot(t, ra - ra[0], label=f"right ascension - {ra[0]:.4f} deg")
        ax.plot(t, dec - dec[0], label=f"declination - {dec[0]:.4f} deg")
    ax.set_title(f"{cfg.title}: the boresight on the sky", fontsize=8)
    ax.set_xlabel("log time (s)", fontsize=7)
    ax.set_ylabel("deg", fontsize=7)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6)
    ax.grid(alpha=0.3)


def render_preview(log: str | Path, out_png: str | Path, layout: str | Path = DEFAULT_LAYOUT,
                   frame: int | None = None) -> Path:
    """Draw every panel of ``layout`` from ``log`` into ``out_png`` (module docstring); ``frame``: the
    image shown (default the middle one)."""
    check_not_an_input(out_png, [log, layout])  # before drawing: the figure takes seconds to draw
    reader = LogReader(log)
    panels = read_layout(layout, reader)
    images = [panel for kind, panel in panels if kind == "Image"]
    others = [(kind, panel) for kind, panel in panels if kind != "Image"]
    plt = pyplot()
    rows = max(len(others), 1)
    fig = plt.figure(figsize=(16, 2.6 * rows + 1))
    grid = fig.add_gridspec(rows, 2, width_ratios=(1.1, 1.0))
    if images:  # the image on the left, over the full height; the other panels stacked on the right
        _image_panel(fig.add_subplot(grid[:, 0]), reader, images[0], frame)
    for row, (kind, panel) in enumerate(others):
        ax = fig.add_subplot(grid[row, 1])
        (_plot_panel if kind == "Plot" else _pose_panel)(ax, reader, panel)
    fig.suptitle(f"{Path(log).name} with the layout {Path(layout).name}", fontsize=10)
    fig.tight_layout()
    with safe_output(out_png, [log, layout]) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(out_png)

"""The one interface every plugin implements.

Modelled on scikit-learn: the constructor only validates and stores parameters (a pydantic model,
``Params``, with unknown keys rejected); state is created in :meth:`Plugin.setup`, called by the
runner once before the first frame with the :class:`~rollingstar.estimators.data.SensorContext`;
:meth:`Plugin.process` maps one :class:`~rollingstar.estimators.data.FrameData` to a new one without mutating
its input. Third-party plugins subclass the role base class and register under the entry-point
group ``rollingstar.plugins``.
"""
from __future__ import annotations

from typing import ClassVar

from pydantic import BaseModel, ConfigDict

from rollingstar.estimators.data import FrameData, SensorContext

#: What a stage may need or provide (:attr:`Plugin.needs`, :attr:`Plugin.provides`): word -> meaning.
FRAME_CONTENTS: dict[str, str] = {
    "image": "the frame's image",
    "spots": "detected stars",
    "identified": "stars with catalogue ids",
    "velocities": "per-star image velocities",
    "common_time": "stars referred to one time",
    "rate": "a body-rate estimate",
    "attitude": "an attitude estimate",
}


class NoParams(BaseModel):
    """Parameters of a plugin that takes none."""

    model_config = ConfigDict(extra="forbid")


class Plugin:
    """Base class of all plugins. Subclasses set ``role``, ``name``, ``Params`` and a docstring.

    What the runner calls, in order, and what a plugin may override (each has a default here):

    - :meth:`setup` once before the first frame (``ValueError``: the plugin cannot run on this
      recording; the message says why);
    - :meth:`process` for every frame, and for a stage with ``defers_output`` (a smoother)
      :meth:`release` right after it;
    - :meth:`finish` once at the end of the recording (not when the run was interrupted);
    - :meth:`update_prior` on every stage with each frame once the frame's stages have run (up to
      and including a ``defers_output`` stage, whose provisional estimate it then carries); a
      tracking identifier takes its prior for the next frame from it. Default: nothing, False;
    - ``needs_truth``: read before the first frame; when a stage of the pipeline declares it True,
      every frame carries ``frame.truth`` (the recording's truth attitude samples of that frame;
      oracle baselines on simulated recordings only). Default False; a subclass may set it as a
      class attribute or compute it from its parameters as a property;
    - ``needs`` and ``provides``: what the stage reads from a frame and what it adds, in the words
      of :data:`FRAME_CONTENTS`. The pipeline checks the order of its stages with them when it is
      built and again against the recording before the first frame. Each role's base class
      declares its role's contract; a plugin that needs or provides something else overrides
      them, as a class attribute or as a property computed from its parameters. Default: nothing.
    """

    role: ClassVar[str] = ""
    name: ClassVar[str] = ""
    Params: ClassVar[type[BaseModel]] = NoParams
    #: True for stages that hold frames back (smoothers): the runner then drops the provisional
    #: frame :meth:`process` returns and passes on the frames of :meth:`release` and :meth:`finish`.
    defers_output: ClassVar[bool] = False
    #: True for oracle stages that read ``frame.truth`` (see the class docstring).
    needs_truth: bool = False
    #: What the stage reads from a frame (words of :data:`FRAME_CONTENTS`); see the class docstring.
    needs: ClassVar[frozenset[str]] = frozenset()
    #: What the stage adds to a frame (words of :data:`FRAME_CONTENTS`).
    provides: ClassVar[frozenset[str]] = frozenset()

    def __init__(self, **params):
        self.params = self.Params(**params)

    def setup(self, context: SensorContext) -> None:
        """Prepare per-run state. Called once before the first frame, and again to restart."""
        self.context = context

    def process(self, frame: FrameData) -> FrameData:  # pragma: no cover - interface
        raise NotImplementedError

    def finish(self) -> list[FrameData]:
        """Frames still held back when the recording ends (smoothers); default none."""
        return []

    def release(self) -> list[FrameData]:
        """Frames a ``defers_output`` stage has finalised since the last call (in frame order)."""
        return []

    def update_prior(self, frame: FrameData) -> bool:
        """Take what the next frame needs from ``frame`` (the frame after its stages ran).

        Returns True when the plugin took a new prior from it. Default: takes nothing, False.
        """
        return False

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params.model_dump().items())
        return f"{type(self).__name__}({args})"

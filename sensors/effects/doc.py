"""Generate ``docs/effects.md`` from the effect library (the doc is never edited by hand).

``python -m rollingstar.sensors.effects.doc docs/effects.md`` rewrites it; ``tests/sensors/test_effects.py``
fails when the committed file differs from :func:`render_markdown`.
"""
from __future__ import annotations

import sys
from pathlib import Path

from rollingstar.sensors.effects import EFFECTS
from rollingstar.sensors.effects.base import (
    STAGE_DETECTOR,
    STAGE_GYRO,
    STAGE_OPTICS,
    STAGE_SKY,
    STAGE_TIME,
)

STAGE_NAMES = {STAGE_TIME: "time", STAGE_SKY: "sky", STAGE_OPTICS: "optics", STAGE_DETECTOR: "detector",
               STAGE_GYRO: "gyro"}
COMMAND = "python -m rollingstar.sensors.effects.doc docs/effects.md"


def _fmt(v: float) -> str:
    return f"{v:g}"


def render_effect(cls) -> str:
    lines = [f"## `{cls.name}`", ""]
    first = (cls.__doc__ or "").strip().split("\n\n")[0]
    lines += [cls.explanation, ""]
    active = cls(**{p.name: p.default + p.prior_scale for p in cls.parameters})  # needs may depend on values
    needs = ", ".join(f"`{n}`" for n in active.needs) or "--"
    lines += [
        f"- stage: {STAGE_NAMES[cls.stage]}; channels: {', '.join(sorted(cls.channels))}; "
        f"image level: {'yes' if cls.image_level else 'no (centroid level only)'}",
        f"- context needed: {needs}",
    ]
    if cls.synonyms:
        lines.append(f"- also accepted as: {', '.join(f'`{s}`' for s in cls.synonyms)}")
    lines += ["", "Forward model: " + " ".join(first.split()), ""]
    lines += ["| parameter | unit | default | prior scale | bounds | meaning |", "|---|---|---|---|---|---|"]
    for p in cls.parameters:
        lines.append(f"| `{p.name}` | {p.unit} | {_fmt(p.default)} | {_fmt(p.prior_scale)} | "
                     f"[{_fmt(p.bounds[0])}, {_fmt(p.bounds[1])}] | {p.description} |")
    lines.append("")
    if cls.aliases:
        lines += ["| looks like | why | separating experiment |", "|---|---|---|"]
        for a in cls.aliases:
            other = a.other if a.other in ("attitude", "rate") else f"`{a.other}`"
            lines.append(f"| {other} | {a.reason} | {a.separating_experiment} |")
        lines.append("")
    return "\n".join(lines)


def render_markdown() -> str:
    """The whole of ``docs/effects.md``."""
    head = [
        "# Effect library",
        "",
        f"Generated from `sensors/effects/` by `{COMMAND}` -- do not edit by hand.",
        "",
        "Every effect can be switched on in a scenario (`effects: [{kind: <name>, params: {...}}]`) and "
        "simulated; every parameter's default means \"effect absent\". The interface (observation "
        "context, forward model, image-plane Jacobian, time/gyro hooks, aliases) is documented in "
        "`sensors/effects/base.py`; detection limits in `sensors/effects/design.py`.",
        "",
        "| effect | parameters | stage | looks like |",
        "|---|---|---|---|",
    ]
    for name, cls in EFFECTS.items():
        head.append(f"| [`{name}`](#{name}) | {', '.join(cls.parameter_names())} | {STAGE_NAMES[cls.stage]} | "
                    f"{', '.join(cls.alias_names())} |")
    head.append("")
    return "\n".join(head + [render_effect(cls) for cls in EFFECTS.values()])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = render_markdown()
    if argv:
        Path(argv[0]).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

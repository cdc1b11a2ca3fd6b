"""Plugins described for people: each parameter's type, default, unit and one-line description, read
from the plugin's ``Params`` model (``rollingstar plugins`` and the documentation's plugin reference).

Units come from the parameter's name, which the project spells with its unit (``gate_px``,
``rate_sigma_deg_s``, ``saturation_adu``; ``UNIT_SUFFIXES``), else from a unit in brackets in its
description (``"Tile size (px) ..."``); a parameter without either is dimensionless or a choice.
"""
from __future__ import annotations

import re
import types
import typing
from dataclasses import dataclass

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

# longest first: ``_deg_s2`` before ``_deg_s`` before ``_s``
UNIT_SUFFIXES = (
    ("_deg_s_sqrt_s", "deg/s/√s"), ("_arcsec_sqrt_s", "arcsec/√s"), ("_deg_sqrt_h", "deg/√h"), ("_deg_h", "deg/h"),
    ("_rad_sqrt_s", "rad/√s"), ("_e_per_adu", "e-/ADU"), ("_deg_s2", "deg/s²"), ("_deg_s", "deg/s"),
    ("_rad_s", "rad/s"), ("_px_s", "px/s"), ("_arcsec", "arcsec"), ("_rad2", "rad²"), ("_adu", "ADU"),
    ("_deg", "deg"), ("_rad", "rad"), ("_px", "px"), ("_ms", "ms"), ("_us", "µs"), ("_ns", "ns"),
    ("_hz", "Hz"), ("_mm", "mm"), ("_um", "µm"), ("_e", "e-"), ("_s", "s"), ("_frames", "frames"),
)
_BRACKET_UNITS = ("px", "ADU", "deg", "deg/s", "rad/s", "arcsec", "s", "ms", "µs", "us", "ns", "Hz", "e-/ADU",
                  "px/s", "tiles", "frames", "pixels", "sigmas", "rad", "mm")
_ABBREVIATIONS = ("e.g", "i.e", "etc", "vs", "cf")
_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|obj|ref|doc):`~?([^`]+)`")
_SEE_DOCSTRING = re.compile(r"\s*\(\s*(?:see )?(?:the )?(?:(?:module|class)(?:'s)? )?docstring[^)]*\)"
                            r"|[;,]\s*see (?:the )?(?:(?:module|class) )?docstring(?=\))")


def unit_of(name: str, description: str, annotation=None) -> str:
    """The unit of parameter ``name`` (module docstring); ``""`` when it has none (a switch, a
    ``bool`` ``annotation``, has none whatever its description mentions)."""
    if annotation is bool:
        return ""
    for suffix, unit in UNIT_SUFFIXES:
        if name.lower().endswith(suffix):
            return unit
    for unit in _BRACKET_UNITS:
        if f"({unit})" in description or f"({unit}," in description:
            return unit
    return ""


def plain(text: str) -> str:
    """Docstring or description text without reStructuredText markup: roles and double backticks
    become the plain name (the last dotted part of a role's target)."""
    text = _ROLE.sub(lambda m: m.group(1).split(".")[-1], text)
    text = _SEE_DOCSTRING.sub("", text)  # a pointer into the source, not a meaning
    return text.replace("``", "").replace("`", "")


def first_sentence(text: str) -> str:
    """The first sentence of ``text`` (up to the first full stop outside brackets), markup removed."""
    text = " ".join(plain(text).split())
    depth = 0
    for i, ch in enumerate(text):
        depth += ch in "([{"
        depth -= ch in ")]}"
        if ch == "." and depth == 0 and (i + 1 == len(text) or text[i + 1] == " ") \
                and not text[max(0, i - 3):i].endswith(_ABBREVIATIONS):
            return text[: i + 1]
    return text


def type_name(annotation) -> str:
    """``float``, ``int or None``, ``'median' | 'tiles'``, ``tuple of float``, ``cog parameters``."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        inner = [type_name(a) for a in args if a is not type(None)]
        return " or ".join(inner) + (" or None" if type(None) in args else "")
    if origin in (tuple, list):
        items = [type_name(a) for a in args if a is not Ellipsis]
        if len(set(items)) == 1:
            return f"{origin.__name__} of {len(args)} {items[0]}" if Ellipsis not in args else f"{origin.__name__} of {items[0]}"
        return f"{origin.__name__} of ({', '.join(items)})"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        name = annotation.__name__.removesuffix("Params")
        return f"{name} parameters"
    return getattr(annotation, "__name__", str(annotation))


def default_text(field) -> str:
    """The default as a reader wants it: floats to 4 significant digits, nested parameters as
    ``(their defaults)``, ``required`` when there is none."""
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True) if field.default is PydanticUndefined else field.default
    return _value_text(value)


def _value_text(value) -> str:
    if isinstance(value, BaseModel):
        return "(their defaults)"
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (tuple, list)):
        return "(" + ", ".join(_value_text(v) for v in value) + ")"
    if isinstance(value, str):
        return repr(value)
    return str(value)


@dataclass(frozen=True)
class Parameter:
    name: str
    type: str
    default: str
    unit: str
    description: str


def parameters(cls) -> list[Parameter]:
    """Every parameter of plugin class ``cls`` (its ``Params`` model), in declaration order."""
    out = []
    for name, field in cls.Params.model_fields.items():
        description = field.description or ""
        out.append(Parameter(name, type_name(field.annotation), default_text(field),
                             unit_of(name, description, field.annotation),
                             first_sentence(description)))
    return out


def summary(cls) -> str:
    """The plugin's one-line summary: the first sentence of its class docstring, markup removed."""
    return first_sentence((cls.__doc__ or "").strip().split("\n\n")[0])

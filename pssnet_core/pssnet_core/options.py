"""``NAME=VALUE`` overrides of a frozen dataclass config, as command lines give them.

One parser for every ``--*-option`` flag (the checked sampler's, the grasp planner's): each value is read as its
field's type, a nested config's field is named with a dot (``gripper.grip_force=40``), and the result is built with
``dataclasses.replace`` so that the config's own checks run on it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, TypeVar

Config = TypeVar("Config")

_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


def _parse(label: str, text: str, current: Any) -> Any:
    """``text`` read as the type of ``current`` (the field's present value); ``label`` starts error messages."""
    text = text.strip()
    try:
        if isinstance(current, bool):  # before int: bool is an int
            if text.lower() not in _TRUE + _FALSE:
                raise ValueError
            return text.lower() in _TRUE
        if isinstance(current, tuple):
            return tuple(float(v) for v in text.split(",")) if text else ()
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            return float(text)
        if isinstance(current, str):
            return text
    except ValueError:
        wanted = ("true or false" if isinstance(current, bool) else "comma-separated numbers"
                  if isinstance(current, tuple) else "an integer" if isinstance(current, int) else "a number")
        raise ValueError(f"{label}: {text!r} is not {wanted}") from None
    raise ValueError(f"{label}: a {type(current).__name__} field cannot be set from the command line")


def config_with(base: Config, options: Sequence[str], what: str = "option",
                refused: Sequence[str] = ()) -> Config:
    """``base`` with ``NAME=VALUE`` overrides of its fields (``what`` names the flag in messages).

    Args:
        base: a frozen dataclass instance.
        options: ``NAME=VALUE`` strings; NAME may be ``FIELD.SUBFIELD`` for a nested dataclass field.
        what: how messages name an option (e.g. ``"sampler option"``).
        refused: field names that may not be set this way (they have their own flag).

    Raises:
        ValueError: an unknown or refused name, a value of the wrong form, or values the config refuses.
    """
    names = [f.name for f in dataclasses.fields(base)]
    changes: dict[str, Any] = {}
    nested: dict[str, list[str]] = {}
    for option in options:
        name, sep, text = str(option).partition("=")
        name = name.strip()
        head, dot, rest = name.partition(".")
        if not sep or head not in names or name in refused:
            raise ValueError(f"{what} {option!r}: expected NAME=VALUE with NAME one of {', '.join(names)}"
                             + (f" (not {', '.join(refused)}: they have their own flags)" if refused else ""))
        current = getattr(base, head)
        if dot:
            if not dataclasses.is_dataclass(current):
                raise ValueError(f"{what} {option!r}: {head} has no fields")
            nested.setdefault(head, []).append(f"{rest}={text}")
        elif dataclasses.is_dataclass(current):
            raise ValueError(f"{what} {option!r}: set {head}'s fields as {head}.FIELD=VALUE")
        else:
            changes[name] = _parse(f"{what} {option!r}", text, current)
    for head, parts in nested.items():
        changes[head] = config_with(getattr(base, head), parts, f"{what} {head}")
    return dataclasses.replace(base, **changes)

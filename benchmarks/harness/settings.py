"""SLAM settings of a benchmark run as dotted overrides (``{"backend.kind": "sim3"}``), and grids of them.

A benchmark names what it changes, setting by setting, with the keys of a config file
(``section.name``, or a top-level name such as ``overlap``); :func:`with_settings` applies them to a
copy of a config through :func:`sl4slam.config.config_from_dict`, so an unknown or misspelt key, or a
value of the wrong type, is an error instead of an attribute that changes nothing. :func:`grid` makes
the product of several axes, as ``sl4slam sweep --grid`` does.
"""

from __future__ import annotations

import copy
import itertools
import json
from typing import Any, Iterable, Mapping, Sequence

Settings = Mapping[str, Any]
"""Dotted setting -> value, e.g. ``{"submap.size": 16, "sim.profile": "vggt"}``."""


def nested(settings: Settings) -> dict:
    """``{"a.b": 1, "c": 2}`` -> ``{"a": {"b": 1}, "c": 2}`` (the shape of a config file)."""
    tree: dict = {}
    for key, value in settings.items():
        *sections, name = key.split(".")
        node = tree
        for section in sections:
            node = node.setdefault(section, {})
        node[name] = value
    return tree


def with_settings(config, settings: Settings):
    """A copy of ``config`` (a :class:`sl4slam.config.SLAMConfig`) with ``settings`` applied.

    Args:
        config: the starting settings (not changed).
        settings: dotted setting -> value; keys of earlier releases are read under their current
            names, as in a config file.

    Raises:
        sl4slam.errors.UserError: an unknown setting or a value of the wrong type.
    """
    from sl4slam.config import config_from_dict

    return config_from_dict(nested(settings), base=copy.deepcopy(config))


def simulated_config(settings: Settings = {}, **more: Any):
    """The defaults with the simulated frontend, and ``settings`` (then ``more``) on top.

    Args:
        settings: dotted setting -> value (``{"sim.profile": "vggt", "retrieval.kind": "orb"}``).
        more: further settings as keywords, with ``__`` for the dot (``sim__seed=3``).

    Returns:
        A new :class:`sl4slam.config.SLAMConfig`.
    """
    from sl4slam.config import SLAMConfig

    merged = {**settings, **{key.replace("__", "."): value for key, value in more.items()}}
    return with_settings(SLAMConfig(frontend="simulated"), merged)


def seed_settings(seed: int, *names: str) -> dict[str, int]:
    """``{name: seed}`` for each dotted setting name (default ``sim.seed``): the seeds of one run."""
    return {name: int(seed) for name in (names or ("sim.seed",))}


def grid(axes: Mapping[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """Every combination of the axes' values, in order (the last axis varies fastest).

    Args:
        axes: dotted setting -> the values it takes, e.g. ``{"alignment.model": ["sl4", "select"],
            "submap.overlap": [1, 2]}``.

    Returns:
        One ``{setting: value}`` dict per combination (``[{}]`` for no axes).
    """
    names = list(axes)
    return [dict(zip(names, values)) for values in itertools.product(*(axes[name] for name in names))]


def parse_settings(pairs: Iterable[str], flag: str = "") -> dict[str, Any]:
    """``["submap.overlap=2", "loops.enabled=false"]`` -> ``{"submap.overlap": 2, "loops.enabled": False}``.

    Each value is read as JSON where it parses (numbers, true / false, quoted strings) and kept as
    text otherwise.

    Args:
        pairs: ``section.name=value`` texts (a command line's).
        flag: the option they came with, named in the error (``"--ours"``).

    Raises:
        ValueError: a pair without ``=`` or without a section (``section.name=value``).
    """
    settings: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or "." not in key:
            named = f"{flag} {pair!r}" if flag else repr(pair)
            raise ValueError(f"{named}: expected section.name=value, e.g. submap.overlap=2")
        try:
            settings[key.strip()] = json.loads(text)
        except json.JSONDecodeError:
            settings[key.strip()] = text
    return settings


def describe(settings: Settings) -> str:
    """``"backend.kind=sim3, submap.overlap=2"``, or ``"library defaults"`` for none."""
    return ", ".join(f"{key}={value}" for key, value in settings.items()) or "library defaults"

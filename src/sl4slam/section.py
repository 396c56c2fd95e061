"""The base of every config section: a setting's flag, its help group and its allowed values,
declared once on the field (:func:`setting`), and the one-line check of a bad value.

Each stage's section lives beside the stage that reads it (``sl4slam.alignment.settings``,
``sl4slam.keyframes``, ...); ``sl4slam.config`` composes them into the run's tree.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from typing import Any, Callable, ClassVar

from .errors import UserError

__all__ = ["Section", "setting"]


def setting(default: Any = dataclasses.MISSING, *, factory: Any = dataclasses.MISSING, choices: tuple = (),
            common: bool = False, advanced: bool = False, flag: str = "", aliases: tuple[str, ...] = (),
            check: Callable[[Any], bool] | None = None, allowed: str = "", extra: dict | None = None) -> Any:
    """A section field with what the command line and the checks need to know about it.

    Args:
        default: the value when not set (or ``factory``: a callable that makes it).
        choices: the allowed values of a string setting (checked by :meth:`Section.validate`).
        common: shown by ``run --help`` (most runs touch it).
        advanced: listed under the section's "advanced" group of ``run --help-all``.
        flag: the command-line flag, when not the one made from the section's prefix and the name.
        aliases: further flags that set the same field (older or shorter names).
        check: whether a value is in the setting's range (a rule that reads this field alone;
            rules between fields stay in the section's ``validate``).
        allowed: the range in words, for the one-line error (``--flag (config key k) must be
            <allowed>, got v``).
        extra: further metadata of the section's own (e.g. a simulator magnitude's "exact" value).

    Returns:
        A ``dataclasses.field`` carrying these in its metadata.
    """
    metadata = {"choices": tuple(choices), "common": common, "advanced": advanced, "flag": flag,
                "aliases": tuple(aliases), "check": check, "allowed": allowed, **(extra or {})}
    if factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


class Section:
    """Behaviour shared by the config sections: flag names and range checks.

    Class attributes (not settings):
        section: the section's key in the tree (``[alignment]`` in a config file).
        flag_prefix: prefix of the section's command-line flags (``--ransac-...``).
        flag_names: per-field flag overrides (from :func:`setting`'s ``flag``).
        flag_aliases: per-field further flags that set the same field (``aliases``).
        choices: per-field allowed values of string settings (``choices``).
        advanced: fields listed under the section's "advanced" group of ``run --help-all``.
        common: fields most runs touch, the ones ``run --help`` shows.
        builds: what the section configures, ``"module:name"`` (imported only when built): a
            callable taking the section first (:meth:`setup`); empty for a section that builds
            nothing on its own.

    ``flag_names`` to ``common`` are gathered from the fields' :func:`setting` declarations when a
    section class is defined (and inherited from a base section).
    """

    section: ClassVar[str] = ""
    flag_prefix: ClassVar[str] = ""
    builds: ClassVar[str] = ""
    flag_names: ClassVar[dict[str, str]] = {}
    flag_aliases: ClassVar[dict[str, tuple[str, ...]]] = {}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {}
    advanced: ClassVar[frozenset[str]] = frozenset()
    common: ClassVar[frozenset[str]] = frozenset()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        declared = {name: value.metadata for name, value in vars(cls).items()
                    if isinstance(value, dataclasses.Field) and "choices" in value.metadata}
        cls.flag_names = {**cls.flag_names, **{n: m["flag"] for n, m in declared.items() if m["flag"]}}
        cls.flag_aliases = {**cls.flag_aliases, **{n: m["aliases"] for n, m in declared.items() if m["aliases"]}}
        cls.choices = {**cls.choices, **{n: m["choices"] for n, m in declared.items() if m["choices"]}}
        cls.advanced = cls.advanced | {n for n, m in declared.items() if m["advanced"]}
        cls.common = cls.common | {n for n, m in declared.items() if m["common"]}

    def setup(self, *args: Any, **kwargs: Any) -> Any:
        """The stage this section configures: ``builds(self, *args, **kwargs)``.

        Raises:
            TypeError: the section builds nothing on its own (``builds`` is empty).
        """
        if not self.builds:
            raise TypeError(f"{type(self).__name__} builds nothing on its own")
        module, _, name = self.builds.partition(":")
        return getattr(importlib.import_module(module), name)(self, *args, **kwargs)

    @classmethod
    def flag(cls, name: str) -> str:
        """The command-line flag of field ``name``."""
        if name in cls.flag_names:
            return cls.flag_names[name]
        if name == "kind":
            return f"--{cls.section}"
        dashed = name.replace("_", "-")
        return "--" + (dashed if dashed.startswith(cls.flag_prefix) else cls.flag_prefix + dashed)

    def _require(self, name: str, ok: bool, allowed: str) -> None:
        """Raise a one-line ``UserError`` naming the flag and config key unless ``ok``."""
        value = getattr(self, name)
        finite = not isinstance(value, float) or math.isfinite(value)
        if not (ok and finite):
            key = f"{self.section}.{name}" if self.section else name
            raise UserError(f"{self.flag(name)} (config key {key}) must be {allowed}, got {value!r}")

    @classmethod
    def field_default(cls, name: str) -> Any:
        """The value field ``name`` has when not set (for help texts and flag types)."""
        return getattr(cls(), name)

    def _require_choice(self, name: str) -> None:
        allowed = self.choices[name]
        self._require(name, getattr(self, name) in allowed, "one of " + ", ".join(allowed))

    def validate(self) -> None:
        """Raise ``UserError`` for a value outside its meaningful range: each field's choices, then
        each field's own ``check`` (a section adds the rules between its fields)."""
        for name in self.choices:
            self._require_choice(name)
        for item in dataclasses.fields(self):
            check = item.metadata.get("check")
            if check is not None:
                self._require(item.name, check(getattr(self, item.name)), item.metadata["allowed"])

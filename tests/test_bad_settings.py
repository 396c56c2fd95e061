"""Every bad setting is one line that names its flag, its config key and the allowed range, given
before a frame is read, and the same line whichever way the setting arrives: the Python API
(``run_slam``), a config file (``sl4slam run SRC --config FILE``) or a flag (``sl4slam run SRC --flag
VALUE``).

The rules are not listed here. The sections and their fields come from the config tree
(``dataclasses.fields`` of ``SLAMConfig``, each section's ``section``, ``flag()`` and ``choices``);
each field is tried with a few values that break most settings of its type, and every value the API
refuses with a ``UserError`` is a case. Pairs of values that are each accepted but refused together
(rules between settings, in a section's ``validate()`` or in ``sl4slam.resolve.resolve``) are cases
too. A field whose ``validate()`` has a rule, or which has ``choices``, but that no candidate breaks
fails ``test_every_rule_is_reached``: a new rule needs a candidate value that reaches it.

A value outside a flag's ``choices`` is refused by argparse itself, before any setting is built, with
its own usage line and message; the test checks that message instead (the file and the API give the
settings' line). Lines that do not name their config key are listed in ``KEYLESS_LINES`` as known
gaps.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import json
import math
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

import sl4slam.io
import sl4slam.runner
from sl4slam.cli import build_parser, main
from sl4slam.config import SLAMConfig, load_config
from sl4slam.errors import UserError
from sl4slam.registry import frontend_names
from sl4slam.resolve import resolve
from sl4slam.runner import run_slam

# ------------------------------------------------------------------------------------ the settings

FLOAT_CANDIDATES = (-1.0, -0.5, 0.0, 1e12, math.nan, math.inf)
INT_CANDIDATES = (-1, 0, 10**12)  # ints only: a float in an int setting is a type error in a file, not a rule
CHOICE_CANDIDATES = ("bogus",)
OPEN_STRING_CANDIDATES = ("", "   ", "bogus")  # strings without ``choices`` (paths, names, specs)

# Valid values of the open strings worth pairing with the others (the choices and bools pair over
# every value they have); ``frontend`` pairs over every registered frontend.
PAIR_VALUES: dict[str, tuple[Any, ...]] = {
    "device": ("cpu", "cuda", "cuda:1"),
    "frontend": tuple(frontend_names()),
    "source.intrinsics": ("auto", "500,500,320,240"),
}

# Lines that do not name their config key: the product's rule says every bad setting's line does,
# so each is a known gap (strict: a fixed one turns the xfail into a failure, to be removed here).
KEYLESS_LINES: dict[str, str] = {}


@dataclass(frozen=True)
class Setting:
    """One field of the tree as every entry point addresses it."""

    attr: str  # the section's attribute in SLAMConfig (its [table] in a file); "" at the top level
    name: str
    owner: type
    kind: str  # "bool", "int", "float" or "str": the type the flag parses and a file must hold

    @property
    def key(self) -> str:
        return f"{self.owner.section}.{self.name}" if self.owner.section else self.name

    @property
    def flag(self) -> str:
        return self.owner.flag(self.name)

    @property
    def choices(self) -> tuple[str, ...] | None:
        return self.owner.choices.get(self.name)

    def default(self) -> Any:
        return getattr(_owner_of(SLAMConfig(), self.attr), self.name)

    def set(self, config: SLAMConfig, value: Any) -> None:
        setattr(_owner_of(config, self.attr), self.name, value)


def _owner_of(config: SLAMConfig, attr: str) -> Any:
    return getattr(config, attr) if attr else config


def _owners() -> list[tuple[str, Any]]:
    """("", the tree) and (attribute, section) for every section of the tree, in tree order."""
    config = SLAMConfig()
    return [("", config)] + [(f.name, getattr(config, f.name)) for f in dataclasses.fields(config)
                             if dataclasses.is_dataclass(getattr(config, f.name))]


def _kind(owner: Any, name: str) -> str:
    value = getattr(owner, name)
    if value is None:  # a setting whose None means "from elsewhere" (a profile): typed by what it stands for
        value = type(owner).field_default(name)
    if isinstance(value, bool):
        return "bool"
    return "int" if isinstance(value, int) else "float" if isinstance(value, float) else "str"


def _settings() -> list[Setting]:
    return [Setting(attr, f.name, type(owner), _kind(owner, f.name)) for attr, owner in _owners()
            for f in dataclasses.fields(owner) if not dataclasses.is_dataclass(getattr(owner, f.name))]


SETTINGS = _settings()


def _candidates(setting: Setting) -> tuple[Any, ...]:
    if setting.kind == "bool":
        return ()
    if setting.kind == "int":
        return INT_CANDIDATES
    if setting.kind == "float":
        return FLOAT_CANDIDATES
    return CHOICE_CANDIDATES if setting.choices else OPEN_STRING_CANDIDATES


def _pair_values(setting: Setting) -> tuple[Any, ...]:
    if setting.kind == "bool":
        values: tuple[Any, ...] = (True, False)
    elif setting.choices:
        values = setting.choices
    else:
        values = PAIR_VALUES.get(setting.key, ())
    return tuple(v for v in values if v != setting.default())


# ------------------------------------------------------------------------------------- the cases

@dataclass(frozen=True)
class Case:
    values: tuple[tuple[Setting, Any], ...]
    line: str  # what the API refuses it with (sl4slam.resolve.resolve, the device left as given)

    @property
    def id(self) -> str:
        return "+".join(f"{s.key}={v!r}" for s, v in self.values)

    @property
    def section(self) -> str:
        return self.values[0][0].owner.section or "(top)"

    def config(self) -> SLAMConfig:
        config = SLAMConfig()
        for setting, value in self.values:
            setting.set(config, value)
        return config


def _refusal(values: tuple[tuple[Setting, Any], ...]) -> str | None:
    """The line the API refuses ``values`` with, or None. The device is not probed, so the cases do
    not depend on this machine's GPUs (no rule under test does)."""
    config = SLAMConfig()
    for setting, value in values:
        setting.set(config, value)
    try:
        resolve(config, probe_device=False)
    except UserError as exc:
        return str(exc)
    return None


def _find_cases() -> tuple[list[Case], list[Case]]:
    singles = []
    for setting in SETTINGS:
        for value in _candidates(setting):
            line = _refusal(((setting, value),))
            if line is not None:
                singles.append(Case(((setting, value),), line))
    accepted = [(s, v) for s in SETTINGS for v in _pair_values(s) if _refusal(((s, v),)) is None]
    pairs = []
    for a, b in itertools.combinations(accepted, 2):
        if a[0] != b[0]:
            line = _refusal((a, b))
            if line is not None:
                pairs.append(Case((a, b), line))
    return singles, pairs


SINGLE_CASES, PAIR_CASES = _find_cases()
CASES = SINGLE_CASES + PAIR_CASES


def _keyless(case: Case) -> str | None:
    return next((why for pattern, why in KEYLESS_LINES.items() if re.search(pattern, case.line)), None)


def _params(cases: list[Case], known_gaps: bool) -> list[Any]:
    params = []
    for case in cases:
        why = _keyless(case) if known_gaps else None
        marks = [pytest.mark.xfail(reason=why, strict=True)] if why else []
        params.append(pytest.param(case, id=case.id, marks=marks))
    return params


# ----------------------------------------------------------------------------- the entry points

class SourceOpened(Exception):
    """A run got as far as opening its source (the tests below must fail before that)."""


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    """A tiny image folder: a real source, which the guard below keeps from being opened."""
    import cv2
    import numpy as np

    folder = tmp_path_factory.mktemp("frames")
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.full((24, 32, 3), 40 * i, np.uint8))
    return folder


@pytest.fixture
def guard(monkeypatch) -> None:
    """Opening a source (the step before any frame is read) raises :class:`SourceOpened`."""
    def opened(*args, **kwargs):
        raise SourceOpened(f"the source was opened: {args}")

    monkeypatch.setattr(sl4slam.io, "open_source", opened)
    if hasattr(sl4slam.runner, "open_source"):
        monkeypatch.setattr(sl4slam.runner, "open_source", opened)


@pytest.fixture(scope="module")
def one_parser():
    """``sl4slam.cli.main`` parses with one parser built once: the parser does not change between
    calls, and building it anew (every setting's flag with its help) for each of several hundred
    calls would take most of this file's time. ``test_the_guard_sees_a_source_being_opened`` builds
    it as ``main`` does."""
    import sl4slam.cli

    parser = sl4slam.cli.build_parser()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sl4slam.cli, "build_parser", lambda: parser)
        yield


@pytest.fixture
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("case")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    return json.dumps(value)  # a TOML basic string


def _toml(values: tuple[tuple[Setting, Any], ...]) -> str:
    tables: dict[str, list[str]] = {}
    for setting, value in values:
        tables.setdefault(setting.attr, []).append(f"{setting.name} = {_toml_value(value)}")
    top = tables.pop("", [])  # top-level keys come before the first [table]
    return "\n".join(top + [f"[{attr}]\n" + "\n".join(lines) for attr, lines in tables.items()]) + "\n"


def _flag_args(setting: Setting, value: Any) -> list[str]:
    if setting.kind == "bool":
        return [setting.flag if value else "--no-" + setting.flag[2:]]
    return [setting.flag, repr(value) if isinstance(value, float) else str(value)]


def _cli(argv: list[str], capsys) -> tuple[int, str]:
    """``sl4slam`` in this process: its exit status and stderr (argparse's own errors exit)."""
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    assert captured.out == ""
    return code, captured.err


def _cli_line(line: str) -> str:
    """What ``sl4slam`` prints for a ``UserError`` (exit status 2)."""
    return f"\nsl4slam: error: {line}\n"


# ------------------------------------------------------------------------------------------ tests

def test_the_tree_is_walked() -> None:
    """Each section's table in a file is the key its lines name, and every section yields cases."""
    for attr, owner in _owners()[1:]:
        assert type(owner).section == attr, f"[{attr}] is named {type(owner).section!r} in its lines"
    assert {s.attr for s in SETTINGS if s.kind != "bool"} <= {s.attr for c in CASES for s, _ in c.values}


def _ruled_fields(owner: type) -> set[str]:
    """Fields a section's checks name: string constants equal to a field name in each method of the
    class that calls ``_require`` (``validate`` and what it delegates to), plus the ``choices``."""
    names = {f.name for f in dataclasses.fields(owner)}
    tree = ast.parse(textwrap.dedent(inspect.getsource(owner)))
    found = set(owner.choices)
    for node in ast.walk(tree):
        if not isinstance(node, ast.FunctionDef):
            continue
        calls = {sub.func.attr for sub in ast.walk(node) if isinstance(sub, ast.Call)
                 and isinstance(sub.func, ast.Attribute)}
        if calls & {"_require", "_require_choice"}:
            found |= {sub.value for sub in ast.walk(node) if isinstance(sub, ast.Constant) and sub.value in names}
    return found


def test_every_rule_is_reached() -> None:
    """A field with a rule (a check in its section's code, or choices) must yield a case: a rule no
    candidate value breaks is not tested by anything here, so add a candidate that does."""
    reached = {(s.attr, s.name) for case in SINGLE_CASES for s, _ in case.values}
    unreached = []
    for attr, owner in _owners():
        for name in sorted(_ruled_fields(type(owner))):
            if (attr, name) not in reached:
                unreached.append(f"{Setting(attr, name, type(owner), _kind(owner, name)).key}")
    assert not unreached, f"rules that no candidate value breaks: {unreached}"


@pytest.mark.parametrize("case", _params(CASES, known_gaps=True))
def test_the_line_names_the_flag_and_the_config_key(case: Case) -> None:
    line = case.line
    assert line.strip() and "\n" not in line
    named = re.findall(r"\(config key ([\w.]+)\)", line)
    assert named, f"names no config key: {line}"
    keys = {s.key: s for s, _ in case.values}
    subject = next((keys[key] for key in named if key in keys), None)
    if len(case.values) == 2:
        # a rule between two settings: the line is about one of them, naming its flag and key
        assert subject is not None, f"names neither {sorted(keys)}: {line}"
        assert line.startswith(subject.flag + " "), line
        return
    (setting, _), = case.values
    assert re.search(re.escape(setting.flag) + r"(?![\w-])", line), f"does not name {setting.flag}: {line}"
    if subject is None:
        # A value that breaks the rule of another setting measured against it (--backend-min-sigma
        # 1e12 leaves --backend-max-sigma below it): the line is that setting's, naming this flag.
        other = next(s for s in SETTINGS if s.key == named[0])
        assert line.startswith(other.flag + " "), line
    else:
        assert line.startswith(setting.flag + " "), line


@pytest.mark.parametrize("case", _params(CASES, known_gaps=False))
def test_the_same_line_from_python_a_file_and_a_flag(case: Case, source: Path, work: Path, guard, one_parser,
                                                    capsys) -> None:
    line = case.line
    out = work / "out"

    # Python: the public entry point, before the output folder and the source
    with pytest.raises(UserError) as caught:
        run_slam(source, out, case.config(), progress=False)
    assert str(caught.value) == line
    with pytest.raises(UserError) as caught:
        resolve(case.config())
    assert str(caught.value) == line

    # a config file: read by the library, and by `sl4slam run --config`
    toml = work / "settings.toml"
    toml.write_text(_toml(case.values))
    with pytest.raises(UserError) as caught:
        resolve(load_config(toml))
    assert str(caught.value) == line, toml.read_text()
    assert _cli(["run", str(source), "--out", str(out), "--config", str(toml), "--quiet"], capsys) == (2, _cli_line(line))

    # flags (nan, inf and 1e12 pass argparse's float() and int() and meet the settings' rules)
    argv = ["run", str(source), "--out", str(out), "--quiet"]
    for setting, value in case.values:
        argv += _flag_args(setting, value)
    code, err = _cli(argv, capsys)
    off_choices = [(s, v) for s, v in case.values if s.choices and v not in s.choices]
    if off_choices:
        # A flag with choices is parsed by argparse, which refuses any other value itself, before the
        # settings are built: its own usage line and message (exit status 2), naming the flag and the
        # choices, instead of the settings' line.
        (setting, value), = off_choices
        assert code == 2, err
        assert err.startswith("usage: sl4slam run"), err
        assert re.search(rf"argument {re.escape(setting.flag)}\S*: invalid choice: '?{re.escape(value)}'?", err), err
        assert all(choice in err for choice in setting.choices), err
    else:
        assert (code, err) == (2, _cli_line(line)), argv

    assert not out.exists(), "a refused setting must leave no output folder behind"


def test_the_guard_sees_a_source_being_opened(source: Path, work: Path, guard, monkeypatch) -> None:
    """The check above means something: with good settings each entry point reaches the source."""
    import sl4slam.cli

    monkeypatch.setattr(sl4slam.cli, "build_parser", build_parser)  # a fresh parser, whatever ran before
    with pytest.raises(SourceOpened):
        run_slam(source, work / "api", SLAMConfig(frontend="simulated"), progress=False)
    with pytest.raises(SourceOpened):
        main(["run", str(source), "--out", str(work / "cli"), "--quiet", "--frontend", "simulated"])

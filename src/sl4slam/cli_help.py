"""Help a person can read: ``run --help`` shows the settings most runs touch, ``run --help-all [WORD]``
every setting (or those matching a word), and a mistyped flag gets its verb's usage and the closest
flag names."""

from __future__ import annotations

import argparse
import difflib
import re
import sys
import textwrap

from .config import SLAMConfig
from .config import sections as sections_of

WIDTH = 100
"""Width of the short help's lines."""

FLAG_COLUMN = 30
"""Where the short help's descriptions start."""

RUN_OPTIONS = ("--out", "--config", "--overwrite", "--quiet", "--view", "--all-frames", "--replay")
"""Options of ``run`` itself (not settings) that the short help shows, in this order."""


def common_destinations(config: SLAMConfig | None = None) -> list[str]:
    """The ``section.field`` destinations (``field`` at the top level) of every section's ``common``
    fields, in the order the sections and fields are declared."""
    config = config if config is not None else SLAMConfig()
    found = []
    for name, section in [("", config)] + [(s.section, s) for s in sections_of(config)]:
        for field in section.__dataclass_fields__:
            if field in section.common:
                found.append(f"{name}.{field}" if name else field)
    return found


def first_sentence(text: str) -> str:
    """The first sentence of a help text, without its "(default: ...)" tail."""
    text = re.sub(r"\s*\(default: [^()]*\)\s*$", "", text.replace("%%", "%")).strip()
    match = re.search(r"(?<=[a-z0-9)\"'])\.(\s|$)", text)
    return text[: match.start()] if match else text


def _default_of(action: argparse.Action) -> str:
    match = re.search(r"\(default: ([^()]*)\)\s*$", action.help or "")
    return match.group(1) if match else ""


def _flag_text(action: argparse.Action) -> str:
    flags = ", ".join(action.option_strings) if action.option_strings else action.dest.upper()
    if isinstance(action, argparse.BooleanOptionalAction) or action.nargs == 0:
        return flags
    if action.choices:
        return f"{flags} {{{','.join(str(c) for c in action.choices)}}}"
    return f"{flags} {action.metavar or action.dest.upper()}"


def _entry(action: argparse.Action) -> list[str]:
    """One setting in the short help: flag, first sentence of its help, default; wrapped to WIDTH."""
    summary = first_sentence(action.help or "")
    default = _default_of(action)
    if default not in ("", "None"):
        summary += f" (default: {default})"
    flag = "  " + _flag_text(action)
    body = textwrap.wrap(summary, WIDTH - FLAG_COLUMN) or [""]
    if len(flag) + 2 <= FLAG_COLUMN:
        lines = [flag.ljust(FLAG_COLUMN) + body[0]]
    else:
        lines = [flag, " " * FLAG_COLUMN + body[0]]
    return lines + [" " * FLAG_COLUMN + line for line in body[1:]]


def _actions_by_dest(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {action.dest: action for action in parser._actions}


def _actions_by_flag(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {flag: action for action in parser._actions for flag in action.option_strings}


def settings_count(parser: argparse.ArgumentParser) -> int:
    """How many settings (config fields) the parser has flags for."""
    config = SLAMConfig()
    fields = sum(1 for f in config.__dataclass_fields__ if f in _actions_by_dest(parser))
    return fields + sum(1 for a in parser._actions if "." in a.dest)


def short_run_help(parser: argparse.ArgumentParser) -> str:
    """``sl4slam run --help``: usage, the run's own options and the settings most runs touch."""
    by_dest, by_flag = _actions_by_dest(parser), _actions_by_flag(parser)
    lines = [parser.format_usage().rstrip(), "",
             "Run SLAM on SOURCE: an image folder, video file, TUM RGB-D or 7-Scenes sequence folder, camera",
             "index (0, 1, ...) or stream URL (rtsp://, http://); the kind is detected.", "",
             "The run:"]
    for flag in RUN_OPTIONS:
        lines += _entry(by_flag[flag])
    lines += ["", "Most-used settings:"]
    for dest in common_destinations():
        lines += _entry(by_dest[dest])
    lines += ["",
              f"Every setting ({settings_count(parser)} in all, with defaults and where they come from):",
              "  sl4slam run --help-all            all of them",
              "  sl4slam run --help-all WORD       those whose flag or text contains WORD (e.g. ransac, loop)",
              "The same settings go in a TOML/JSON file: --config FILE ([submap] size = 32, [sim] profile = \"vggt\").",
              "Examples: README.md, \"Using it\" and \"Your own video\"."]
    return "\n".join(lines) + "\n"


def matching_help(parser: argparse.ArgumentParser, word: str) -> str | None:
    """The full help restricted to the options whose flags, choices or text contain ``word``
    (case-insensitive), under their groups; ``None`` when none does."""
    needle = word.lower()
    formatter = parser._get_formatter()
    found = 0
    for group in parser._action_groups:
        hits = [a for a in group._group_actions if a.help != argparse.SUPPRESS and needle in " ".join(
            [*a.option_strings, a.dest, a.help or "", *(str(c) for c in a.choices or ())]).lower()]
        if not hits:
            continue
        found += len(hits)
        formatter.start_section(group.title)
        formatter.add_arguments(hits)
        formatter.end_section()
    if not found:
        return None
    return f"{found} option(s) of `sl4slam {parser.prog.split()[-1]}` matching {word!r}:\n" + formatter.format_help()


class ShortHelp(argparse.Action):
    """``-h`` / ``--help`` of ``run``: the short help, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        sys.stdout.write(short_run_help(parser))
        parser.exit()


class HelpAll(argparse.Action):
    """``--help-all [WORD]``: every option, or those matching WORD; one line when none matches."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs="?", metavar="WORD",
                         help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        if not values:
            sys.stdout.write(parser.format_help())
            parser.exit()
        text = matching_help(parser, values)
        if text is None:
            parser.exit(2, f"sl4slam: no option of `{parser.prog}` matches {values!r}; "
                           f"`{parser.prog} --help-all` lists all of them\n")
        sys.stdout.write(text)
        parser.exit()


def unknown_flags(parser: argparse.ArgumentParser, tokens: list[str]) -> list[str]:
    """The ``--flags`` among ``tokens`` that ``parser`` does not know (nor as an unambiguous prefix),
    up to a bare ``--``."""
    flags = _actions_by_flag(parser)
    unknown = []
    for token in tokens:
        if token == "--":
            break
        if not token.startswith("--"):
            continue
        name = token.split("=", 1)[0]
        if name not in flags and not any(flag.startswith(name) for flag in flags):
            unknown.append(name)
    return unknown


def unknown_flags_message(parser: argparse.ArgumentParser, extras: list[str]) -> str:
    """The error for arguments ``parser`` does not know, with the closest flag names of each."""
    flags = sorted(_actions_by_flag(parser))
    hints = []
    for extra in extras:
        if not extra.startswith("-"):
            continue
        name = extra.split("=", 1)[0]
        close = difflib.get_close_matches(name, flags, n=3, cutoff=0.6)
        if close:
            hints.append(f"{name}: did you mean {' or '.join(close)}?")
        else:
            hints.append(f"{name}: no flag of that name ({parser.prog} --help lists them)")
    message = f"unrecognized arguments: {' '.join(extras)}"
    return message + ("; " + "; ".join(hints) if hints else "")

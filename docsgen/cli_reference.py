"""Markdown pages of every ``scancell`` command and option, from the argparse parsers."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import dataclass

from scancell.docsgen.markdown import cell


@dataclass(frozen=True)
class CommandPage:
    """One command (``scancell ctl``) with its sub-commands, as the parser defines it."""

    path: tuple[str, ...]
    parser: argparse.ArgumentParser
    help: str


def _subparsers(parser: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser, str]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield name, sub, helps.get(name, "")


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> Iterator[CommandPage]:
    """Every command and sub-command below ``parser``, depth first."""
    for name, sub, help_ in _subparsers(parser):
        yield CommandPage((*path, name), sub, help_)
        yield from walk(sub, (*path, name))


def options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """A parser's own arguments (no help flag, no sub-command selector)."""
    return [a for a in parser._actions
            if not isinstance(a, argparse._HelpAction | argparse._SubParsersAction)]


def option_names(parser: argparse.ArgumentParser) -> set[str]:
    """What a reader types: each option string, and each positional's metavar or dest."""
    out: set[str] = set()
    for a in options(parser):
        out.update(a.option_strings or [a.metavar or a.dest])
    return out


def _default(a: argparse.Action) -> str:
    if a.option_strings and isinstance(a, argparse._StoreTrueAction | argparse._StoreFalseAction
                                       | argparse._CountAction | argparse._VersionAction):
        return ""
    if a.default is None or a.default == argparse.SUPPRESS or a.default == []:
        return ""
    return f"`{a.default}`"


def _usage(page: CommandPage) -> str:
    usage = page.parser.format_usage().strip()
    return usage.removeprefix("usage: ")


def command_markdown(page: CommandPage, heading: bool = True) -> str:
    """One command's section: usage, what it does, each option with its default (``heading``:
    under a heading of its own; a top-level command's page has its title instead)."""
    head = "#" * min(len(page.path) + 1, 4)
    out = [f"{head} `scancell {' '.join(page.path)}`", ""] if heading else []
    text = page.parser.description or page.help
    if text:
        out += [cell(text), ""]
    out += ["```text", _usage(page), "```", ""]
    rows = options(page.parser)
    if rows:
        out += ["| argument | default | what |", "|---|---|---|"]
        for a in rows:
            names = ", ".join(f"`{s}`" for s in a.option_strings) or f"`{a.metavar or a.dest}`"
            if a.option_strings and a.nargs != 0 and a.metavar:
                names += f" `{a.metavar}`" if isinstance(a.metavar, str) else ""
            what = a.help if a.help and a.help != argparse.SUPPRESS else ""
            if a.choices and not isinstance(a, argparse._SubParsersAction):
                what = f"{what} (one of {', '.join(f'`{c}`' for c in a.choices)})".strip()
            out.append(f"| {names} | {_default(a)} | {cell(what % vars(a) if '%(' in what else what)} |")
        out.append("")
    subs = list(_subparsers(page.parser))
    if subs:
        out += ["Sub-commands: " + ", ".join(f"`{n}`" for n, _, _ in subs) + ".", ""]
    return "\n".join(out)


def pages() -> dict[str, str]:
    """``reference/cli/<command>.md`` -> Markdown, one page per top-level command, and the
    index ``reference/cli/index.md``."""
    from scancell.cli import COMMANDS, build_parser

    root = build_parser()
    out: dict[str, str] = {}
    index = ["# Command line", "",
             "Every `scancell` command and option, generated from the argparse parsers "
             "(`cli/`) when the site is built. `scancell COMMAND --help` prints the same.", "",
             "```text", root.format_usage().strip().removeprefix("usage: "), "```", "",
             "| command | what |", "|---|---|"]
    for name, (help_, _module) in COMMANDS.items():
        index.append(f"| [`{name}`]({name}.md) | {cell(help_)} |")
    out["reference/cli/index.md"] = "\n".join(index) + "\n"
    for top in walk_top(root):
        body = [f"# scancell {top.path[0]}", ""]
        body += [command_markdown(top, heading=False)]
        body += [command_markdown(p) for p in walk(top.parser, top.path)]
        out[f"reference/cli/{top.path[0]}.md"] = "\n".join(body)
    return out


def walk_top(root: argparse.ArgumentParser) -> Iterator[CommandPage]:
    for name, sub, help_ in _subparsers(root):
        yield CommandPage((name,), sub, help_)

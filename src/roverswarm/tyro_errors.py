"""tyro's refusals of a command line, in one line each.

tyro answers a value it cannot convert, a choice or an option it does not know, or a missing
argument with a box of many lines (and, for a mistyped option, every command's help of the
options it might have meant). The command line says every refusal in one line
(``roverswarm: error: ...``) with exit code 2: :func:`refusal` reads the box tyro printed.
"""

from __future__ import annotations

import itertools
import re


def _is_rule(line: str) -> bool:
    """A rule across tyro's box (``───``, or ``---`` in ASCII)."""
    return bool(line.strip()) and set(line.strip()) <= set("─-")


def _box(text: str) -> tuple[str, list[list[str]]] | None:
    """tyro's error box in ``text``: its title and its sections (the lines between its rules,
    sides and padding removed, indents kept, a blank line as ""); None if ``text`` holds no
    box. Drawn with lines (``╭─ title ─╮``, or ASCII ``+-`` where the output cannot show
    them), or, where tyro draws no frame (output that is not a terminal's), as the title, a
    rule and the contents indented by 2."""
    lines = text.strip("\n").splitlines()
    top = next((i for i, line in enumerate(lines) if line.startswith(("╭", "+-"))), None)
    if top is not None:
        title, contents = lines[top], []
        for line in lines[top + 1 :]:
            if line.startswith(("╰", "+-")):  # the bottom edge
                break
            contents.append(line[2:-1] if line[:1] in "│|" else line)
    elif len(lines) >= 2 and _is_rule(lines[1]):
        title, contents = lines[0], [line[2:] for line in lines[2:]]
    else:
        return None
    sections: list[list[str]] = [[]]
    for line in contents:
        if _is_rule(line):
            sections.append([])
        else:
            sections[-1].append(line.rstrip())
    return title.strip("╭╮+─- "), sections


def _paragraph(lines: list[str]) -> str:
    """The first paragraph of ``lines`` (up to a blank one) as one line."""
    return " ".join(line.strip() for line in (lines + [""])[: (lines + [""]).index("")])


def _suggestions(lines: list[str], argv: list[str]) -> list[str]:
    """The options of tyro's "Perhaps you meant" ``lines`` (``--episodes INT``, indented by 4,
    each followed by the commands it is in) that the command in ``argv`` has, each once."""
    words = [arg for arg in itertools.takewhile(lambda a: not a.startswith("-"), argv)]
    found: dict[str, None] = {}
    option = None
    for line in lines:
        if re.match(r" {4}\S", line):
            option = line.split()[0]
        where = re.fullmatch(r"\s+in roverswarm (.*) --help", line)
        if option and where and where[1].split() == words[: len(where[1].split())]:
            found[option] = None
    return list(found)


def refusal(text: str, argv: list[str], commands: tuple[str, ...]) -> str | None:
    """tyro's error box in ``text``, for the command line ``argv`` of a program with the
    subcommands ``commands``, as one line (a value it could not convert, an unknown choice,
    option or command, a missing argument); None if ``text`` holds no box (tyro's help)."""
    box = _box(text)
    if box is None:
        return None
    title, (body, *hints) = box
    message = _paragraph(body)
    helper = f"roverswarm {argv[0]} --help" if argv and argv[0] in commands else "roverswarm --help"
    if message.startswith("Error parsing "):
        return _value_error(message.removeprefix("Error parsing "))
    choice = re.fullmatch(r"invalid choice '(.*)' for argument '(.*)'\. Expected one of \((.*)\)\.?", message)
    if choice:
        allowed = ", ".join(c.strip().strip("'") for c in choice[3].split(","))
        return f"{choice[2]} must be one of {allowed}, got '{choice[1]}'"
    unknown = re.fullmatch(r"Unrecognized (?:or misplaced )?options: (.*)", message)
    if unknown:
        given = re.split(r"[,\s]+", re.sub(r"\(applied to [^)]*\)", "", unknown[1]).strip())
        flags = [g for g in given if g.startswith("-")]
        listed = next((_paragraph(h) for h in hints if h and h[0].startswith("Available subcommands: ")), None)
        if listed and not flags:
            return f"unknown command '{given[0]}': choose one of {listed.removeprefix('Available subcommands: ')}"
        meant = next((_suggestions(h, argv) for h in hints if h and h[0].strip() == "Perhaps you meant:"), [])
        guess = f" (did you mean {' or '.join(meant)}?)" if meant else ""
        return f"unknown option {', '.join(flags or given)}{guess}: see {helper}"
    missing = re.fullmatch(r"Missing from (.*):", body[0].strip()) if body else None
    if missing:
        needed = [line.split()[0] for line in body[1:] if re.match(r" {4}\S", line)]
        return f"{missing[1]} needs {', '.join(needed)}: see {missing[1]} --help"
    return f"{title}: {message}: see {helper}"


def _value_error(message: str) -> str:
    """tyro's message for a value it could not convert (``--episodes: invalid literal for int()
    with base 10: '2.5'``) in our words."""
    option, _, message = message.partition(": ")
    conversions = {
        "invalid literal for int() with base 10: ": "an integer",
        "could not convert string to float: ": "a number",
    }
    for said, kind in conversions.items():
        if message.startswith(said):
            return f"{option} must be {kind}, got {message.removeprefix(said)}"
    optional = re.fullmatch(r"no type matching \{None\}\|(INT|FLOAT) could be instantiated from \['(.*)'\]\.?", message)
    if optional:  # an option whose default is None (the preset's value)
        kind = "an integer" if optional[1] == "INT" else "a number"
        return f"{option} must be {kind} (or None: the default), got {optional[2]!r}"
    listed = re.fullmatch(r"Could not find valid parse for arguments: \[(.*)\]", message)
    if listed:  # a list of integers (--hidden)
        return f"{option} must be a list of integers, got {listed[1]}"
    return f"{option}: {message}"

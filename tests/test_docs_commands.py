"""Every `dali` command the documentation writes names options the command has: the commands in
README.md, docs/ and the model cards (code spans, indented and fenced code) are checked against
the CLI's own option words, so a renamed or removed option cannot live on in a page. The
`--detector-config` values they give are parsed as the option parses them."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from cli_commands import cli_commands, option_words

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")),
         *sorted((ROOT / "models").glob("*/README.md"))]  # fmt: skip
SPAN = re.compile(r"`([^`\n]*\bdali [^`\n]*)`")
OPTION = re.compile(r"^--[a-z0-9][a-z0-9-]*")


def code_texts(text: str) -> list[str]:
    """The code of a markdown page: inline spans, indented lines and fenced blocks (a line ending
    in a backslash joined with the next)."""
    texts, fenced = [], False
    for line in text.replace("\\\n", " ").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or line.startswith("    "):
            texts.append(line)
        else:
            texts += SPAN.findall(line)
    return texts


def written_commands() -> list[tuple[str, str, list[str]]]:
    """(page, command, the words after it) of every `dali COMMAND ...` in the pages' code."""
    commands = cli_commands()
    found = []
    for page in PAGES:
        for code in code_texts(page.read_text(encoding="utf-8")):
            for match in re.finditer(
                r"(?:^|[\s;&|($/])dali ((?:[a-z][a-z-]*)(?: [a-z][a-z-]*)?)", code
            ):
                words = match.group(1).split()
                name = " ".join(words) if " ".join(words) in commands else words[0]
                if name not in commands:
                    continue
                rest = code[match.start(1) + len(name) :]
                rest = re.split(r"[;`]|&&|\|\||(?:^|\s)dali\s|\s#\s", rest)[0]
                found.append((page.relative_to(ROOT).as_posix(), name, rest.split()))
    return found


WRITTEN = written_commands()


def test_the_pages_write_commands():
    assert len(WRITTEN) > 100, "the scan found too few dali commands in the pages"


@pytest.mark.parametrize("page", sorted({page for page, _, _ in WRITTEN}))
def test_every_option_a_page_writes_is_one_the_command_has(page):
    commands = cli_commands()
    unknown = []
    for where, name, words in WRITTEN:
        if where != page:
            continue
        accepted = option_words(commands[name]) | {"--help"}
        for word in words:
            option = OPTION.match(word.lstrip("[({"))
            if option and option.group(0) not in accepted:
                unknown.append(f"dali {name} {option.group(0)}")
    assert not unknown, f"{page}: {sorted(set(unknown))}"


def test_the_detector_configs_the_pages_give_parse():
    from dali_cli.commands.pretrain import read_json_option
    from dali_cli.detector.config import DetectorConfig

    values = [
        value
        for page in PAGES
        for value in re.findall(
            r"--detector-config '(\{[^']*\})'", page.read_text(encoding="utf-8")
        )
        if not re.search(r"\b[A-Z]\b", value)  # a placeholder such as W
    ]
    assert values, "no inline --detector-config in the pages"
    for value in values:
        DetectorConfig.from_dict(read_json_option(shlex.split(f"'{value}'")[0]))

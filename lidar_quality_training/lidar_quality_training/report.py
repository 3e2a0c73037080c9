"""The one writer of the offline reports: markdown tables and model cards.

:func:`markdown_table` writes every table of the train / evaluate CLIs and the demo report;
:class:`ModelCard` is the shape of the three ``MODEL_CARD.md`` files (a title, then
sections of paragraphs, bullet lists, tables and code blocks); :func:`update_card` puts
one named section into an existing card, replacing it when present (the evaluators'
held-out results, so that re-running an evaluation leaves one copy).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

__all__ = ["fmt", "round_floats", "markdown_table", "bullets", "code_block", "Section", "ModelCard",
           "put_section", "update_card"]

MISSING = "–"


def round_floats(d, digits: int = 5):
    """``d`` (dicts, lists, tuples, floats) with every float rounded to ``digits`` and
    non-finite floats as None: manifests' and summaries' JSON."""
    if isinstance(d, dict):
        return {k: round_floats(v, digits) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [round_floats(v, digits) for v in d]
    if isinstance(d, (float, np.floating)):
        return round(float(d), digits) if np.isfinite(d) else None
    return d


def fmt(x, digits: int = 3) -> str:
    """A value for a table cell or a sentence: ``None`` / NaN / inf as '–', integers as
    integers, other numbers with ``digits`` decimals, a (mean, std) pair as 'm ± s',
    text as it is."""
    if x is None:
        return MISSING
    if isinstance(x, str):
        return x
    if isinstance(x, (tuple, list)) and len(x) == 2:
        return f"{fmt(x[0], digits)} ± {fmt(x[1], digits)}"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    try:
        xf = float(x)
    except (TypeError, ValueError):
        return str(x)
    return f"{xf:.{digits}f}" if np.isfinite(xf) else MISSING


def _escape(text: str) -> str:
    # An unescaped '|' would end the cell early (also inside `code` in GitHub tables).
    return re.sub(r"(?<!\\)\|", r"\\|", text)


def _row(cells: Iterable[str]) -> str:
    return "|" + "|".join(f" {c} " if c else " " for c in cells) + "|"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence], digits: int = 3) -> str:
    """A GitHub markdown table ending in a newline; cells pass through :func:`fmt`
    (``digits`` decimals) and '|' in text is escaped. Raises ``ValueError`` for a row
    whose length is not the header's."""
    for r in rows:
        if len(r) != len(header):
            raise ValueError(f"table row of {len(r)} cells under {len(header)} columns: {r!r}")
    lines = [_row(_escape(str(h)) for h in header), "|" + "---|" * len(header)]
    lines += [_row(_escape(fmt(c, digits)) for c in r) for r in rows]
    return "\n".join(lines) + "\n"


def bullets(items: Iterable[str]) -> str:
    """A markdown bullet list, one item a line."""
    return "\n".join(f"- {i}" for i in items)


def code_block(text: str, lang: str = "bash") -> str:
    """A fenced code block."""
    return f"```{lang}\n{text}\n```"


@dataclass
class Section:
    """A ``## title`` section: markdown blocks (paragraphs, lists, tables, code) written
    with one blank line between them; empty blocks are left out."""

    title: str
    blocks: list[str] = field(default_factory=list)

    def add(self, *blocks: str) -> Section:
        self.blocks.extend(blocks)
        return self

    def render(self) -> str:
        return _join([f"## {self.title}", *self.blocks])


@dataclass
class ModelCard:
    """A model card: ``# title``, intro blocks, then sections."""

    title: str
    intro: list[str] = field(default_factory=list)
    sections: list[Section] = field(default_factory=list)

    def section(self, title: str, *blocks: str) -> Section:
        """Append a section and return it (to add more blocks)."""
        s = Section(title, list(blocks))
        self.sections.append(s)
        return s

    def render(self) -> str:
        return _join([f"# {self.title}", *self.intro, *(s.render() for s in self.sections)])

    def write(self, path: Path) -> Path:
        Path(path).write_text(self.render())
        return Path(path)


def _join(blocks: Iterable[str]) -> str:
    return "\n\n".join(b.strip("\n") for b in blocks if b and b.strip("\n")) + "\n"


def _headings(lines: list[str]) -> list[tuple[int, int, str]]:
    """(line index, level, title) of the headings outside fenced code (a ``#`` line in a
    shell block is a comment, not a heading)."""
    out, fenced = [], False
    for i, line in enumerate(lines):
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"(#{1,6}) +(.*?)\s*$", line)):
            out.append((i, len(m.group(1)), m.group(2)))
    return out


def put_section(text: str, section: Section, *, before: str | None = None) -> str:
    """``text`` with ``section`` in place of its ``## title`` section (up to the next
    heading of level 1 or 2) if it has one; else inserted before the ``## before``
    section if there is one; else appended. Putting the same section twice gives the
    text of putting it once."""
    lines = text.splitlines(keepends=True)
    heads = [h for h in _headings(lines) if h[1] <= 2]
    block = section.render()
    at = next((k for k, h in enumerate(heads) if h[1] == 2 and h[2] == section.title), None)
    if at is not None:
        start = heads[at][0]
        end = heads[at + 1][0] if at + 1 < len(heads) else len(lines)
        tail = "".join(lines[end:])
        return "".join(lines[:start]) + block + ("\n" + tail if tail else "")
    nxt = next((h[0] for h in heads if h[1] == 2 and h[2] == before), None)
    if before is not None and nxt is not None:
        return "".join(lines[:nxt]) + block + "\n" + "".join(lines[nxt:])
    head = text.rstrip("\n")
    return (head + "\n\n" if head else "") + block


def update_card(path: Path, section: Section, *, before: str | None = None) -> Path:
    """Put ``section`` into the card at ``path`` (see :func:`put_section`); a missing
    card is started with the section alone."""
    path = Path(path)
    text = path.read_text() if path.is_file() else ""
    path.write_text(put_section(text, section, before=before))
    return path

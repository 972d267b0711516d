"""What the documentation tests read from the pages: their shell lines, the simple commands in a line,
and a heading's anchor (shared by tests/test_readme.py and tests/test_citations.py)."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def shell_lines(text: str) -> list[str]:
    """The lines of a page's ```bash blocks, each continued line (a trailing backslash) joined."""
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    return [line for block in blocks for line in block.replace("\\\n", " ").splitlines() if line.strip()]


def shell_blocks(page: Path) -> list[str]:
    """The ```bash lines of a page file (shell_lines of its text)."""
    return shell_lines(page.read_text())


def commands(line: str) -> list[list[str]]:
    """The simple commands of a shell line: split at |, &&, ; and &, comments dropped."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars="|&;")
    lexer.whitespace_split, lexer.commenters = True, "#"
    found, current = [], []
    for token in lexer:
        if set(token) <= set("|&;"):
            found.append(current)
            current = []
        else:
            current.append(token)
    return [c for c in found + [current] if c]


def slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")

"""A benchmark's report: Markdown lines printed as they come and kept, to be written to a file
(``--out``) at the end (imported as a sibling module, as the benchmarks run as scripts)."""

from __future__ import annotations

import pathlib
from typing import List, Optional, Sequence


class Report:
    """Lines printed at once (flushed: a long run shows its progress) and kept for `save`."""

    def __init__(self) -> None:
        self.lines: List[str] = []

    def __call__(self, line: str = "") -> None:
        print(line, flush=True)
        self.lines.append(line)

    def save(self, path: Optional[str]) -> None:
        """Writes every line so far to ``path`` (nothing where it is None)."""
        if path:
            pathlib.Path(path).write_text("\n".join(self.lines) + "\n")


def table_head(columns: Sequence[str]) -> str:
    """A Markdown table's first two lines: the columns' names, then the rule under them."""
    return "| " + " | ".join(columns) + " |\n" + "|---" * len(columns) + "|"

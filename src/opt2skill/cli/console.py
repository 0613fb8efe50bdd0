"""Shared terminal output: one rich console, and tables of figures."""

from __future__ import annotations

from collections.abc import Iterable

from rich.console import Console
from rich.table import Table

# soft_wrap: a line longer than the terminal is left to the terminal, never broken by rich, so a path
# printed in a message stays one copyable (and greppable) string.
console = Console(soft_wrap=True)
err_console = Console(stderr=True, soft_wrap=True)


def figures_table(title: str, rows: Iterable[tuple[str, str]], headers: tuple[str, str] = ("quantity", "value")) -> Table:
    table = Table(title=title, title_justify="left")
    table.add_column(headers[0])
    table.add_column(headers[1], justify="right")
    for name, value in rows:
        table.add_row(name, value)
    return table

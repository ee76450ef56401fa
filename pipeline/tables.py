"""Listings that never cut what users type: a table when it fits the terminal, else a plain listing.

Rich shrinks a table that is wider than the terminal by wrapping and then cutting cells with an
ellipsis. Names and paths (what users type or paste) must stay whole, so ``keep`` columns are never
wrapped or cut: the table is drawn only when those columns fit at their full width beside narrow
other columns (which wrap); otherwise the rows are printed as a plain listing, one field per line.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

#: the narrowest a wrapped (not kept) column is squeezed to before the plain listing is used instead
MIN_WRAPPED_WIDTH = 12


@dataclass(frozen=True)
class Column:
    """A column; ``keep``: shown whole on one line (names, paths)."""

    header: str
    keep: bool = False
    justify: str = "left"


def cell_width(cell: str) -> int:
    """Printed width of a cell written in rich markup."""
    return Text.from_markup(cell).cell_len


def table_fits(columns: Sequence[Column], rows: Sequence[Sequence[str]], width: int) -> bool:
    """Whether the kept columns fit whole with every other column at least ``MIN_WRAPPED_WIDTH`` wide."""
    need = 1  # the left border; each column adds its padding (2) and a border (1)
    for i, col in enumerate(columns):
        full = max([cell_width(col.header), *(cell_width(r[i]) for r in rows)])
        need += 3 + (full if col.keep else min(full, MIN_WRAPPED_WIDTH))
    return need <= width


def print_listing(console: Console, title: str, columns: Sequence[Column], rows: Sequence[Sequence[str]]) -> None:
    """A table when its kept columns fit whole at the console's width, else a plain listing.

    Cells are rich markup (escape literal text with :func:`rich.markup.escape`).
    """
    if table_fits(columns, rows, console.width):
        table = Table(title=title, title_justify="left")
        for col in columns:
            full = max([cell_width(col.header), *(cell_width(r[columns.index(col)]) for r in rows)])
            if col.keep:
                table.add_column(col.header, no_wrap=True, min_width=full, justify=col.justify)  # type: ignore[arg-type]
            else:
                table.add_column(col.header, overflow="fold", justify=col.justify)  # type: ignore[arg-type]
        for r in rows:
            table.add_row(*r)
        console.print(table)
        return
    # plain listing: one line per row, the first column then the others as "header: value", never cut
    console.print(f"[bold]{escape(title)}[/]", soft_wrap=True)
    for r in rows:
        rest = [f"{escape(col.header)}: {cell}" for col, cell in zip(columns[1:], r[1:], strict=True)
                if cell_width(cell)]
        console.print(f"[bold]{r[0]}[/]  " + " | ".join(rest), soft_wrap=True, highlight=False)

"""What every scenario ends with: its checks, measured in the physics, as a table.

A check is ``(name, ok, measured)``: what was checked, whether it held, and the measured
figure as text (so a reader sees how close a pass or a failure was)."""

from __future__ import annotations

from pathlib import Path

from rich.table import Table
from rich.text import Text

Check = tuple[str, bool, str]


def checks_table(title: str, results: list[Check]) -> Table:
    """The checks as a table: check, ok/FAILED, measured."""
    table = Table(title=title)
    for col in ("check", "result", "measured"):
        table.add_column(col)
    for name, ok, measured in results:
        table.add_row(name, Text("ok", style="green") if ok else Text("FAILED", style="red"),
                      measured)
    return table


def process_failures(failed: dict[str, int], log_dir: Path) -> list[Check]:
    """A failed check naming every scenario process that died, with its exit code and
    log; none when all ran to the end."""
    if not failed:
        return []
    return [("every process ran to the end", False,
             ", ".join(f"{n} exit {c} (log: {log_dir / (n + '.log')})"
                       for n, c in sorted(failed.items())))]

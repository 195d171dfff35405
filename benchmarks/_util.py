"""Helpers shared by the benchmarks: percentiles and the JSON-line report."""

from __future__ import annotations

import json
import statistics
from collections.abc import Sequence
from typing import Any


def percentile(samples: Sequence[float], q: float) -> float:
    """The q-th percentile (0–100) of ``samples``, nearest-rank."""
    ordered = sorted(samples)
    if not ordered:
        raise ValueError("no samples")
    k = max(0, min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1))))
    return ordered[k]


def median(samples: Sequence[float]) -> float:
    return statistics.median(samples)


def report(name: str, value: float, unit: str, target: str | None = None,
           ok: bool | None = None, **extra: Any) -> dict[str, Any]:
    """Print one figure as a JSON line and return it.

    ``target`` is human-readable (``"<= 2 ms"``); ``ok`` says whether it was met
    (None: informational figure, e.g. a floor).
    """
    row: dict[str, Any] = {"name": name, "value": round(value, 3), "unit": unit,
                           "target": target, "ok": ok, **extra}
    print(json.dumps(row), flush=True)
    return row

"""The console demo checks itself; run it so `make demo` cannot rot silently."""

from __future__ import annotations

import io

from rich.console import Console

from behaviours.demos.console import run_highlevel_demo


def test_highlevel_demo_reports_no_problem() -> None:
    out = io.StringIO()
    problems = run_highlevel_demo(Console(file=out, width=100))
    assert problems == []
    text = out.getvalue()
    assert "type lock refused" in text and "'driving'" in text


def test_tutorial_example_runs(capsys) -> None:  # type: ignore[no-untyped-def]
    import runpy
    from pathlib import Path

    example = Path(__file__).resolve().parent.parent / "examples" / "patrol.py"
    runpy.run_path(str(example), run_name="__main__")
    out = capsys.readouterr().out
    assert "speed right after the switch: 0.0" in out
    assert "refused: action type 'driving'" in out
    assert "charge: SUCCEEDED docked" in out
    assert "patrol INTERRUPTED" in out

"""docs/tutorial.md works for a newcomer: its code blocks, in order, are a complete program
that prints what the text says, and examples/patrol.py is that program."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from beehave.testing import WALL_TIMEOUT_S

ROOT = Path(__file__).resolve().parent.parent
TUTORIAL = ROOT / "docs" / "tutorial.md"
EXAMPLE = ROOT / "examples" / "patrol.py"


def section_one_blocks() -> list[str]:
    text = TUTORIAL.read_text()
    section = text[text.index("## 1."):text.index("## 2.")]
    return re.findall(r"```python\n(.*?)```", section, re.S)


def test_the_tutorial_code_runs_as_written(tmp_path: Path) -> None:
    program = tmp_path / "tutorial.py"
    program.write_text("\n\n".join(section_one_blocks()))
    done = subprocess.run([sys.executable, str(program)], capture_output=True, text=True,
                          timeout=WALL_TIMEOUT_S, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "switched; speed right after the switch: 0.0\n" in out, out
    assert "refused: action type 'driving' is held by DriveTo" in out, out
    assert "charge: SUCCEEDED docked" in out, out
    assert re.search(r"^\s+patrol INTERRUPTED", out, re.M), out


def test_the_example_is_the_tutorial_code() -> None:
    example = EXAMPLE.read_text()
    for block in section_one_blocks():
        assert block.rstrip("\n") in example, f"not in {EXAMPLE.name}:\n{block}"

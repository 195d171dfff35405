"""docs/testing.md works as written: its test files, run by plain pytest in a directory of
their own (the plugin loads because beehave is installed, as for a user), all pass."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from beehave.testing import WALL_TIMEOUT_S

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "testing.md"


def doc_test_files() -> dict[str, str]:
    blocks = re.findall(r"```python\n(# (test_\w+\.py)\n.*?)```", DOC.read_text(), re.S)
    return {name: code for code, name in blocks}


def test_the_doc_has_its_examples() -> None:
    assert set(doc_test_files()) == {"test_tour.py", "test_switch.py", "test_autojump.py",
                                     "test_lights.py"}


def test_the_docs_tests_pass_under_plain_pytest(tmp_path: Path) -> None:
    for name, code in doc_test_files().items():
        (tmp_path / name).write_text(code)
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
         "--rootdir", str(tmp_path), str(tmp_path)],
        capture_output=True, text=True, timeout=WALL_TIMEOUT_S, cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert re.search(r"\b4 passed\b", done.stdout), done.stdout

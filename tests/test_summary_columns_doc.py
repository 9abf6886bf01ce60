"""Every summary column is described where the table is (the command-line guide's "The summary columns"),
and the run prints a pointer to that section under its table."""

import re
from pathlib import Path

from torchflow.app.cli import COLUMNS_GUIDE
from torchflow.app.runner import SUMMARY_COLUMNS

ROOT = Path(__file__).resolve().parents[1]


def test_every_summary_column_is_described_in_the_guide():
    guide = (ROOT / "docs" / "guide" / "command-line.md").read_text()
    start = guide.index("### The summary columns")
    section = guide[start : guide.index("\n## ", start)]
    described = set()
    for row in re.findall(r"^\| (.+?) \| .+ \|$", section, re.M):
        described |= set(re.findall(r"`([a-z_]+)`", row))
    missing = [c for c in SUMMARY_COLUMNS if c not in described]
    assert not missing, f"summary columns not described in the guide: {missing}"
    path, anchor = COLUMNS_GUIDE.split("#")
    assert path == "docs/guide/command-line.md" and anchor == "the-summary-columns"

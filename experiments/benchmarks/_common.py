"""Small helpers shared by the benchmark scripts: load average and result files."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

HERE = Path(__file__).resolve().parent


def loadavg() -> Optional[list]:
    """1/5/15-minute load average (rounded), or None where the OS has none."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # pragma: no cover
        return None


def write_results(res: dict, name: str, quick: bool = False, out: Optional[str] = None) -> Path:
    """Write ``res["markdown"]`` to ``out`` (default ``results_<name>[_quick].md`` in this folder) and
    the rest of ``res`` as JSON next to it; print the markdown. A ``--quick`` smoke test never
    overwrites the full results."""
    path = Path(out) if out else HERE / (f"results_{name}_quick.md" if quick else f"results_{name}.md")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(res["markdown"])
    path.with_suffix(".json").write_text(json.dumps({k: v for k, v in res.items() if k != "markdown"},
                                                    indent=1, default=str))
    print(res["markdown"])
    print(f"wrote {path}")
    return path

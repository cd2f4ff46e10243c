"""What every benchmark script shares: writing its result as JSON."""

from __future__ import annotations

import json
import pathlib


def save_json(result: dict, out: str | None, default: str | None = None) -> pathlib.Path | None:
    """Write `result` to `out` (or `default`), creating folders; prints and returns the path.

    Nothing is written when neither is given.
    """
    path = out or default
    if not path:
        return None
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))
    print(f"wrote {path}")
    return path

"""Reading the protocol twins' JSON-lines ground-truth files."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from typing import Any

__all__ = ["iter_truth_records"]


def iter_truth_records(path: str | os.PathLike[str]) -> Iterator[dict[str, Any]]:
    """The records of a twin's truth file in order, skipping a line still being written.

    A twin appends one JSON object per line while it runs; the last line may be partial
    when the file is read during the run, and is skipped (it is complete on the next read).
    """
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.strip()
            if not line:
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line being written right now
            if isinstance(record, dict):
                yield record

"""Reading `index.jsonl`, the sequence's one-row-per-FrameSet index, tolerating the damage a crash leaves.

The recorder appends a row only after every image it names is completely written, so the index never
points at a file that is not there (up to the last sync on a power cut). What a crash can leave is a
torn last row; a damaged disk can leave a corrupt line anywhere.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.storage.layout import INDEX, SequenceError


@dataclass
class IndexScan:
    rows: list[dict]  # every whole, well-formed row in file order, also those after a corrupt line
    row_ends: list[int]  # for each row, the byte offset just after its newline
    good_bytes: int  # offset after the last row before any damage: the index is whole up to here
    torn_tail: bool  # the last line is incomplete or unparseable (the recorder died mid-row)
    corrupt_lines: list[int]  # 1-based numbers of unparseable lines before the last one


def is_index_row(row: Any) -> bool:
    """A row as the recorder writes it: a set number and, per camera, a frame record or null."""
    if not isinstance(row, dict) or "set" not in row or not isinstance(row.get("frames"), dict):
        return False
    return all(rec is None or (isinstance(rec, dict) and isinstance(rec.get("file"), str)
                               and isinstance(rec.get("host_ts_ns"), int))
               for rec in row["frames"].values())


def scan_index(root: Path) -> IndexScan:
    path = root / INDEX
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SequenceError(f"{root}: not a sequence ({INDEX} missing)") from None
    scan = IndexScan(rows=[], row_ends=[], good_bytes=0, torn_tail=False, corrupt_lines=[])
    pos = 0
    line_no = 0
    while pos < len(data):
        nl = data.find(b"\n", pos)
        line_no += 1
        if nl < 0:  # no newline: the recorder died mid-row
            scan.torn_tail = True
            break
        line = data[pos:nl]
        pos = nl + 1
        try:
            row = json.loads(line)
        except ValueError:  # JSON and UTF-8 errors alike
            row = None
        if not is_index_row(row):
            scan.corrupt_lines.append(line_no)
            continue
        scan.rows.append(row)
        scan.row_ends.append(pos)
        if not scan.corrupt_lines:
            scan.good_bytes = pos
    if scan.corrupt_lines and scan.corrupt_lines[-1] == line_no and not scan.torn_tail:
        # the last line is damaged: treat it as a torn tail (power cut mid-write)
        scan.corrupt_lines.pop()
        scan.torn_tail = True
    return scan

"""The check of a rig config's `[sim]` tables. The simulator owns what the options mean."""
from __future__ import annotations


def check_options(table: dict, kind: str) -> None:
    """Validate a `[sim]` table of a rig config (`kind`: "scene", "camera" or "trigger"); ValueError
    names the bad key."""
    from simulator.options import validate_options

    validate_options(table, kind)

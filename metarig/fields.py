"""The one way to declare a documented, bounded configuration field (dataclasses).

Every configuration dataclass of the project (devices, nodes, tracker) declares its fields with
`param`, so ROS parameters, command-line flags and docs are generated from one metadata schema:
`{"description": str, "min": number | None, "max": number | None, "choices": tuple | None}`.
"""

from dataclasses import field


def param(default, desc: str, lo=None, hi=None, choices=None, **kw):
    """A dataclass field with a default, a one-line description (with its SI unit) and bounds.

    A class or other callable default (a nested config) becomes a `default_factory`.
    """
    meta = {"description": desc, "min": lo, "max": hi, "choices": choices}
    if callable(default) and not isinstance(default, (int, float, str)):
        return field(default_factory=default, metadata=meta, **kw)
    return field(default=default, metadata=meta, **kw)

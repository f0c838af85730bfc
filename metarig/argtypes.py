"""Command-line value types shared by every `metarig` subcommand (argparse `type=` callables).

A bad value becomes argparse's one-line usage error (exit code 2), never a traceback.
"""

import argparse
import math


def _number(kind, ok, bound: str):
    """Parser of a finite `kind` (int or float) value v with ok(v), else "must be {bound}"."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {kind.__name__}, got {text!r}") from None
        if not (math.isfinite(v) and ok(v)):
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return v
    return parse


def positive(kind=int):
    """Parser of a positive `kind` (int or float) value."""
    return _number(kind, lambda v: v > 0, "at least 1" if kind is int else "positive")


def non_negative(kind=int):
    """Parser of a `kind` (int or float) value >= 0 (where 0 has a meaning, e.g. "all")."""
    return _number(kind, lambda v: v >= 0, "0 or more")


def grid_size(text: str) -> tuple[int, int]:
    """Parser of a lattice size NXxNY (e.g. 24x16), at least 2x2."""
    try:
        nx, ny = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 24x16, got {text!r}") from None
    if nx < 2 or ny < 2:
        raise argparse.ArgumentTypeError(f"size needs at least 2x2, got {text!r}")
    return nx, ny


def text(what: str):
    """Parser of a non-empty text value (an empty one would read as "not given")."""
    def parse(value: str) -> str:
        if not value.strip():
            raise argparse.ArgumentTypeError(f"{what} is empty")
        return value
    return parse


def number_list(what: str, positive_only: bool = False, distinct_sorted: bool = False):
    """Parser of a comma list of numbers; optionally all positive, and distinct (then sorted)."""
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(",") if v.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{what} must be a comma list of numbers, got {text!r}") from None
        if not values:
            raise argparse.ArgumentTypeError(f"{what} list is empty")
        if not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"{what} must be finite, got {text!r}")
        if positive_only and min(values) <= 0:
            raise argparse.ArgumentTypeError(f"{what} must be positive, got {min(values):g}")
        if distinct_sorted:
            if len(set(values)) != len(values):
                raise argparse.ArgumentTypeError(f"{what} list repeats a value: {text!r}")
            values = tuple(sorted(values))
        return values
    return parse

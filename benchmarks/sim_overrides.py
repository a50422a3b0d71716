"""`KEY=VALUE` options that switch one `SimParams` field of our engine for a measurement (fidelity, engine speed)."""

from __future__ import annotations

import argparse

from engine import SimParams


def sim_override(text: str) -> tuple[str, float]:
    """Parse `KEY=VALUE` for argparse: KEY a `SimParams` field, VALUE a number (booleans and enums as 0, 1, ...)."""
    key, _, value = text.partition("=")
    if not value:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    fields = sorted(SimParams.__dataclass_fields__)
    if key not in fields:
        raise argparse.ArgumentTypeError(f"{key!r} is not a SimParams field (fields: {', '.join(fields)})")
    try:
        return key, float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key}={value!r}: the value is not a number") from None

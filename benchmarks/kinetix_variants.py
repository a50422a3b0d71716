"""Kinetix changed in one respect (`benchmarks/kinetix_fidelity_baseline.py --variant`, `benchmarks/fidelity.py
--kinetix-variant`): how far Kinetix's own outcomes move under a change that any engine other than Jax2D itself
makes too, which bounds the agreement such an engine can reach. Imports nothing but the standard library, so both
virtualenvs read it."""

from __future__ import annotations

import argparse

VARIANTS = {
    "solver_iterations": "Jax2D's sequential-impulse iterations per physics step (Kinetix: 10)",
    "solver_batch_size": "contacts of a kind that Jax2D's solver resolves at once, each from the same velocities "
    "(Kinetix: 16, every contact of an s or m level at once); 1 resolves them one after another",
    "padding_writes": "1: Jax2D's solver writes its padding rows' zero impulses to the last pair of each kind (its "
    "bug B1, Kinetix as released); 0: they are dropped, so that pair keeps its warm start",
}
"""What `--variant KEY=VALUE` may change of Kinetix, and what it means."""


def parse_variant(text: str) -> tuple[str, int]:
    """`KEY=VALUE` of a Kinetix variant, refused in one line unless KEY is in VARIANTS and VALUE an integer."""
    key, _, value = text.partition("=")
    if key not in VARIANTS:
        raise argparse.ArgumentTypeError(f"{key!r} is not a Kinetix variant (variants: {', '.join(sorted(VARIANTS))})")
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key}={value!r}: the value is not an integer") from None
    if (key == "padding_writes" and number not in (0, 1)) or (key != "padding_writes" and number < 1):
        raise argparse.ArgumentTypeError(f"{key}={number}: out of range ({VARIANTS[key]})")
    return key, number


def variant_label(variant: dict) -> str:
    """`KEY=VALUE,...` of a variant in a fixed order ('' for Kinetix as released)."""
    return ",".join(f"{key}={value}" for key, value in sorted(variant.items()))

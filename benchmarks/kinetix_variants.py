"""Kinetix changed in one respect (`benchmarks/kinetix_fidelity_baseline.py --variant`, `benchmarks/fidelity.py
--kinetix-variant`). Two uses: how far Kinetix's own outcomes move under a change that any engine other than Jax2D
itself makes too (more solver iterations, another order of solving, Jax2D's B1 corrected), which bounds the agreement
such an engine can reach; and which of Jax2D's contact parameters, moved towards what kforge does, moves Kinetix's
outcomes towards ours. Imports nothing but the standard library, so both virtualenvs read it."""

from __future__ import annotations

import argparse

VARIANTS = {
    "solver_iterations": (int, 1, None, "Jax2D's sequential-impulse iterations per physics step (Kinetix: 10)"),
    "solver_batch_size": (
        int,
        1,
        None,
        "contacts of a kind that Jax2D's solver resolves at once, each from the same velocities (Kinetix: 16, every "
        "contact of an s or m level at once); 1 resolves them one after another",
    ),
    "padding_writes": (
        int,
        0,
        1,
        "1: Jax2D's solver writes its padding rows' zero impulses to the last pair of each kind (its bug B1, Kinetix "
        "as released); 0: they are dropped, so that pair keeps its warm start",
    ),
    "baumgarte_collision": (
        float,
        0.0,
        None,
        "share of a contact's overlap beyond the slop that Jax2D turns into separating velocity per step (Kinetix: "
        "0.2); the velocity stays in the bodies after the overlap is gone",
    ),
    "exact_disc_inertia": (
        int,
        0,
        1,
        "1: a disc turns with its moment of inertia m r^2 / 2 (Jax2D's B2 corrected, as in kforge); 0: m r^2 / 4, as "
        "Jax2D computes it and Kinetix's level files store it",
    ),
    "slop": (float, 0.0, None, "overlap in metres that Jax2D leaves uncorrected (Kinetix: 0.01)"),
    "substeps": (
        int,
        1,
        None,
        "Jax2D steps of 1/60 s divided by this in place of each of 1/60 s (Kinetix: 1; an env step is 2 of them): "
        "contacts are found this much sooner after shapes meet, and motors, thrusters and Baumgarte's share act per "
        "shorter step",
    ),
}
"""What `--variant KEY=VALUE` may change of Kinetix: the value's type, its least and greatest value (None: no
bound), and what it means."""


def parse_variant(text: str) -> tuple[str, float]:
    """`KEY=VALUE` of a Kinetix variant, refused in one line unless KEY is in VARIANTS and VALUE in its range."""
    key, _, value = text.partition("=")
    if key not in VARIANTS:
        raise argparse.ArgumentTypeError(f"{key!r} is not a Kinetix variant (variants: {', '.join(sorted(VARIANTS))})")
    kind, least, greatest, meaning = VARIANTS[key]
    try:
        number = kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key}={value!r}: not a number of type {kind.__name__}") from None
    if number < least or (greatest is not None and number > greatest):
        raise argparse.ArgumentTypeError(f"{key}={number}: out of range ({meaning})")
    return key, number


def variant_label(variant: dict) -> str:
    """`KEY=VALUE,...` of a variant in a fixed order ('' for Kinetix as released)."""
    return ",".join(f"{key}={value}" for key, value in sorted(variant.items()))

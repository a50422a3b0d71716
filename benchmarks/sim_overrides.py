"""Options that switch our engine for a measurement (fidelity, engine speed): `KEY=VALUE` for one `SimParams` field
or one law of `StaticSimParams`, and the solver scheme's settings in `StaticSimParams`."""

from __future__ import annotations

import argparse
import dataclasses
import enum

from kforge.engine import PHYSICS_SCHEMES, SimParams, StaticSimParams
from kforge.engine.schemes import DEFAULT_PHYSICS_SCHEME

LAW_FIELDS: dict[str, type[enum.IntEnum]] = {
    field.name: type(getattr(StaticSimParams(), field.name))
    for field in dataclasses.fields(StaticSimParams)
    if isinstance(getattr(StaticSimParams(), field.name), enum.IntEnum)
}
"""`StaticSimParams` law field -> its enum (the fields whose value is an enum)."""

STATIC_SWITCHES = (*LAW_FIELDS, "swept_speculative_contacts")
"""`StaticSimParams` fields that `KEY=VALUE` also sets: the laws (VALUE an enum's number) and the swept contacts switch
(VALUE 0 or 1)."""

SOLVER_SCHEME_FIELDS = {
    "substeps": "num_substeps",
    "iterations": "num_iterations",
    "relax_iterations": "num_relax_iterations",
    "block_contacts": "block_contacts",
    "relax_contacts": "relax_contacts",
}
"""Solver scheme option (as a measurement names it) -> `StaticSimParams` field."""
SOLVER_COUNT_LEAST = {"substeps": 1, "iterations": 1, "relax_iterations": 0}
"""The least value of each solver count option."""


def sim_override(text: str) -> tuple[str, float | int | bool]:
    """Parse `KEY=VALUE` for argparse: KEY a `SimParams` field (VALUE a number) or one of `STATIC_SWITCHES` (VALUE
    the law's number, or 0/1)."""
    key, _, value = text.partition("=")
    if not value:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    fields = sorted(SimParams.__dataclass_fields__)
    if key not in fields and key not in STATIC_SWITCHES:
        known = ", ".join(fields + sorted(STATIC_SWITCHES))
        raise argparse.ArgumentTypeError(f"{key!r} is neither a SimParams field nor a law (known: {known})")
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key}={value!r}: the value is not a number") from None
    if key in fields:
        return key, number
    if key in LAW_FIELDS:
        try:
            return key, LAW_FIELDS[key](number)
        except ValueError as error:
            raise argparse.ArgumentTypeError(f"{key}={value!r}: {error}") from None
    if number not in (0.0, 1.0):
        raise argparse.ArgumentTypeError(f"{key}={value!r}: the value is not 0 or 1")
    return key, bool(number)


def split_sim_overrides(overrides) -> tuple[dict, dict]:
    """The `(KEY, VALUE)` pairs of `sim_override` (or a dict of them) as `SimParams` fields and `StaticSimParams`
    laws."""
    overrides = dict(overrides)
    constants = {key: value for key, value in overrides.items() if key not in STATIC_SWITCHES}
    return constants, {key: value for key, value in overrides.items() if key in STATIC_SWITCHES}


def with_sim_overrides(params: SimParams, static: StaticSimParams, overrides) -> tuple[SimParams, StaticSimParams]:
    """`params` and `static` with the `(KEY, VALUE)` pairs of `sim_override`, each in the one it belongs to."""
    constants, laws = split_sim_overrides(overrides)
    return (
        params.replace(**constants) if constants else params,
        dataclasses.replace(static, **laws) if laws else static,
    )


def solver_count_errors(scheme: dict, option_prefix: str = "--") -> list[str]:
    """One line per count of `scheme` (options of SOLVER_SCHEME_FIELDS; None: not given) below its least."""
    return [
        f"{option_prefix}{key.replace('_', '-')} must be at least {least}, got {scheme[key]}"
        for key, least in SOLVER_COUNT_LEAST.items()
        if scheme.get(key) is not None and scheme[key] < least
    ]


def with_solver_scheme(sim: StaticSimParams, scheme: dict) -> StaticSimParams:
    """`sim` with the settings of `scheme` (options of SOLVER_SCHEME_FIELDS; None leaves a setting unchanged)."""
    changes = {SOLVER_SCHEME_FIELDS[key]: value for key, value in scheme.items() if value is not None}
    return dataclasses.replace(sim, **changes) if changes else sim


def add_physics_option(parser: argparse.ArgumentParser) -> None:
    """`--physics NAME`: our engine's named physics scheme (a job's env.physics), which the other options switch."""
    parser.add_argument(
        "--physics",
        choices=list(PHYSICS_SCHEMES),
        default=DEFAULT_PHYSICS_SCHEME,
        help="our engine's physics scheme (a job's env.physics), under the options below",
    )


def add_solver_scheme_options(parser: argparse.ArgumentParser) -> None:
    """`--substeps`, `--iterations`, `--relax-iterations`, `--block-contacts`, `--no-relax-contacts`: our solver's
    scheme for a measurement (`solver_scheme` reads them back; the engine's setting where not given)."""
    parser.add_argument("--substeps", type=int, help="solver substeps per physics step of ours (default: the engine's)")
    parser.add_argument(
        "--iterations", type=int, help="position-correcting solver passes per substep of ours (default: the engine's)"
    )
    parser.add_argument(
        "--relax-iterations", type=int, help="relaxing solver passes per substep of ours (default: the engine's)"
    )
    parser.add_argument(
        "--block-contacts",
        action="store_const",
        const=True,
        help="ours solves a pair's two rigid normal rows together (StaticSimParams.block_contacts)",
    )
    parser.add_argument(
        "--no-relax-contacts",
        dest="relax_contacts",
        action="store_const",
        const=False,
        help="ours' relaxing passes solve joints only (StaticSimParams.relax_contacts)",
    )


def solver_scheme(args: argparse.Namespace, parser: argparse.ArgumentParser) -> dict:
    """The options of `add_solver_scheme_options` as a scheme (None: not given); counts below their least are refused
    through `parser`."""
    scheme = {key: getattr(args, key) for key in SOLVER_SCHEME_FIELDS}
    for error in solver_count_errors(scheme):
        parser.error(error)
    return scheme

"""The number of kernels a compiled XLA program runs in sequence, counted from its optimized HLO.

One kernel is one instruction of a sequentially executed computation that does work: a fusion, a custom call,
or an unfused operation (XLA runs each as one thunk on CPU and one launch on GPU). Instructions that only name
or reshape buffers (parameters, constants, tuples, tuple elements, bitcasts) are free. A `while` counts its body
times its trip count plus its condition one more time; a `conditional` counts its largest branch; a `call`
counts its callee. Computations applied per element (the `to_apply` of a reduce, sort, scatter or map) and the
bodies of fusions are inside their kernel and are not counted. Loops whose trip count XLA did not annotate
(`known_trip_count` in the while's backend_config) count once and are reported as unknown.
"""

from __future__ import annotations

import dataclasses
import re

import jax

FREE_OPCODES = frozenset(
    {"parameter", "constant", "get-tuple-element", "tuple", "bitcast", "opt-barrier", "after-all", "add-dependency"}
)
"""Instructions that launch nothing."""

_COMPUTATION = re.compile(r"^(ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s*=\s*.*?\s([a-z][a-z0-9\-]*)\(")
_TRIP_COUNT = re.compile(r'"known_trip_count":\{"n":"(\d+)"')


@dataclasses.dataclass(frozen=True)
class KernelCount:
    kernels: int
    unknown_trip_loops: int  # while loops counted once because XLA did not annotate their trip count


def _computations(hlo_text: str) -> tuple[dict[str, list[str]], str]:
    """Instruction lines of each computation by name, and the entry computation's name."""
    computations: dict[str, list[str]] = {}
    entry, current = None, None
    for line in hlo_text.splitlines():
        if current is None:
            match = _COMPUTATION.match(line)
            if match and not line.startswith(("HloModule", " ")):
                current = match.group(2)
                computations[current] = []
                if match.group(1):
                    entry = current
        elif line.strip() == "}":
            current = None
        else:
            computations[current].append(line)
    if entry is None:
        raise ValueError("HLO text has no ENTRY computation")
    return computations, entry


def _called(line: str, attribute: str) -> list[str]:
    """Computations named by `attribute=%name` or `attribute={%a, %b}` on an instruction line."""
    listed = re.search(attribute + r"=\{([^}]*)\}", line)
    if listed:
        return [name.strip().lstrip("%") for name in listed.group(1).split(",")]
    single = re.search(attribute + r"=%?([\w.\-]+)", line)
    return [single.group(1)] if single else []


def count_hlo_kernels(hlo_text: str) -> KernelCount:
    """Kernels run in sequence by one execution of the optimized HLO module `hlo_text`."""
    computations, entry = _computations(hlo_text)
    unknown = 0

    def count(name: str) -> int:
        nonlocal unknown
        total = 0
        for line in computations[name]:
            match = _INSTRUCTION.match(line)
            if not match or match.group(1) in FREE_OPCODES:
                continue
            opcode = match.group(1)
            if opcode == "while":
                trip = _TRIP_COUNT.search(line)
                if trip is None:
                    unknown += 1
                trips = int(trip.group(1)) if trip else 1
                total += trips * count(_called(line, "body")[0]) + (trips + 1) * count(_called(line, "condition")[0])
            elif opcode == "conditional":
                branches = _called(line, "branch_computations") or (
                    _called(line, "true_computation") + _called(line, "false_computation")
                )
                total += max(count(branch) for branch in branches)
            elif opcode == "call":
                total += count(_called(line, "to_apply")[0])
            else:
                total += 1
        return total

    return KernelCount(count(entry), unknown)


def count_kernels(function, *args) -> KernelCount:
    """Kernels that one call of `jax.jit(function)(*args)` runs in sequence on the default backend."""
    return count_hlo_kernels(jax.jit(function).lower(*args).compile().as_text())

"""Bitwise-repeatable execution on GPUs.

On a GPU, XLA lowers a scatter-add whose indices repeat to atomic additions, whose order, and so whose float
rounding, changes from run to run; a chaotic rollout then drifts apart within a few hundred steps (measured on an
H100: docs/performance.md). The engine sums each body's impulses in a fixed order instead and repeats
bit for bit without help (measured on an H200). XLA's `--xla_gpu_deterministic_ops` lowers every scatter to ordered
code, which guards the rest of a program too, at a measured 8.4x of the engine's time on a GPU. CPUs are
deterministic without it; the flag is ignored there.
"""

from __future__ import annotations

import os

XLA_FLAGS_ENV = "XLA_FLAGS"
DETERMINISTIC_GPU_OPS_FLAG = "--xla_gpu_deterministic_ops=true"


def with_deterministic_ops(xla_flags: str) -> str:
    """`xla_flags` (an XLA_FLAGS value) with XLA's deterministic GPU ops switched on, other flags kept; a value that
    already sets `--xla_gpu_deterministic_ops` either way is returned unchanged (the user's choice stands)."""
    name = DETERMINISTIC_GPU_OPS_FLAG.split("=")[0]
    if any(flag.split("=")[0] == name for flag in xla_flags.split()):
        return xla_flags
    return f"{xla_flags} {DETERMINISTIC_GPU_OPS_FLAG}".strip()


def use_deterministic_ops() -> None:
    """Make this process's GPU programs bitwise repeatable (`with_deterministic_ops` on its XLA_FLAGS).

    Call it before the process first computes anything with JAX: XLA reads its flags when the backend starts.
    """
    os.environ[XLA_FLAGS_ENV] = with_deterministic_ops(os.environ.get(XLA_FLAGS_ENV, ""))

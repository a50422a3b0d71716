"""Helpers that every test folder shares: the `MEASURED` line a test prints its figures in (the one helper for a
test's figures and timings), and stacking pytrees and bringing them to numpy. The shared rollouts are in
tests/rollouts.py.

Test modules and conftest files import them as `from tests.helpers import ...`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def measured(name: str, **values) -> None:
    """Print a test's figures as one `MEASURED name: key=value, ...` line (floats to 6 significant digits); pytest
    shows them with -s."""
    text = ", ".join(
        f"{key}={value:.6g}" if isinstance(value, float) else f"{key}={value}" for key, value in values.items()
    )
    print(f"\nMEASURED {name}: {text}")


def stack(*trees):
    """One pytree whose leaves stack the leaves of `trees` along a new leading axis."""
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def to_numpy(tree):
    """`tree` with numpy leaves (copied to the host)."""
    return jax.tree.map(np.asarray, tree)

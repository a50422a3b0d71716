"""Helpers that every test folder shares: the `MEASURED` line a test prints its figures in, stacking of pytrees, and
the compiled scan of engine steps that the engine tests' rollouts are made of.

Test modules and conftest files import them as `from tests.helpers import ...`.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from kforge import engine
from kforge.engine import SimState, StaticSimParams, StepInfo


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


def scan_steps(static: StaticSimParams, record: Callable[[SimState, StepInfo], object], masked: bool = False):
    """`run(state, params, motor_actions (K, J), thruster_actions (K, T)[, valid_steps])` -> (final state, per-step
    `record(state after the step, its StepInfo)` stacked over K), a `lax.scan` of `engine.step` to jit or vmap.

    `masked`: steps from `valid_steps` on leave the state as it was, so that one compiled length serves every
    shorter run.
    """

    def run(state, params, motor_actions, thruster_actions, valid_steps=None):
        def body(carry, inputs):
            index, motor, thrust = inputs
            new, info = engine.step(carry, params, motor, thrust, static=static)
            if masked:
                new = jax.tree.map(lambda after, before: jnp.where(index < valid_steps, after, before), new, carry)
            return new, record(new, info)

        return jax.lax.scan(body, state, (jnp.arange(motor_actions.shape[0]), motor_actions, thruster_actions))

    return run

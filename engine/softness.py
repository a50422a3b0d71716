"""Soft constraint coefficients (a mass-spring-damper per constraint, stable at any stiffness)."""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Softness:
    """Velocity bias per unit of position error, and the mass/impulse scales of a soft constraint."""

    bias_rate: jnp.ndarray  # [1/s]
    mass_scale: jnp.ndarray  # [-]
    impulse_scale: jnp.ndarray  # [-]


def make_softness(hertz, damping_ratio, substep) -> Softness:
    """Implicit-Euler spring of frequency `hertz` [Hz] and `damping_ratio` over a substep of `substep` [s]."""
    omega = 2.0 * jnp.pi * hertz
    a1 = 2.0 * damping_ratio + substep * omega
    a2 = substep * omega * a1
    a3 = 1.0 / (1.0 + a2)
    return Softness(bias_rate=omega / a1, mass_scale=a2 * a3, impulse_scale=a3)

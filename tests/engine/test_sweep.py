"""The Gauss-Seidel sweeps, looped and unrolled: the result of visiting the items one by one, no copy per loop step,
and fewer kernels unrolled."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.kernels import count_kernels
from kforge.engine.sweep import SWEEPS, pipelined_sweep

NUM_BODIES = 6
PAIRS = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [0, 5], [1, 4]])
"""Item i pushes body PAIRS[i, 0] against body PAIRS[i, 1]."""
RESPONSE = 0.37  # velocity change per unit impulse (one body)
STIFFNESS = 0.8  # share of the relative velocity an item removes


def _problem(count: int, batch: int = 3):
    key_v, key_i = jax.random.split(jax.random.key(count))
    velocity = tuple(jax.random.normal(k, (NUM_BODIES + 1, batch)) for k in jax.random.split(key_v, 3))
    old = {
        "normal": jax.random.uniform(key_i, (count, batch)),
        "pair": jax.random.normal(jax.random.fold_in(key_i, 1), (count, 2, batch)),
    }
    pairs = jnp.asarray(PAIRS[:count])

    def gather(velocity, i):
        return tuple(jnp.stack([v[pairs[i, 0]], v[pairs[i, 1]]]) for v in velocity)

    def solve(inputs, i, start):
        relative = inputs[0][1] - inputs[0][0] + 0.5 * (inputs[2][1] - inputs[2][0])
        normal = jnp.maximum(start["normal"] - STIFFNESS * relative / (2 * RESPONSE), 0.0)
        pair = start["pair"] * 0.5 + jnp.stack([inputs[1][0], inputs[1][1]]) * (i + 1)
        return {"normal": normal, "pair": pair}

    def apply(velocity, i, change):
        a, b = pairs[i, 0], pairs[i, 1]
        push = RESPONSE * change["normal"]
        vx, vy, w = velocity
        vx = vx.at[a].add(-push).at[b].add(push)
        vy = vy.at[a].add(change["pair"][0]).at[b].add(-change["pair"][1])
        w = w.at[a].add(0.5 * push).at[b].add(0.5 * push)
        return vx, vy, w

    return velocity, old, gather, solve, apply


def _one_by_one(velocity, count, old, gather, solve, apply):
    """Reference: visit each item once, in order, in plain Python."""
    new_items = []
    for i in range(count):
        start = jax.tree.map(lambda x, i=i: x[i], old)
        new = solve(gather(velocity, i), i, start)
        velocity = apply(velocity, i, jax.tree.map(jnp.subtract, new, start))
        new_items.append(new)
    return velocity, jax.tree.map(lambda *xs: jnp.stack(xs), *new_items)


@pytest.mark.parametrize("form", sorted(SWEEPS))
@pytest.mark.parametrize("count", [1, 2, 7])
def test_a_sweep_gives_the_result_of_visiting_the_items_one_by_one(count, form):
    """To rounding: the reference is a different program, which XLA fuses differently."""
    velocity, old, gather, solve, apply = _problem(count)
    sweep = SWEEPS[form]
    swept = jax.jit(lambda v, o: sweep(v, count, o, gather, solve, apply))(velocity, old)
    expected = jax.jit(lambda v, o: _one_by_one(v, count, o, gather, solve, apply))(velocity, old)
    for got, want in zip(jax.tree.leaves(swept), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    assert not np.array_equal(swept[0][0], velocity[0])  # the items acted


@pytest.mark.parametrize("form", sorted(SWEEPS))
def test_an_empty_sweep_returns_its_inputs(form):
    velocity, old, gather, solve, apply = _problem(0)
    swept_velocity, swept_old = SWEEPS[form](velocity, 0, old, gather, solve, apply)
    assert swept_velocity is velocity and swept_old is old


def _loop_bodies(hlo: str) -> list[str]:
    bodies = set(re.findall(r"\bwhile\(.*?body=%?([\w.\-]+)", hlo))
    blocks = re.findall(r"^(?:%?)([\w.\-]+) .*?\{\n(.*?)\n\}", hlo, flags=re.S | re.M)
    return [text for name, text in blocks if name in bodies]


@pytest.mark.parametrize("count", [1, 2, 7])
def test_a_sweep_step_copies_no_impulses(count):
    """Carried impulses are updated in place: a copy per step would be a kernel per step on every backend."""
    velocity, old, gather, solve, apply = _problem(count)
    hlo = jax.jit(lambda v, o: pipelined_sweep(v, count, o, gather, solve, apply)).lower(velocity, old).compile()
    bodies = _loop_bodies(hlo.as_text())
    assert len(bodies) == 1
    copies = re.findall(r"= (\w+)\[[^\]]*\][^=]*? copy\(", bodies[0])
    assert [dtype for dtype in copies if dtype != "s32"] == []  # the loop counter may be copied


def test_an_unrolled_sweep_has_no_loop_and_runs_fewer_kernels_than_a_looped_one():
    """What an accelerator pays for: a looped sweep launches its body's kernels once per item, an unrolled one lets
    XLA fuse across items."""
    velocity, old, gather, solve, apply = _problem(len(PAIRS))
    programs = {
        form: jax.jit(lambda v, o, sweep=sweep: sweep(v, len(PAIRS), o, gather, solve, apply))
        for form, sweep in SWEEPS.items()
    }
    unrolled_hlo = programs["unrolled"].lower(velocity, old).compile().as_text()
    assert _loop_bodies(unrolled_hlo) == [] and "while(" not in unrolled_hlo
    looped, unrolled = (count_kernels(programs[form], velocity, old).kernels for form in ("looped", "unrolled"))
    assert unrolled < looped, (unrolled, looped)

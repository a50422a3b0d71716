"""Kernel counting from optimized HLO: free instructions, loops by trip count, branches, calls."""

import jax
import jax.numpy as jnp

from benchmarks.kernels import count_hlo_kernels, count_kernels

HLO = """HloModule example

%fused_add (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  ROOT %add = f32[4]{0} add(%p, %p)
}

%body (arg: (s32[], f32[4])) -> (s32[], f32[4]) {
  %arg = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%arg), index=0
  %x = f32[4]{0} get-tuple-element(%arg), index=1
  %one = s32[] constant(1)
  %next = s32[] add(%i, %one)
  %y = f32[4]{0} fusion(%x), kind=kLoop, calls=%fused_add
  ROOT %out = (s32[], f32[4]{0}) tuple(%next, %y)
}

%cond (arg: (s32[], f32[4])) -> pred[] {
  %arg = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%arg), index=0
  %n = s32[] constant(5)
  ROOT %lt = pred[] compare(%i, %n), direction=LT
}

%big (x: f32[4]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %a = f32[4]{0} sine(%x)
  %b = f32[4]{0} cosine(%a)
  ROOT %c = f32[4]{0} fusion(%b), kind=kLoop, calls=%fused_add
}

%small (x: f32[4]) -> f32[4] {
  ROOT %x = f32[4]{0} parameter(0)
}

ENTRY %main (x: f32[4], p: pred[]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %p = pred[] parameter(1)
  %zero = s32[] constant(0)
  %init = (s32[], f32[4]{0}) tuple(%zero, %x)
  %loop = (s32[], f32[4]{0}) while(%init), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"5"}}
  %y = f32[4]{0} get-tuple-element(%loop), index=1
  %z = f32[4]{0} conditional(%p, %y, %y), true_computation=%big, false_computation=%small
  ROOT %w = f32[4]{0} call(%z), to_apply=%small
}
"""


def test_loops_count_by_trip_count_and_branches_by_the_largest():
    # while: 5 x (add + fusion) + 6 x compare; conditional: 3 (sine, cosine, fusion); call: 0 (a parameter).
    assert count_hlo_kernels(HLO).kernels == 5 * 2 + 6 * 1 + 3
    assert count_hlo_kernels(HLO).unknown_trip_loops == 0


def test_a_loop_without_a_known_trip_count_is_reported():
    unannotated = HLO.replace(', backend_config={"known_trip_count":{"n":"5"}}', "")
    assert count_hlo_kernels(unannotated).unknown_trip_loops == 1
    assert count_hlo_kernels(unannotated).kernels == 2 + 2 + 3


def test_a_compiled_scan_counts_its_body_once_per_step():
    def scanned(length):
        return lambda x: jax.lax.scan(lambda c, _: (jnp.sin(c) @ c, None), x, None, length=length)[0]

    x = jnp.ones((8, 8))
    short, long = count_kernels(scanned(4), x), count_kernels(scanned(12), x)
    assert short.unknown_trip_loops == long.unknown_trip_loops == 0
    assert long.kernels - short.kernels >= 8 and (long.kernels - short.kernels) % 8 == 0

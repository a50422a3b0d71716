"""Predictive coding of per-step state (`pipeline.storage.state_codec`): bit-exact round trips on any values and done
flags, empty slots decoding to the fill value, and residuals that are small where physics makes them small."""

from __future__ import annotations

import numcodecs
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from kforge.env import ActionType, StaticEnvParams
from kforge.pipeline.storage.layout import DONE, VALID, FieldSpec, make_layout
from kforge.pipeline.storage.state_codec import decode, decode_arrays, encode, encode_arrays, is_coded, stored_dtype

pytestmark = pytest.mark.smoke

FLOAT_FIELD = FieldSpec("env_state/sim/bodies/position", (3, 2), "float32", True)
INT_FIELD = FieldSpec("env_state/sim/contacts/feature", (2,), "int32", True)
NUM_STEPS = 32

GRAVITY = 9.81  # [m/s^2]
DT = 1 / 30  # [s] one env step: two physics steps of 1/60 s
LOW_BYTES = 2  # a smoothly moving body's residuals fit in this many low bytes


def _bits(values: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(values).view(np.uint32)


@st.composite
def trajectories(draw, spec: FieldSpec):
    """(values, done) with arbitrary bit patterns (NaN payloads, +-0, inf, subnormals) and arbitrary episode ends."""
    batch = draw(st.integers(1, 3))
    words = draw(hnp.arrays(np.uint32, (batch, NUM_STEPS) + spec.shape, elements=st.integers(0, 2**32 - 1)))
    done = draw(hnp.arrays(np.bool_, (batch, NUM_STEPS)))
    return words.view(np.float32 if spec.dtype == "float32" else np.int32), done


@settings(max_examples=200, deadline=None)
@given(trajectories(FLOAT_FIELD))
def test_float_fields_round_trip_bit_for_bit(case):
    values, done = case
    stored = encode(FLOAT_FIELD, values, done)
    assert stored.dtype == np.uint32 and stored.shape == values.shape
    np.testing.assert_array_equal(_bits(decode(FLOAT_FIELD, stored, done)), _bits(values))


@settings(max_examples=100, deadline=None)
@given(trajectories(INT_FIELD))
def test_int_fields_round_trip_exactly(case):
    values, done = case
    decoded = decode(INT_FIELD, encode(INT_FIELD, values, done), done)
    assert decoded.dtype == np.int32
    np.testing.assert_array_equal(decoded, values)


def test_special_floats_round_trip():
    specials = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-45, -1e-45, 3.4e38, -3.4e38], np.float32)
    values = np.resize(specials, (1, NUM_STEPS, 3, 2)).astype(np.float32)
    values.view(np.uint32)[0, 3, 0, 0] = 0xFFC00001  # a negative NaN with a payload
    done = np.zeros((1, NUM_STEPS), bool)
    done[0, ::5] = True
    np.testing.assert_array_equal(_bits(decode(FLOAT_FIELD, encode(FLOAT_FIELD, values, done), done)), _bits(values))


def test_stored_words_are_the_documented_residuals():
    """The on-disk format, worked by hand from the module docstring (a change here breaks every stored dataset)."""
    spec = FieldSpec("env_state/last_distance", (), "float32", True)
    values = np.array([[0x3F800000, 0x3F800001, 0x80000000, 0x00000000]], np.uint32).view(np.float32)  # 1, 1+ulp, -0, 0
    done = np.array([[False, True, False, False]])  # step 2 starts an episode: predicted by step 0
    # image(1.0) = 0x3F800000 -> zigzag 2 x; +1 ulp -> 2; image(-0.0) = -1, -1 - 0x3F800000 -> 2 x 0x3F800001 - 1;
    # image(0.0) - image(-0.0) = 1 -> 2
    expected = np.array([[0x7F000000, 2, 0x7F000001, 2]], np.uint32)
    np.testing.assert_array_equal(encode(spec, values, done), expected)
    np.testing.assert_array_equal(_bits(decode(spec, expected, done)), _bits(values))
    ints = FieldSpec("env_state/timestep", (), "int32", True)
    counts = np.array([[5, -3, 7, 7]], np.int32)  # residuals 5, -8, 10, 0 -> zigzag 10, 15, 20, 0
    no_done = np.zeros((1, 4), bool)
    np.testing.assert_array_equal(encode(ints, counts, no_done), np.array([[10, 15, 20, 0]], np.uint32))
    np.testing.assert_array_equal(decode(ints, np.array([[10, 15, 20, 0]], np.uint32), no_done), counts)


@pytest.mark.parametrize(("batch", "shape"), [(0, (3, 2)), (2, (0, 2)), (0, ())])
def test_empty_batches_and_zero_size_fields_round_trip(batch, shape):
    spec = FieldSpec("env_state/sim/joints/motor_impulse", shape, "float32", True)  # (0,): a size without joints
    values = np.full((batch, NUM_STEPS) + shape, 1.5, np.float32)
    done = np.zeros((batch, NUM_STEPS), bool)
    decoded = decode(spec, encode(spec, values, done), done)
    assert decoded.shape == values.shape and decoded.dtype == np.float32 and (decoded == 1.5).all()


def test_empty_slots_store_zeros_and_read_as_the_fill_value():
    """A slot not kept is all zeros on disk (the zarr fill value: no chunk is written) and reads as NaN / -1."""
    layout = make_layout(StaticEnvParams.for_size("s"), ActionType.MULTI_DISCRETE, NUM_STEPS)
    rng = np.random.default_rng(0)
    valid = np.array([True, False, True])
    done = rng.random((3, NUM_STEPS)) < 0.1
    position = rng.normal(size=(3, NUM_STEPS, 7, 2)).astype(np.float32)
    feature = rng.integers(-1, 9, size=(3, NUM_STEPS, 15, 2)).astype(np.int32)
    names = ("env_state/sim/bodies/position", "env_state/sim/contacts/feature")
    arrays = dict(zip(names, (position, feature), strict=True)) | {DONE: done, VALID: valid}
    stored = encode_arrays(layout, arrays)
    assert all(stored[name].dtype == np.uint32 and not stored[name][1].any() for name in names)
    decoded = decode_arrays(layout, {name: stored[name] for name in names}, done, valid)
    assert np.isnan(decoded[names[0]][1]).all() and (decoded[names[1]][1] == -1).all()
    np.testing.assert_array_equal(_bits(decoded[names[0]][valid]), _bits(position[valid]))
    np.testing.assert_array_equal(decoded[names[1]][valid], feature[valid])
    assert decoded[names[0]].dtype == np.float32 and decoded[names[1]].dtype == np.int32


def test_coding_needs_the_done_and_valid_flags():
    layout = make_layout(StaticEnvParams.for_size("s"), ActionType.MULTI_DISCRETE, NUM_STEPS)
    position = np.zeros((1, NUM_STEPS, 7, 2), np.float32)
    with pytest.raises(ValueError, match="'meta/valid'"):
        encode_arrays(layout, {"env_state/sim/bodies/position": position, DONE: np.zeros((1, NUM_STEPS), bool)})


def test_a_field_at_rest_stores_only_zeros():
    """A static body's constant 0.0 velocity is all-zero residuals, from the first step on."""
    values = np.zeros((1, NUM_STEPS, 3, 2), np.float32)
    assert not encode(FLOAT_FIELD, values, np.zeros((1, NUM_STEPS), bool)).any()


def _projectile(num_episodes_end: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Three bodies thrown from fixed starts under gravity, restarted from their start after each done step."""
    starts = np.array([[0.5, 1.0], [2.0, 3.0], [-1.5, 0.25]])
    speeds = np.array([[1.0, 2.0], [-0.5, 0.0], [0.3, 4.0]])
    done = np.zeros((1, NUM_STEPS), bool)
    done[0, num_episodes_end] = True
    values = np.zeros((1, NUM_STEPS, 3, 2), np.float32)
    since_reset = 0
    for t in range(NUM_STEPS):
        time = since_reset * DT
        values[0, t] = starts + speeds * time + np.array([0.0, -0.5 * GRAVITY * time**2])
        since_reset = 0 if done[0, t] else since_reset + 1
    return values, done


def test_smooth_motion_leaves_only_low_bytes_and_resets_cost_nothing():
    values, done = _projectile([10, 21])
    stored = encode(FLOAT_FIELD, values, done)
    moving = stored[0, 1:]
    assert (moving < 2 ** (8 * LOW_BYTES + 8)).mean() > 0.9  # consecutive positions differ in low mantissa bits
    assert not stored[0, 11].any() and not stored[0, 22].any()  # an episode restarts at the window's first state
    raw = len(numcodecs.Blosc(cname="zstd", clevel=1, shuffle=numcodecs.Blosc.SHUFFLE).encode(values))
    coded = len(numcodecs.Blosc(cname="zstd", clevel=1, shuffle=numcodecs.Blosc.SHUFFLE).encode(stored))
    assert coded < raw


@pytest.mark.parametrize(
    ("spec", "coded"),
    [
        (FLOAT_FIELD, True),
        (INT_FIELD, True),
        (FieldSpec("env_state/sim/bodies/inverse_mass", (3,), "float32", False), False),  # static: stored once
        (FieldSpec("action", (6,), "int32", True), False),  # not state
        (FieldSpec("done", (), "bool", True), False),
    ],
)
def test_which_fields_are_coded(spec, coded):
    assert is_coded(spec) is coded
    assert stored_dtype(spec) == ("uint32" if coded else spec.dtype)

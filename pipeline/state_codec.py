"""Lossless predictive coding of the per-step state: what the dataset stores instead of the raw state values.

Each per-step state field is stored as the residual of its values against a prediction made from the trajectory's
earlier steps, on the integer images of the float bit patterns, so that zstd after Blosc's byte shuffle finds mostly
zero high bytes:

    image(x)       float32 bits read as an int32 and made monotonic (negative floats get their 31 low bits flipped);
                   int32 values as they are
    prediction(t)  image(x[t - 1]) within an episode; image(x[0]) at an episode's first step (every episode of a
                   window restarts the same level, so its first state equals the window's first state); 0 at t = 0
    stored(t)      zigzag(image(x[t]) - prediction(t)) as uint32, wrapping modulo 2^32

Only integer arithmetic is involved, so decoding is exact on every platform. Episode starts come from the stored
`done` flags. A slot not kept stores zeros (the zarr fill value: nothing is written) and decodes, through its
`meta/valid` flag, to the field's fill value: empty slots read as NaN / -1 as they do without coding.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from pipeline.layout import DONE, VALID, FieldSpec, Layout

STORED_DTYPE = "uint32"
"""dtype of a coded field on disk."""

CODED_DTYPES = ("float32", "int32")
"""Per-step state fields of these dtypes are coded; any other field is stored as it is."""

_LOW_BITS = np.int64(0x7FFFFFFF)
_HALF_WORD = 1 << 31


def is_coded(spec: FieldSpec) -> bool:
    """Whether `spec` is stored as prediction residuals."""
    return spec.per_step and spec.dtype in CODED_DTYPES and spec.name.startswith("env_state/")


def stored_dtype(spec: FieldSpec) -> str:
    """The dtype `spec`'s array has on disk."""
    return STORED_DTYPE if is_coded(spec) else spec.dtype


def _image(values: np.ndarray, spec: FieldSpec) -> np.ndarray:
    """int64 image of float32 bit patterns (order-preserving, one-to-one onto int32) or of int32 values."""
    signed = np.ascontiguousarray(values, spec.dtype).view(np.int32).astype(np.int64)
    if spec.dtype == "float32":
        return np.where(signed < 0, signed ^ _LOW_BITS, signed)
    return signed


def _wrap(x: np.ndarray) -> np.ndarray:
    """int64 values modulo 2^32, into [-2^31, 2^31)."""
    return (x + _HALF_WORD) % (2 * _HALF_WORD) - _HALF_WORD


def _from_image(image: np.ndarray, spec: FieldSpec) -> np.ndarray:
    signed = _wrap(image).astype(np.int32)
    if spec.dtype == "float32":
        signed = np.where(signed < 0, signed ^ np.int32(_LOW_BITS), signed).astype(np.int32)
        return signed.view(np.float32)
    return signed


def _episode_starts(done: np.ndarray) -> np.ndarray:
    """(B, T) bool: step t begins an episode after an earlier one ended (done at t - 1); never at t = 0."""
    starts = np.zeros(done.shape, bool)
    starts[:, 1:] = done[:, :-1]
    return starts


def _expand(mask: np.ndarray, ndim: int) -> np.ndarray:
    return mask.reshape(mask.shape + (1,) * (ndim - mask.ndim))


def _predictions(image: np.ndarray, starts: np.ndarray) -> np.ndarray:
    previous = np.concatenate([np.zeros_like(image[:, :1]), image[:, :-1]], axis=1)
    return np.where(_expand(starts, image.ndim), image[:, :1], previous)


def encode(spec: FieldSpec, values: np.ndarray, done: np.ndarray) -> np.ndarray:
    """Stored residuals (uint32, shape of `values`) of a coded field's trajectories (B, T, ...) given their done."""
    image = _image(values, spec)
    residual = _wrap(image - _predictions(image, _episode_starts(done)))
    return ((residual << 1) ^ (residual >> 63)).astype(np.uint32)


def decode(spec: FieldSpec, stored: np.ndarray, done: np.ndarray) -> np.ndarray:
    """Values of `spec`'s dtype from stored residuals (B, T, ...) and the trajectories' done (inverse of encode)."""
    zigzag = np.asarray(stored, np.uint32).astype(np.int64)
    residual = (zigzag >> 1) ^ -(zigzag & 1)
    starts = _expand(_episode_starts(done), residual.ndim)
    # Image at t of an episode starting at s: image[0] + (total[t] - total[s - 1]) when s > 0, total[t] for the
    # first episode, where total is the running sum of residuals (so image[0] = total[0]).
    total = np.cumsum(residual, axis=1)
    step = np.arange(residual.shape[1]).reshape((1, -1) + (1,) * (residual.ndim - 2))
    start = np.maximum.accumulate(np.where(starts, step, 0), axis=1)
    before_start = np.take_along_axis(total, np.maximum(start - 1, 0), axis=1)
    base = np.where(start > 0, total[:, :1] - before_start, 0)
    return _from_image(base + total, spec)


def encode_arrays(layout: Layout, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`arrays` (field name -> (B, ...) values of B slots) with the coded fields encoded; a coded field needs the
    slots' `done` and `meta/valid` among `arrays`."""
    coded = [name for name in arrays if is_coded(layout.field(name))]
    missing = [name for name in (DONE, VALID) if coded and name not in arrays]
    if missing:
        raise ValueError(f"coding {coded[0]} needs the {missing[0]!r} values of the same slots")
    stored = dict(arrays)
    for name in coded:
        value = encode(layout.field(name), arrays[name], arrays[DONE])
        stored[name] = np.where(_expand(arrays[VALID], value.ndim), value, 0).astype(STORED_DTYPE)
    return stored


def decode_arrays(
    layout: Layout, stored: Mapping[str, np.ndarray], done: np.ndarray, valid: np.ndarray
) -> dict[str, np.ndarray]:
    """Inverse of `encode_arrays`, given the slots' done and valid flags: slots not valid read as the fill value."""
    arrays = dict(stored)
    for name, value in stored.items():
        spec = layout.field(name)
        if is_coded(spec):
            arrays[name] = np.where(_expand(valid, value.ndim), decode(spec, value, done), spec.fill_value)
            arrays[name] = arrays[name].astype(spec.dtype)
    return arrays

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

from kforge.pipeline.storage.layout import DONE, VALID, FieldSpec, Layout

STORED_DTYPE = "uint32"
"""dtype of a coded field on disk."""

CODED_DTYPES = ("float32", "int32")
"""Per-step state fields of these dtypes are coded; any other field is stored as it is."""

_SIGN_SHIFT = np.uint32(31)
_LOW_BITS = np.uint32(0x7FFFFFFF)


def is_coded(spec: FieldSpec) -> bool:
    """Whether `spec` is stored as prediction residuals."""
    return spec.per_step and spec.dtype in CODED_DTYPES and spec.name.startswith("env_state/")


def stored_dtype(spec: FieldSpec) -> str:
    """The dtype `spec`'s array has on disk."""
    return STORED_DTYPE if is_coded(spec) else spec.dtype


# All arithmetic below is on uint32, which wraps modulo 2^32: an int32 image and its two's-complement bits are the
# same word, so differences, sums and zigzags need no wider type.


def _image(values: np.ndarray, spec: FieldSpec) -> np.ndarray:
    """uint32 words of the order-preserving image of float32 bit patterns (negative floats get their 31 low bits
    flipped), or of int32 values as they are."""
    bits = np.ascontiguousarray(values, spec.dtype).view(np.uint32)
    if spec.dtype == "float32":
        return bits ^ ((bits >> _SIGN_SHIFT) * _LOW_BITS)
    return bits


def _from_image(image: np.ndarray, spec: FieldSpec) -> np.ndarray:
    bits = image ^ ((image >> _SIGN_SHIFT) * _LOW_BITS) if spec.dtype == "float32" else image
    return np.ascontiguousarray(bits, np.uint32).view(spec.dtype)


def _zigzag(residual: np.ndarray) -> np.ndarray:
    """Signed residuals (as uint32 words) to small unsigned ones: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return (residual << np.uint32(1)) ^ (np.uint32(0) - (residual >> _SIGN_SHIFT))


def _unzigzag(stored: np.ndarray) -> np.ndarray:
    return (stored >> np.uint32(1)) ^ (np.uint32(0) - (stored & np.uint32(1)))


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
    return _zigzag(image - _predictions(image, _episode_starts(done)))


class _Episodes:
    """Where each step's episode began, from the trajectories' (B, T) done flags (shared by every field)."""

    def __init__(self, done: np.ndarray):
        batch, steps = done.shape
        step = np.arange(steps)
        start = np.maximum.accumulate(np.where(_episode_starts(done), step, 0), axis=1)
        self.shape = done.shape
        self.later = start > 0  # the step's episode began after t = 0
        self.row_before_start = (np.arange(batch)[:, None] * steps + np.maximum(start - 1, 0)).reshape(-1)


def _decode(spec: FieldSpec, stored: np.ndarray, episodes: _Episodes) -> np.ndarray:
    # Image at t of an episode starting at s: image[0] + (total[t] - total[s - 1]) when s > 0, total[t] for the
    # first episode, where total is the running sum of residuals (so image[0] = total[0]).
    total = np.cumsum(_unzigzag(np.asarray(stored, np.uint32)), axis=1, dtype=np.uint32)
    rows = total.reshape((episodes.shape[0] * episodes.shape[1],) + total.shape[2:])
    before_start = rows[episodes.row_before_start].reshape(total.shape)
    later = _expand(episodes.later, total.ndim)
    return _from_image(np.where(later, total[:, :1] - before_start + total, total), spec)


def decode(spec: FieldSpec, stored: np.ndarray, done: np.ndarray) -> np.ndarray:
    """Values of `spec`'s dtype from stored residuals (B, T, ...) and the trajectories' done (inverse of encode)."""
    return _decode(spec, stored, _Episodes(np.asarray(done, bool)))


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
    episodes, valid = _Episodes(np.asarray(done, bool)), np.asarray(valid, bool)
    for name, value in stored.items():
        spec = layout.field(name)
        if is_coded(spec):
            decoded = _decode(spec, value, episodes)
            if not valid.all():
                decoded = np.where(_expand(valid, value.ndim), decoded, spec.fill_value).astype(spec.dtype, copy=False)
            arrays[name] = decoded
    return arrays

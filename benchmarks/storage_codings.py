"""How far the stored per-step state is from what lossless coding can reach, measured on an existing dataset.

Reads every kept trajectory of a dataset written by `kforge run` and prints bytes per stored transition of its
per-step state (the bulk of a dataset) under lossless variants, each field compressed one trajectory at a time
as the shard files do (payload only: no chunk index, checksum or per-level fields):

    raw values             the float / int values as they are, Blosc-zstd 5 with byte shuffle
    order-1 (stored)       the dataset's coding (pipeline.storage.state_codec): residuals against the previous step
    order-1, zstd 9        the same residuals at Blosc's highest zstd level
    order-1, bitshuffle    the same residuals with Blosc's bit shuffle
    order-1, xz            the same residuals byte-shuffled, then LZMA preset 9 (slow; a bound, not an option)
    order-2                residuals of the residuals (linear extrapolation from the two previous steps)
    best of 1 / 2          per feature time series, whichever of order 1 and order 2 is smaller
    order-1, batch chunk   a level batch's kept trajectories in one chunk instead of one each

and the share of the per-step state taken by the solver's warm-start caches (contact and joint impulses, contact
feature ids), which no observation reads but a bit-exact restart needs. `--json` prints one JSON document.

    python -m benchmarks.storage_codings outputs/1M-s-tiny
"""

from __future__ import annotations

import argparse
import json
import lzma
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numcodecs import Blosc

from kforge.pipeline.storage import DATA_DIR, DONE, VALID, open_dataset
from kforge.pipeline.storage.shard_store import BLOSC_LEVEL
from kforge.pipeline.storage.state_codec import encode, is_coded


def _blosc(level: int = BLOSC_LEVEL, shuffle: int = Blosc.SHUFFLE) -> Callable[[np.ndarray], int]:
    codec = Blosc(cname="zstd", clevel=level, shuffle=shuffle)
    return lambda array: len(codec.encode(array))


def _xz(array: np.ndarray) -> int:
    shuffled = np.ascontiguousarray(array.view(np.uint8).reshape(-1, array.itemsize).T)
    return len(lzma.compress(shuffled.tobytes(), preset=9))


def _time_last(trajectory: np.ndarray) -> np.ndarray:
    """(T, ...) -> (..., T): each feature's time series contiguous, as the shard files store it."""
    return np.ascontiguousarray(np.moveaxis(trajectory, 0, -1))


def _order_two(stored: np.ndarray, done: np.ndarray) -> np.ndarray:
    """Zigzagged differences of consecutive order-1 residuals inside an episode (decodable: order 1 is their
    running sum), the order-1 residual at the first two steps of every episode."""
    zigzag = stored.astype(np.int64)
    residual = (zigzag >> 1) ^ -(zigzag & 1)
    starts = np.zeros(done.shape, bool)
    starts[:, 0] = True
    starts[:, 1:] = done[:, :-1]
    fresh = starts.copy()
    fresh[:, 1:] |= starts[:, :-1]
    fresh = fresh.reshape(fresh.shape + (1,) * (stored.ndim - 2))
    previous = np.concatenate([np.zeros_like(residual[:, :1]), residual[:, :-1]], axis=1)
    second = np.where(fresh, residual, residual - previous)
    second = (second + (1 << 31)) % (1 << 32) - (1 << 31)
    return ((second << 1) ^ (second >> 63)).astype(np.uint32)


def _best_series(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Per (trajectory, feature) time series, the one of two residual arrays with fewer significant bits."""
    cost = [np.log2(x.astype(np.float64) + 1.0).sum(axis=1, keepdims=True) for x in (first, second)]
    return np.where(cost[1] < cost[0], second, first)


def measure(root: Path) -> dict:
    dataset = open_dataset(root)
    layout = dataset.layout
    valid = dataset.read([VALID], range(dataset.geometry.num_slots))[VALID]
    kept = np.flatnonzero(valid)
    if not len(kept):
        raise SystemExit(f"{root}: no kept trajectory to measure")
    coded = [spec for spec in layout.fields if is_coded(spec)]
    data = dataset.read([DONE, VALID] + [spec.name for spec in coded], kept)
    done = data[DONE]
    transitions = len(kept) * layout.num_steps
    batch_of = kept // dataset.geometry.levels_per_batch

    per_trajectory = {
        "raw values": (_blosc(), "values"),
        "order-1 (stored)": (_blosc(), "order1"),
        "order-1, zstd 9": (_blosc(9), "order1"),
        "order-1, bitshuffle": (_blosc(shuffle=Blosc.BITSHUFFLE), "order1"),
        "order-1, xz": (_xz, "order1"),
        "order-2": (_blosc(), "order2"),
        "best of 1 / 2": (_blosc(), "best"),
    }
    totals = {name: 0 for name in per_trajectory} | {"order-1, batch chunk": 0}
    by_field, caches = {}, 0
    for spec in coded:
        values = np.ascontiguousarray(data[spec.name])
        order1 = encode(spec, values, done)
        order2 = _order_two(order1, done)
        forms = {"values": values, "order1": order1, "order2": order2, "best": _best_series(order1, order2)}
        for name, (size, form) in per_trajectory.items():
            nbytes = sum(size(_time_last(trajectory)) for trajectory in forms[form])
            totals[name] += nbytes
            if name == "order-1 (stored)":
                by_field[spec.name] = nbytes / transitions
                caches += nbytes if spec.is_solver_cache else 0
        size = _blosc()
        for batch in np.unique(batch_of):
            chunk = order1[batch_of == batch]
            totals["order-1, batch chunk"] += size(np.ascontiguousarray(np.moveaxis(chunk, 1, -1)))
    shard_bytes = sum(
        path.stat().st_size for path in (root / DATA_DIR).rglob("*") if path.is_file() and path.name != "zarr.json"
    )
    stored = totals["order-1 (stored)"]
    return {
        "dataset": str(root),
        "kept_trajectories": int(len(kept)),
        "shard_bytes_per_transition": shard_bytes / transitions,
        "per_step_state_bytes_per_transition": {name: total / transitions for name, total in totals.items()},
        "relative_to_stored": {name: total / stored for name, total in totals.items()},
        "solver_cache_share": caches / stored,
        "shard_bytes_per_transition_without_solver_caches": (shard_bytes - caches) / transitions,
        "largest_fields": dict(sorted(by_field.items(), key=lambda item: -item[1])[:8]),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path, help="a dataset directory written by kforge run")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    report = measure(args.dataset)
    if args.json:
        print(json.dumps(report, indent=1))
        return
    print(
        f"{report['dataset']}: {report['kept_trajectories']} kept trajectories, "
        f"{report['shard_bytes_per_transition']:.1f} B of shard files per transition"
    )
    print("per-step state payload, B per transition (ratio to the stored coding):")
    for name, value in report["per_step_state_bytes_per_transition"].items():
        print(f"  {name:22s} {value:7.2f}  ({report['relative_to_stored'][name]:.3f})")
    print(
        f"solver warm-start caches: {100 * report['solver_cache_share']:.0f} % of the stored per-step state; "
        f"shard files without them {report['shard_bytes_per_transition_without_solver_caches']:.1f} B per transition"
    )
    print("largest fields (stored coding, B per transition):")
    for name, value in report["largest_fields"].items():
        print(f"  {value:6.2f}  {name}")


if __name__ == "__main__":
    main()

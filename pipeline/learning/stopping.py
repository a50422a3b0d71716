"""When a BC run has trained enough: its validation loss has reached a plateau, and the curve that shows it.

The rule is early stopping with patience: a validation improves on the run when its loss is below the best loss so far
by at least `min_improvement`; the run stops at the `patience`-th validation in a row that does not. Both the rule and
the curve are functions of the recorded metrics lines, so a resumed run decides as the uninterrupted one would.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

CURVE_FILE = "curve.json"
"""The run's loss curve (train and validation per validation step), gradient steps and why it stopped."""


@dataclasses.dataclass(frozen=True)
class Plateau:
    """Where a validation-loss sequence stands under the patience rule."""

    best_index: int | None  # validation holding the best loss so far (the last improvement); None before any
    stop_index: int | None  # validation at which the rule stops the run; None while it goes on
    since_improvement: int  # [validations] in a row without an improvement after `best_index`


def plateau(losses: list[float], patience: int, min_improvement: float) -> Plateau:
    """The patience rule over validation losses in order; `patience` 0 never stops. The sequence is read up to the
    stop, so losses recorded after it change nothing."""
    best, best_index, waited = float("inf"), None, 0
    for index, loss in enumerate(losses):
        if loss < best - min_improvement:
            best, best_index, waited = loss, index, 0
            continue
        waited += 1
        if patience and waited >= patience:
            return Plateau(best_index, index, waited)
    return Plateau(best_index, None, waited)


def loss_curve(lines: list[dict], patience: int, min_improvement: float) -> dict:
    """The curve of a run's metrics lines (`{"step", "train", "validation"}` each): gradient steps, train and
    validation losses per validation step, the best validation and, once the rule stops the run, the plateau."""
    validated = [line for line in lines if line["validation"] is not None]
    state = plateau([line["validation"]["loss"] for line in validated], patience, min_improvement)
    best = None if state.best_index is None else validated[state.best_index]
    return {
        "gradient_steps": lines[-1]["step"] if lines else 0,
        "steps": [line["step"] for line in lines],
        "train_loss": [None if line["train"] is None else line["train"]["loss"] for line in lines],
        "validation_loss": [None if line["validation"] is None else line["validation"]["loss"] for line in lines],
        "best_step": None if best is None else best["step"],
        "best_validation_loss": None if best is None else best["validation"]["loss"],
        "plateau_step": None if state.stop_index is None else validated[state.stop_index]["step"],
        "patience": patience,
        "min_improvement": min_improvement,
    }


def write_curve(run_dir: str | os.PathLike, curve: dict) -> Path:
    """Write `curve` as <run>/curve.json (written whole and renamed: a reader never sees half a file)."""
    path = Path(run_dir) / CURVE_FILE
    partial = path.with_suffix(".partial")
    partial.write_text(json.dumps(curve, indent=1))
    os.replace(partial, path)
    return path

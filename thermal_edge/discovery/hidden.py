"""Hidden effects for the simulator: a plant that has catalogue effects the model lacks.

``thermal-edge simulate --effect NAME[:TARGET][=PARAM=VALUE,...]`` builds the plant from the
model document with each effect added on top of whatever the model already has (a plant with
extra ``copper_temperature`` heats its winding more with temperature than the model says).
Unset parameters take the effect's default magnitude (:mod:`.effects`), raised where needed
until the plant differs from the model by at least 1 K RMS on some sensor over the cycle (a
visible gap); reference speed and current are taken from the run's inputs (the cycle).
Where even the largest magnitude the parameter's bounds allow cannot open that gap (an extra
resistance on a joint with a parallel path, seen by no sensor), the plant stays below it:
:func:`sensor_gap` measures what the sensors can see of a hidden effect.
"""
from __future__ import annotations

import copy
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Run
from ..lptn import Model, ModelError
from ..lptn.loader import build_model, read_yaml
from ..sim.plant import simulate_plant
from . import effects as E

MIN_GAP_K = 1.0  # K: the smallest gap (RMS, some sensor) a default magnitude must open


def read_document(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The raw YAML mapping of a model file (errors name the file, as the loader's do)."""
    raw = read_yaml(path, ModelError)
    if not isinstance(raw, dict):
        raise ModelError(f"{Path(path).name}: (top): expected a mapping of model sections")
    return raw


def builder(path: str | os.PathLike[str] | None,
            data_dir: str | os.PathLike[str] | None = None) -> Callable[[dict[str, Any]], Model]:
    """A ``build(raw) -> Model`` closure that resolves table files as the original file would."""
    p = Path(path) if path is not None else None
    fname = p.name if p is not None else "<model>"

    def build(raw: dict[str, Any]) -> Model:
        return build_model(copy.deepcopy(raw), fname=fname, path=p, data_dir=data_dir)

    return build


def plant_document(raw: Mapping[str, Any], specs: Sequence[str], refs: Mapping[str, float],
                   build: Callable[[dict[str, Any]], Model],
                   inputs: Run | None = None, min_gap_k: float = MIN_GAP_K,
                   ) -> tuple[dict[str, Any], list[tuple[E.Candidate, dict[str, float]]]]:
    """The model document with the ``--effect`` specs added; also the resolved (candidate, values).

    With ``inputs`` (the cycle's run), an effect whose primary parameters were not given gets
    its default magnitude raised (doubled, up to 8 times, within the parameter's bounds) until
    the plant differs from the model by at least ``min_gap_k`` RMS on some sensor over the run.
    """
    model = build(dict(raw))
    ctx = E.context(raw, model, refs, build)
    resolved = []
    base = None
    for spec in specs:
        cand, values = E.hidden_candidate(ctx, spec)
        given = E.parse_spec(spec)[2]
        free = [p for p in cand.effect.params if p.primary and p.short not in given]
        if inputs is not None and free and min_gap_k > 0:
            if base is None:
                base = _sensor_series(model, inputs)
            sc = E.scale(ctx, cand)
            for _ in range(9):
                doc, _, _ = E.augment(raw, [(cand, values)], refs, build, model=model)
                gap = _max_rms(base, _sensor_series(build(doc), inputs))
                if gap >= min_gap_k or any(values[p.short] * 2 > p.upper * sc for p in free):
                    break
                for p in free:
                    values[p.short] *= 2.0
        resolved.append((cand, values))
    doc, _, _ = E.augment(raw, resolved, refs, build, model=model)
    return doc, resolved


def sensor_gap(model: Model, plant: Model, inputs: Run) -> float:
    """What the sensors can see of the plant's hidden effects: the largest RMS difference (K)
    between plant and model over the run, on any sensor of the model, without sensor noise."""
    return _max_rms(_sensor_series(model, inputs), _sensor_series(plant, inputs))


def _sensor_series(model: Model, inputs: Run) -> dict[str, np.ndarray]:
    res = simulate_plant(model, inputs, noise_k=0.0, resolution_k=0.0)
    return {s: res.run.columns[s] for s in model.sensors}


def _max_rms(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> float:
    return max(float(np.sqrt(np.mean((a[s] - b[s]) ** 2))) for s in a if s in b)


def describe(resolved: Sequence[tuple[E.Candidate, Mapping[str, float]]], refs: Mapping[str, float]) -> str:
    """One line naming the hidden effects and their values (for the run file's header)."""
    parts = []
    for cand, vals in resolved:
        parts.append(cand.label + "=" + ",".join(f"{k}={v:g}" for k, v in vals.items()))
    return f"hidden effects: {'; '.join(parts) or 'none'} (n_ref {refs['n_ref']:g} rpm, i_ref {refs['i_ref']:g} A)"

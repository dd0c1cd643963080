"""The shipped GAPS models (T-shirt, dress, skirt) reproduce the figures recorded in their JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from draping.body import AnnyBody
from draping.gaps import Case, drape_case, frame_metrics, load_model, shipped_model_path


@pytest.mark.parametrize("name", ["tshirt", "dress", "skirt"])
def test_shipped_model_reproduces_its_record(name):
    """The 20-frame check case (walk, held-out shape): eps_e, eps_a, eps_c within 0.05
    percentage points of the recorded means (float32 inference; the record was computed by the
    same code from the same file, so only summation order and BLAS kernels differ)."""
    path = shipped_model_path(name)
    assert path.is_file(), f"{path.name} is not shipped in draping/data"
    torch.set_num_threads(1)
    rec = json.loads(path.with_suffix(".json").read_text())
    model = load_model(name)
    assert model.garment_name == name
    assert path.stat().st_size < 8e6
    total = rec.get("total_training", rec["training"])
    assert total["cpu_minutes"] <= 60.0  # one thread; wall minutes are recorded beside it
    c = rec["check"]["case"]
    case = Case(c["motion"], c["seed"], c["speed"], tuple(c["shape"]), c["frames"])
    body = AnnyBody.load()
    m = frame_metrics(drape_case(model, body, case), body)
    for k in ("eps_e", "eps_a", "eps_c"):
        assert abs(float(np.mean(m[k])) - rec["check"][k]) <= 0.05, k

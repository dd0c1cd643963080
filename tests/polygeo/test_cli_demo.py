"""The jets part of ``polygeo demo``: its table is computed against analytic truth."""

import numpy as np
import pytest

from polygeo.cli import main


@pytest.mark.slow
def test_demo_jets_table_against_torus_truth(capsys):
    rc = main(["demo", "--only", "jets", "--points", "3000", "--k", "30"])
    assert rc == 0
    out = capsys.readouterr().out
    levels = ("0.0%", "0.1%", "1.0%")
    lines = [ln.split() for ln in out.splitlines() if ln.strip().startswith(levels)]
    assert len(lines) == 12  # 3 noise levels x orders 1..4
    clean = {int(ln[1]): ln for ln in lines if ln[0] == "0.0%"}
    med = {o: float(clean[o][2]) for o in clean}
    # on exact samples the normal error falls with the jet order (Cazals-Pouget)
    assert med[4] < med[2] < med[1]
    h = {o: float(clean[o][5]) for o in (2, 3, 4)}
    assert h[4] < h[2]
    assert all(np.isfinite(float(ln[-1])) and float(ln[-1]) > 0 for ln in lines)

"""The report: overlay figures and the PDF, built from a known-answer alignment."""

from __future__ import annotations

import re

import numpy as np

from regtrack import _io
from regtrack.metrics.metrics import compute_metrics
from regtrack.registration.align import align
from regtrack.registration.geometry import rotate_about
from regtrack.report import figures as F
from regtrack.report.pdf import CaseReport, ViewReport, metrics_table, write_pdf
from regtrack.views import MammogramView


def _views(theta=4.0):
    t = np.linspace(-np.pi / 2, np.pi / 2, 200)
    breast = np.c_[60 * np.cos(t), 50 * np.sin(t)]
    nipple = np.array([60.0, 0.0])
    s = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    tumour = np.c_[30 + 6 * np.cos(s), 15 + 5 * np.sin(s)]
    real = MammogramView("CC", "R", breast, nipple, [tumour])
    shift = np.array([3.0, -2.0])
    virt = MammogramView("CC", "R", rotate_about(breast, nipple, -theta) + shift, nipple + shift,
                         [rotate_about(tumour, nipple, -theta) + shift])
    return real, virt


def test_overlay_and_pdf(tmp_path):
    real, virt = _views()
    al = align(real, virt)
    m = compute_metrics(al, real, virt, D=0.38)
    assert abs(al.theta_p - 4.0) < 0.1
    png = _io.save_figure(F.overlay_figure(real, virt, al), tmp_path / "overlay.png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    row = {"view": "CC", "BS_Av": m.bs_av, "TS_Av": m.ts_av, "theta_p": m.theta_p, "D": 0.38,
           "d_T": m.d_T, "d_B": m.d_B, "theta_p_b": m.theta_p_b, "theta_p_t": m.theta_p_t}
    head, cells = metrics_table([row])
    assert cells[0][head.index("D (%)")] == "38.0"
    rep = CaseReport("case01", "test", [ViewReport("CC", row, real, virt, al,
                                                   steps=[{"step": "compress", "D": 0.38}])],
                     config={"mechanics": {"tissue_c1_kpa": 0.54}}, provenance={"x": 1})
    pdf = write_pdf(rep, tmp_path / "report.pdf")
    data = pdf.read_bytes()
    assert data[:5] == b"%PDF-"
    # summary + steps + overlay page + provenance
    assert len(re.findall(rb"/Type\s*/Page\b", data)) == 4
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []

"""The report: overlay figures, the verdict and the PDF, built from a known-answer
alignment; the 3-D outputs on a two-tetrahedron model."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np
import pytest

from regtrack import _io
from regtrack.metrics.metrics import compute_metrics
from regtrack.model.types import AnatomicalFrame, BreastModel
from regtrack.registration.align import align
from regtrack.registration.geometry import rotate_about
from regtrack.report import export3d
from regtrack.report import figures as F
from regtrack.report.fmt import drop_empty_columns, num
from regtrack.report.pdf import (CaseReport, ViewReport, case_checks, figure_text, metrics_table,
                                 render_pages, write_pdf)
from regtrack.report.settings import changed_settings
from regtrack.report.verdict import check_view, verdict_line
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


def _row(m, D=0.38):
    return {"view": "CC", "BS_Av": m.bs_av, "TS_Av": m.ts_av, "theta_p": m.theta_p, "D": D,
            "d_T": m.d_T, "d_B": m.d_B, "theta_p_b": m.theta_p_b, "theta_p_t": m.theta_p_t,
            "force_N": -0.0001}


def _report(row, real, virt, al) -> CaseReport:
    sim = {"summary": {"force_imbalance_rel": 7e-8},
           "steps": [{"solver": {"force_balance": {"tol": 0.005}}}]}
    steps = [{"step": "gravity-unloading", "D": None, "force_N": -0.0, "seconds": None},
             {"step": "compression", "D": 0.38, "force_N": 43.6363, "seconds": None}]
    return CaseReport("case01", "test", [ViewReport("CC", row, real, virt, al, steps=steps,
                                                    simulation=sim)],
                      header=["Mode: paper"],
                      appendix=[("Provenance", ["Item", "Value"], [["Versions", "regtrack 0.1"]],
                                 [0.05, 0.3], [30, 100])])


def _texts(report) -> list[str]:
    import matplotlib.pyplot as plt

    out = []
    for fig in render_pages(report):
        out += figure_text(fig)
        plt.close(fig)
    return out


def test_overlay_and_pdf(tmp_path):
    real, virt = _views()
    al = align(real, virt)
    m = compute_metrics(al, real, virt, D=0.38)
    assert abs(al.theta_p - 4.0) < 0.1  # the known rotation, within the search's tolerance
    png = _io.save_figure(F.overlay_figure(real, virt, al), tmp_path / "overlay.png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    row = _row(m)
    head, cells = metrics_table([row])
    assert cells[0][head.index("D (%)")] == "38.0"
    assert cells[0][head.index("Force (N)")] == "0.0"  # never "-0.0"
    pdf = write_pdf(_report(row, real, virt, al), tmp_path / "report.pdf")
    data = pdf.read_bytes()
    assert data[:5] == b"%PDF-"
    # summary + the view's page + appendix: at most 6 pages for two views and tracking
    assert len(re.findall(rb"/Type\s*/Page\b", data)) == 3
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_the_pages_print_no_raw_json_long_floats_negative_zero_or_snake_case():
    real, virt = _views()
    al = align(real, virt)
    texts = _texts(_report(_row(compute_metrics(al, real, virt, D=0.38)), real, virt, al))
    joined = "\n".join(texts)
    assert "Mode: paper" in joined and "Verdict" in joined
    assert not re.search(r'[{\[]\s*"', joined), "raw JSON"
    assert not re.search(r"\d\.\d{6,}", joined), "unrounded float"
    assert not re.search(r"(?<![\w.])[-−]0(\.0+)?(?![\d.])", joined), "negative zero"
    assert not re.search(r"\b[a-z]+_[a-z]+(_[a-z]+)*\b", joined), "snake_case name"
    # the legend names the centroid markers ("+", "x") too
    assert {"real breast centroid", "virtual breast centroid", "real tumour centroid",
            "virtual tumour centroid"} <= set(texts)


def test_the_verdict_flags_a_mismatched_fit():
    """The case of issue 53: BS_Av 4.8 % and theta_p -17 degrees must not pass unnoticed."""
    row = {"view": "CC", "BS_Av": 4.8, "theta_p": -17.0, "d_B": 6.0}
    checks = check_view("CC", row, simulation={"summary": {"force_imbalance_rel": 1e-7}},
                        nipple={"confidence": 0.3, "method": "farthest point"})
    flagged = {c.short for c in checks if c.ok is False}
    assert flagged == {"BS_Av", "θp", "nipple confidence"}
    assert {c.short for c in checks if c.ok} == {"d_B", "force balance"}
    line = verdict_line(checks)
    assert line.startswith("3 of 5 quality checks flagged") and "θp -17.0°" in line
    # and a good fit passes every check
    good = check_view("CC", {"BS_Av": 56.8, "theta_p": 3.7, "d_B": 5.7},
                      simulation={"summary": {"force_imbalance_rel": 7e-8, "skin_overlap_mm": 0.0}},
                      nipple={"confidence": 1.0, "method": "given (nipple_px)"})
    assert all(c.ok for c in good)
    assert verdict_line(good) == "All 6 quality checks passed."
    # skin through skin is flagged past 1 mm, not at 0.4 mm
    sim = {"summary": {"force_imbalance_rel": 7e-8, "skin_overlap_mm": 2.7}}
    folded = check_view("CC", {"BS_Av": 56.8, "theta_p": 3.7, "d_B": 5.7}, simulation=sim)
    assert [c.short for c in folded if c.ok is False] == ["skin in tissue"]
    assert "skin in tissue 2.7 mm (limit ≤ 1 mm)" in verdict_line(folded)
    sim["summary"]["skin_overlap_mm"] = 0.4
    assert all(c.ok is not False for c in check_view("CC", {"BS_Av": 56.8}, simulation=sim))


def test_the_report_shows_the_flags_of_a_mismatched_result():
    real, virt = _views(theta=17.0)
    al = align(real, virt)
    row = {**_row(compute_metrics(al, real, virt, D=0.38)), "BS_Av": 4.8}
    rep = _report(row, real, virt, al)
    assert {c.short for c in case_checks(rep) if c.ok is False} >= {"BS_Av", "θp"}
    joined = "\n".join(_texts(rep))
    assert "quality checks flagged" in joined and "✗" in joined


def test_the_view_page_prints_the_simulation_warnings():
    """The sentences a simulation warned with (chest wall, skin in the tissue) are printed on
    the view's page, the first four in full and the rest counted; none: no section."""
    real, virt = _views()
    al = align(real, virt)
    rep = _report(_row(compute_metrics(al, real, virt, D=0.38)), real, virt, al)
    assert not any("Simulation warnings" in t for t in _texts(rep))
    said = [f"step 'compression': warning number {k}, " + "a long explanation " * 12
            for k in range(1, 6)]
    rep.views[0].simulation["summary"]["warnings"] = said
    joined = " ".join(" ".join(_texts(rep)).split())  # the wrapped lines joined again
    assert "Simulation warnings" in joined
    assert all(f"warning number {k}," in joined for k in range(1, 5))
    assert "warning number 5" not in joined and "and 1 more in the view's simulation JSON" in joined
    assert all(" ".join(w.split()) in joined for w in said[:4])  # whole sentences, not cut


def test_numbers_and_tables():
    assert num(-0.0004, 2) == "0.00"
    assert num(-17.04, 1, unit="°", signed=True) == "-17.0°"
    assert num(3.72, 2, signed=True) == "+3.72"
    assert num(None) == num(float("nan")) == "–"
    head, rows = drop_empty_columns(["a", "b", "c"], [["1", "–", ""], ["2", "–", "x"]])
    assert head == ["a", "c"] and rows == [["1", ""], ["2", "x"]]


@dataclass
class _Inner:
    tol: float = 1e-4


@dataclass
class _Section:
    c1_kpa: float = 0.54
    labels: list = field(default_factory=lambda: [1, 2])
    solver: _Inner = field(default_factory=_Inner)


def test_changed_settings_lists_only_what_differs():
    rows = changed_settings({"mechanics": _Section(c1_kpa=0.67, solver=_Inner(tol=1e-3))},
                            {"CC": {"target_D": 0.3}})
    assert rows == [("mechanics.c1_kpa", "0.67", "0.54"), ("mechanics.solver.tol", "0.001", "0.0001"),
                    ("protocol.CC.target_D", "0.3", "shipped protocol")]
    assert changed_settings({"mechanics": _Section()}) == []


def _model() -> BreastModel:
    pts = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 10, 10]], float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    if np.linalg.det(pts[tets[1, 1:]] - pts[tets[1, 0]]) < 0:
        tets[1] = tets[1][[0, 2, 1, 3]]
    skin = np.array([[0, 2, 1], [1, 2, 4]])
    frame = AnatomicalFrame(np.array([-95.0, -50.0, -8.0]),
                            np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]), "R")
    return BreastModel(pts, tets, np.array([1, 2]), np.array([0, 1]), skin,
                       np.array([1, 1, 1, 0, 0], bool), 4, frame)


def test_3d_outputs_are_in_lps_and_form_a_series(tmp_path):
    import meshio

    model = _model()
    u = np.zeros((5, 3))
    u[4] = [0.0, -2.0, 0.0]  # 2 mm down (model y is superior)
    paths = export3d.write_3d_outputs(model, {"CC": [("compression", u)]}, tmp_path)
    names = {p.relative_to(tmp_path).as_posix() for p in paths}
    assert names == {"model.vtu", "cc/cc_0_prone-reference.vtu", "cc/cc_1_compression.vtu",
                     "cc/cc.pvd", "lesion.mrk.json"}
    ref = meshio.read(tmp_path / "model.vtu")
    np.testing.assert_allclose(ref.points, model.frame.to_patient(model.points))
    # model x (anterior) is LPS -P: the node at model x = 10 lies 10 mm anterior of the nipple
    np.testing.assert_allclose(ref.points[1], [-95.0, -60.0, -8.0])
    last = meshio.read(tmp_path / "cc" / "cc_1_compression.vtu")
    np.testing.assert_allclose(last.point_data["displacement"][4], [0.0, 0.0, -2.0])  # inferior
    np.testing.assert_allclose(last.points - ref.points, last.point_data["displacement"])
    pvd = ET.parse(tmp_path / "cc" / "cc.pvd").getroot()
    assert [d.get("file") for d in pvd.iter("DataSet")] == ["cc_0_prone-reference.vtu",
                                                           "cc_1_compression.vtu"]
    doc = json.loads((tmp_path / "lesion.mrk.json").read_text())
    mk = doc["markups"][0]
    assert mk["type"] == "Fiducial" and mk["coordinateSystem"] == "LPS"
    pts = {c["label"]: c["position"] for c in mk["controlPoints"]}
    # the tumour is the second tetrahedron: its centroid, in LPS
    c = model.points[model.tets[1]].mean(axis=0)
    np.testing.assert_allclose(pts["tumour (MRI)"], model.frame.to_patient(c))
    np.testing.assert_allclose(pts["nipple (MRI)"], [-95.0, -50.0, -8.0])
    assert "tumour (CC compressed)" in pts


@pytest.mark.parametrize("missing", [True, False])
def test_truth_table_rows(tmp_path, missing):
    from regtrack.report.truth import read_truth, truth_table

    if missing:
        assert read_truth(tmp_path) is None
        return
    (tmp_path / "truth").mkdir()
    (tmp_path / "truth" / "mammo_truth.json").write_text(json.dumps({"views": {"CC": {
        "rotation_deg": 5.0, "simulation": {"D": 0.38, "upper_force_N": 37.4},
        "tumour": {"centroid_canonical_mm": [31.2, 72.3]}}}}))
    truth = read_truth(tmp_path)
    head, rows = truth_table(truth, {"CC": {"theta_p": 3.72, "D": 0.38, "force_N": 43.6,
                                            "tumour_xy_mm": [31.7, 71.8]}})
    assert head == ["Quantity", "View", "Truth", "Result", "Difference"]
    assert rows[0] == ["In-plane rotation (°)", "CC", "5.00", "3.72", "-1.28"]
    assert rows[1][-1] == "0.0" and rows[2][-1] == "+6.2"
    assert rows[3][-1] == "0.7 mm apart"


def test_a_case_without_mammograms_gets_virtual_pages_and_no_verdict(tmp_path):
    _, virt = _views()
    rep = CaseReport("case02", "no mammograms", [ViewReport("CC", {"view": "CC", "D": 0.38},
                                                            virtual=virt)])
    assert case_checks(rep) == []
    joined = "\n".join(_texts(rep))
    assert "No quality check could be made" in joined and "virtual CC (R)" in joined
    data = write_pdf(rep, tmp_path / "r.pdf").read_bytes()
    assert len(re.findall(rb"/Type\s*/Page\b", data)) == 2


def test_biopsy_section_cuts_a_tetrahedron_exactly():
    """The biopsy page's sections (:func:`regtrack.report.biopsy.plane_section`): the unit
    tetrahedron's surface cut at z = 1/2 is the triangle (0,0,½), (½,0,½), (0,½,½) (the
    base face z = 0 is not cut); the boundary of two tets sharing a face has 6 faces."""
    from types import SimpleNamespace

    from regtrack.report.biopsy import plane_section, tumour_surface

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    one = SimpleNamespace(points=pts, tets=np.array([[0, 1, 2, 3]]), region=np.array([2]))
    faces = tumour_surface(one)
    assert len(faces) == 4
    seg = plane_section(pts, faces, np.array([0, 0, 0.5]), np.array([0, 0, 1.0]))
    assert seg.shape == (3, 2, 3)
    ends = {tuple(np.round(p, 12)) for p in seg.reshape(-1, 3)}
    assert ends == {(0, 0, 0.5), (0.5, 0, 0.5), (0, 0.5, 0.5)}
    two = SimpleNamespace(points=pts, tets=np.array([[0, 1, 2, 3], [1, 2, 3, 4], [0, 1, 2, 4]]),
                          region=np.array([2, 2, 1]))  # the tissue tet is not tumour
    assert len(tumour_surface(two)) == 6
    assert plane_section(pts, faces, np.array([0, 0, 5.0]), np.array([0, 0, 1.0])).shape == (0, 2, 3)


def test_sequence_panels_draw_the_cut_faces_only_when_seen_across():
    """A 2 mm box whose y = 0 face is 'cut by the field of view': a side view looking along
    y draws it as a second (grey) layer with its note; one looking along z sees it edge-on
    and draws the skin alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from regtrack.mechanics.meshes import box_model
    from regtrack.mechanics.pictures import CUT_FILL, draw_sequence
    from regtrack.model.checks import boundary_faces

    m = box_model((2.0, 2.0, 2.0), (2, 2, 2))
    faces, _ = boundary_faces(m.tets)
    on_cut = np.all(np.isclose(m.points[faces][:, :, 1], 0.0), axis=1)
    plate = {"origin_mm": [0.0, 0.0, -1.0], "normal": [0.0, 0.0, 1.0], "edge_radius_mm": 1.0,
             "s_range_mm": [0.0, 10.0]}
    u = np.zeros_like(m.points)
    for normal, drawn in (([0.0, 0.0, 1.0], True), ([0.0, 1.0, 0.0], False)):
        fig, ax = plt.subplots()
        frame = {"e_x": [1.0, 0.0, 0.0], "normal": normal}
        draw_sequence([ax], m.points, faces[~on_cut], [{"name": "s", "D": None, "plates": {"p": plate}}],
                      [u], frame, faces[on_cut])
        layers = [c for c in ax.collections if isinstance(c, PolyCollection)]
        grey = matplotlib.colors.to_rgba(CUT_FILL, 0.6)
        assert len(layers) == (2 if drawn else 1)
        assert any(np.allclose(c.get_facecolor()[0], grey) for c in layers) == drawn
        assert any("field of view" in t.get_text() for t in ax.texts) == drawn
        plt.close(fig)

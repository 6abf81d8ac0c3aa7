"""One-screen text summary of a validated :class:`~regtrack.case.schema.Case`."""

from __future__ import annotations

import os
from pathlib import Path

from regtrack.case.schema import Case

_CLASS_ORDER = ("tumour", "tissue", "skin", "muscle", "background")


def _rel(case: Case, path: Path | None) -> str:
    return "-" if path is None else os.path.relpath(path, case.root)


def _fmt_num(v: float) -> str:
    return f"{v:.4g}"


def _labels_line(case: Case) -> list[str]:
    lm = case.label_map
    scheme = case.mri.scheme
    if lm is None:
        return [f"  label classes  {scheme.to_dict()}"]
    vox = lm.shape[0] * lm.shape[1] * lm.shape[2]
    vol_ml = vox and float(lm.spacing_mm[0] * lm.spacing_mm[1] * lm.spacing_mm[2]) / 1000.0
    out = [f"  grid           {lm.shape[0]} x {lm.shape[1]} x {lm.shape[2]} voxels of "
           + " x ".join(_fmt_num(s) for s in lm.spacing_mm) + " mm"]
    for cls in _CLASS_ORDER:
        values = getattr(scheme, cls)
        present = [(v, lm.counts[v]) for v in values if v in lm.counts]
        if not values:
            continue
        if not present:
            out.append(f"  {cls:<14} absent (values {list(values)})")
            continue
        names = scheme.names if cls == "tumour" else {}
        text = ", ".join(f"{v}{' ' + names[v] if v in names else ''}: {n}" for v, n in present)
        total = sum(n for _, n in present)
        out.append(f"  {cls:<14} {text} vox ({total * vol_ml:.3g} mL)")
    return out


def _override_lines(case: Case) -> list[str]:
    if not case.overrides:
        return ["  (none: every stage uses its defaults)"]
    out = []
    for sec, ov in case.overrides.items():
        items = ", ".join(f"{k} = {v!r}" for k, v in _flat(ov.table))
        note = "" if ov.config is not None else "  [not checked: stage config not available]"
        out.append(f"  [{sec}] {items or '(empty)'}{note}")
    return out


def _flat(table: dict, prefix: str = ""):
    for k, v in table.items():
        if isinstance(v, dict):
            yield from _flat(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def format_summary(case: Case) -> str:
    """Plain-text summary (about 20-30 lines): id, MRI, views, overrides, warnings."""
    mri = case.mri
    lines = [f"case {case.id}" + (f": {case.title}" if case.title else ""),
             f"  folder         {case.root}",
             "MRI",
             f"  labels         {_rel(case, mri.labels)}  (scheme: "
             f"{mri.scheme_name or 'custom'}"
             + (" + [mri.label_values]" if mri.scheme_name and mri.explicit_classes else "") + ")"]
    if mri.series is not None:
        lines.append(f"  series         {_rel(case, mri.series)}")
    lines += _labels_line(case)
    lines.append(f"  side           {mri.side or 'auto'}")
    nip = mri.nipple_lps_mm
    lines.append("  nipple (LPS)   " + ("auto" if nip is None else
                                        "[" + ", ".join(_fmt_num(v) for v in nip) + "] mm"))
    lines.append("Views" if case.views else "Views          (none)")
    for name, view in case.views.items():
        info = case.mammograms.get(name)
        ann = _rel(case, view.tumour_polygon or view.tumour_mask)
        head = f"  {name:<4} {_rel(case, view.mammogram)}"
        if info is not None:
            sp = ("?" if info.spacing_mm is None else
                  " x ".join(_fmt_num(s) for s in info.spacing_mm) + f" mm ({info.spacing_source})")
            head += (f"  {info.rows} x {info.columns} px, {sp}, {info.modality or '?'} "
                     f"{info.laterality or '?'}{info.view_position or ''}")
        lines.append(head)
        nip_px = "auto" if view.nipple_px is None else f"{list(view.nipple_px)} (row, col)"
        n = f", {info.tumour_polygons} region(s)" if info is not None else ""
        mode = ("paper mode" if (view.tumour_polygon or view.tumour_mask)
                else "tracking mode: the MRI lesion is predicted")
        lines.append(f"       tumour: {ann}{n}; nipple: {nip_px}; {mode}")
    lines.append("Overrides")
    lines += _override_lines(case)
    if case.warnings:
        lines.append(f"Warnings ({len(case.warnings)})")
        lines += [f"  - {w}" for w in case.warnings]
    lines.append("OK" if case.deep else "OK (shallow: inputs not opened)")
    return "\n".join(lines)

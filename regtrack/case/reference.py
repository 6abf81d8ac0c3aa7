"""Key reference of ``case.toml``, generated from the config dataclasses.

``docs/case-format.md`` holds the output of :func:`format_reference` between two marker
lines; regenerate it after changing any section's fields with::

    python -m regtrack.case.reference --write docs/case-format.md
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import typing
from pathlib import Path

from regtrack.case.overrides import SECTIONS, config_class
from regtrack.case.schema import CaseTable, MriTable, ViewTable
from regtrack.config import describe
from regtrack.model.labels import CLASSES

BEGIN = ("<!-- BEGIN GENERATED KEY REFERENCE "
         "(python -m regtrack.case.reference --write docs/case-format.md) -->")
END = "<!-- END GENERATED KEY REFERENCE -->"


def _cell(value) -> str:
    text = "" if value is None else str(value)
    return text.replace("|", "\\|").replace("\n", " ")


def _default(value) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, float):
        return f"`{value:g}`"
    return f"`{value}`"


def _range(row: dict) -> str:
    parts = [row["range"]] if row["range"] else []
    if row["choices"]:
        parts.append("one of " + ", ".join(f'"{c}"' if isinstance(c, str) else str(c)
                                           for c in row["choices"]))
    return "; ".join(parts)


def section_table(cls: type, section: str) -> list[str]:
    """Markdown table(s) of one section; nested dataclass fields get their own table."""
    hints = typing.get_type_hints(cls)
    lines = [f"#### `[{section}]`", "", "| key | default | unit | range | meaning |",
             "|---|---|---|---|---|"]
    nested = []
    for row in describe(cls):
        tp = hints[row["key"]]
        if dataclasses.is_dataclass(tp):
            nested.append((tp, f"{section}.{row['key']}"))
            continue
        if row["key"] == "label_values":
            continue  # documented as its own table
        unit = "" if row["unit"] in ("", "-") else row["unit"]
        lines.append(f"| `{row['key']}` | {_default(row['default'])} | {_cell(unit)} | "
                     f"{_cell(_range(row))} | {_cell(row['doc'])} |")
    lines.append("")
    for tp, sub in nested:
        lines += section_table(tp, sub)
    return lines


def format_reference() -> str:
    """The generated Markdown block (between :data:`BEGIN` and :data:`END`)."""
    lines = [BEGIN, ""]
    lines += section_table(CaseTable, "case")
    lines += section_table(MriTable, "mri")
    lines += ["#### `[mri.label_values]`", "",
              "Each key is a class; each value a list of integer labels (or one integer). "
              "Keys given replace the preset's values of that class; classes not given keep "
              "the preset's.", "", "| key | meaning |", "|---|---|",
              *(f"| `{c}` | {_CLASS_DOC[c]} |" for c in CLASSES), ""]
    lines += section_table(ViewTable, "views.CC] / [views.MLO")
    done: set[str] = set()
    for section, target in SECTIONS.items():
        if target in done:
            continue
        done.add(target)
        cls = config_class(section)
        name = section
        if section.startswith("protocol."):
            name = "protocol.CC] / [protocol.MLO] / [protocol.BIOPSY"
        lines.append(f"Overrides `{target.replace(':', '.')}`.")
        lines.append("")
        lines += section_table(cls, name)
    lines.append(END)
    return "\n".join(lines)


_CLASS_DOC = {
    "tissue": "breast parenchyma (fat, gland, transition): the tissue region of the model",
    "tumour": "lesions; each connected component becomes one tumour (at least one voxel "
              "must be present)",
    "skin": "skin voxels (homogenised with the tissue; the model's skin membrane is the "
            "outer surface)",
    "muscle": "pectoral muscle / chest wall: marks the posterior boundary of the breast",
    "background": "air and everything outside the body",
}


def replace_block(text: str, block: str) -> str:
    """``text`` with the generated block replaced (or appended when absent)."""
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        return head + block + tail
    return text.rstrip() + "\n\n" + block + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", metavar="MD", help="replace the generated block of this file")
    args = parser.parse_args(argv)
    block = format_reference()
    if args.write is None:
        sys.stdout.write(block + "\n")
        return 0
    from regtrack._io import write_text

    path = Path(args.write)
    write_text(path, replace_block(path.read_text(encoding="utf-8"), block))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

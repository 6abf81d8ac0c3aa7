"""Label schemes: which integer values of a label map mean tissue, tumour, skin, muscle.

A :class:`LabelScheme` lists the label values of each class.  The presets cover the
bundled data:

* ``"pelicano-simple"``: -4 benign tumour, -3 malignant tumour, -2 skin, -1 muscle,
  0 background, 1 fat + gland (Pelicano et al., *Sensors* 2021; *PLoS One* 2024);
* ``"pelicano-detailed"``: the same negatives, with fat and gland split into
  7, 6, 5 fat (high, median, low intensity), 4 transition, 3, 2, 1 fibroglandular
  (high, median, low).  The synthetic phantom (``regtrack.phantom``) uses it too.

A case may override a preset with ``[mri.label_values]`` in ``case.toml``; use
:func:`scheme_from_table` for that.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from regtrack.errors import CaseError

CLASSES = ("tissue", "tumour", "skin", "muscle", "background")


def _ints(values) -> tuple[int, ...]:
    return tuple(int(v) for v in values)


@dataclass(frozen=True)
class LabelScheme:
    """Label values of each class of a segmentation.

    Attributes
    ----------
    tissue : tuple of int
        Breast parenchyma (fat, gland, transition).  Homogenised with ``skin`` into
        the tissue region of the model.
    tumour : tuple of int
        Lesions (benign and malignant); every connected component becomes one tumour.
    skin : tuple of int
        Skin voxels (part of the homogenised tissue volume; the model's skin membrane is
        the outer surface).
    muscle : tuple of int
        Pectoral muscle / chest wall: marks the posterior boundary of the breast.
    background : tuple of int
        Air and everything outside the body.
    names : dict
        Optional human-readable name per label value (e.g. ``{-3: "malignant"}``).
    """

    tissue: tuple[int, ...]
    tumour: tuple[int, ...]
    skin: tuple[int, ...] = ()
    muscle: tuple[int, ...] = ()
    background: tuple[int, ...] = (0,)
    names: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        for c in CLASSES:
            object.__setattr__(self, c, _ints(getattr(self, c)))
        problems = self.problems()
        if problems:
            raise ValueError("; ".join(problems))

    def problems(self) -> list[str]:
        """Consistency problems (a value in two classes, no tissue label)."""
        out = []
        if not self.tissue:
            out.append("label scheme has no 'tissue' values")
        seen: dict[int, str] = {}
        for c in CLASSES:
            for v in getattr(self, c):
                if v in seen and seen[v] != c:
                    out.append(f"label value {v} is in both '{seen[v]}' and '{c}'")
                seen[v] = c
        return out

    @property
    def body(self) -> tuple[int, ...]:
        """Values inside the breast model: tissue + skin + tumour."""
        return self.tissue + self.skin + self.tumour

    def mask(self, data: np.ndarray, cls: str) -> np.ndarray:
        """Boolean mask of the voxels whose label belongs to class ``cls``.

        ``cls`` is one of ``tissue``, ``tumour``, ``skin``, ``muscle``, ``background``,
        ``body`` (tissue + skin + tumour).
        """
        values = self.body if cls == "body" else getattr(self, cls)
        if not values:
            return np.zeros(data.shape, bool)
        return np.isin(np.rint(data).astype(np.int64) if data.dtype.kind == "f" else data, values)

    def to_dict(self) -> dict:
        return {c: list(getattr(self, c)) for c in CLASSES}


PRESETS: dict[str, LabelScheme] = {
    "pelicano-simple": LabelScheme(
        tissue=(1,), tumour=(-3, -4), skin=(-2,), muscle=(-1,), background=(0,),
        names={-4: "benign tumour", -3: "malignant tumour", -2: "skin", -1: "muscle",
               0: "background", 1: "fat+gland"},
    ),
    "pelicano-detailed": LabelScheme(
        tissue=(1, 2, 3, 4, 5, 6, 7), tumour=(-3, -4), skin=(-2,), muscle=(-1,), background=(0,),
        names={-4: "benign tumour", -3: "malignant tumour", -2: "skin", -1: "muscle",
               0: "background", 1: "gland (low)", 2: "gland (median)", 3: "gland (high)",
               4: "transition", 5: "fat (low)", 6: "fat (median)", 7: "fat (high)"},
    ),
}


def get_scheme(name: str, *, where: str = "case.toml [mri] scheme") -> LabelScheme:
    """Preset by name; an unknown name raises :class:`CaseError` listing the presets."""
    try:
        return PRESETS[name]
    except KeyError:
        raise CaseError(
            f"{where} = {name!r}: unknown label scheme; use one of "
            + ", ".join(repr(k) for k in PRESETS)
            + " or give [mri.label_values]"
        ) from None


def scheme_from_table(table: dict, *, base: LabelScheme | None = None,
                      where: str = "case.toml [mri.label_values]") -> LabelScheme:
    """Build a scheme from a TOML table ``{class: [values]}``, overriding ``base``.

    Raises :class:`CaseError` naming the key for unknown classes, non-integer values or
    a value listed in two classes.
    """
    problems = []
    kw = base.to_dict() if base is not None else {c: [] for c in CLASSES}
    if base is None:
        kw["background"] = [0]
    for key, vals in table.items():
        if key not in CLASSES:
            problems.append(f"{where}: unknown class '{key}'; use {', '.join(CLASSES)}")
            continue
        if not isinstance(vals, (list, tuple)):
            vals = [vals]
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in vals):
            problems.append(f"{where} {key} = {vals!r}: expected a list of integers")
            continue
        kw[key] = list(vals)
    if not problems:
        try:
            return LabelScheme(**kw)
        except ValueError as exc:
            problems.append(f"{where}: {exc}")
    raise CaseError(problems)

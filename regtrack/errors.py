"""Domain exceptions.

Every error a user can cause derives from :class:`RegtrackError`.  Its message is a
single line that names the file (and TOML key or DICOM tag where relevant) and says
what to do.  The CLI prints ``str(err)`` and exits with :attr:`RegtrackError.exit_code`;
``--debug`` shows the traceback.
"""

from __future__ import annotations


class RegtrackError(Exception):
    """Base class of every user-facing regtrack error."""

    exit_code = 2


class CaseError(RegtrackError):
    """A case folder or ``case.toml`` is invalid.

    ``problems`` holds every problem found (validation collects all of them).
    """

    def __init__(self, problems: list[str] | str):
        if isinstance(problems, str):
            problems = [problems]
        self.problems = list(problems)
        if len(self.problems) == 1:
            msg = self.problems[0]
        else:
            msg = f"{len(self.problems)} problems:\n" + "\n".join(
                f"  - {p}" for p in self.problems
            )
        super().__init__(msg)


class ConfigError(RegtrackError):
    """A simulation / study configuration value is invalid."""


class InputFileError(RegtrackError):
    """An input file (label map, MRI series, mesh, DICOM) cannot be read or is inconsistent."""


class DicomError(InputFileError):
    """A DICOM file is unreadable or lacks a tag regtrack needs."""


class MeshQualityError(RegtrackError):
    """Meshing failed its quality checks after every retry. ``figures`` holds the measures."""

    def __init__(self, msg: str, figures: dict | None = None):
        super().__init__(msg)
        self.figures = figures or {}


class SolverDidNotConvergeError(RegtrackError):
    """Newton did not converge; ``last_converged`` keeps the last converged state."""

    exit_code = 3

    def __init__(self, msg: str, *, load_fraction: float | None = None, last_converged=None):
        super().__init__(msg)
        self.load_fraction = load_fraction
        self.last_converged = last_converged


class ContactDidNotConvergeError(SolverDidNotConvergeError):
    """Contact iterations (status changes / augmentations) did not settle."""


class ResultCheckError(RegtrackError):
    """A computed result failed a guard-rail check (non-finite values, inverted elements,
    penetration bound, ...). The message names the stage."""

    exit_code = 3


class MammogramError(RegtrackError):
    """A mammogram could not be segmented / its contour or nipple could not be found."""


class RegistrationError(RegtrackError):
    """Registration inputs are degenerate (no tumour contour, too few points, ...)."""


class TrackingError(RegtrackError):
    """A tracking request is invalid (point outside the breast, unknown view, ...)."""

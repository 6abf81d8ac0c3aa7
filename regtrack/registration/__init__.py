"""2-D registration of virtual and real mammograms (nipple + golden-section rotation)."""

from regtrack.registration.align import Alignment, align
from regtrack.registration.config import RegistrationConfig
from regtrack.registration.golden import GoldenResult, golden_section

__all__ = ["Alignment", "GoldenResult", "RegistrationConfig", "align", "golden_section"]

"""Virtual mammograms: plate frames, projection of the deformed model, X-ray-like images."""

from regtrack.virtual.config import VirtualConfig
from regtrack.virtual.frames import NOMINAL_ANGLE_DEG, PlateFrame, medial_unit, plate_frame
from regtrack.virtual.project import VirtualMammogram, default_frame, project_model

__all__ = ["NOMINAL_ANGLE_DEG", "PlateFrame", "VirtualConfig", "VirtualMammogram",
           "default_frame", "medial_unit", "plate_frame", "project_model"]

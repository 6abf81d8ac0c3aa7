"""Virtual mammograms: plate frames, projection of the deformed model, X-ray-like images."""

from regtrack.virtual.frames import NOMINAL_ANGLE_DEG, PlateFrame, medial_unit, plate_frame

__all__ = ["NOMINAL_ANGLE_DEG", "PlateFrame", "medial_unit", "plate_frame"]

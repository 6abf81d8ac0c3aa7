"""Patient model: label map -> one breast -> quality tetrahedral mesh (:class:`BreastModel`)."""

from regtrack.model.types import AnatomicalFrame, BreastModel

__all__ = ["AnatomicalFrame", "BreastModel"]

"""Seeded, parametric synthetic prone breast phantom (label map + T1-like MRI + truth).

>>> from regtrack.phantom import PhantomParams, make_phantom
>>> mri, labels, truth = make_phantom(PhantomParams(seed=3, tumour_size_mm=(20, 18, 20)))
"""

from regtrack.phantom.make import make_phantom
from regtrack.phantom.params import PhantomParams, phantom_params

__all__ = ["PhantomParams", "make_phantom", "phantom_params"]

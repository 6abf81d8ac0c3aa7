"""Seeded, parametric synthetic prone breast phantom (label map + T1-like MRI + truth),
and its simulated CC / MLO mammograms with a hidden ground truth.

>>> from regtrack.phantom import PhantomParams, make_phantom
>>> mri, labels, truth = make_phantom(PhantomParams(seed=3, tumour_size_mm=(20, 18, 20)))

Mammograms (minutes: a mesh and two protocol simulations)::

    from regtrack.phantom.case_mammo import make_case_mammograms
    make_case_mammograms("my_case", labels, truth, params=MammoTruthParams())
"""

from regtrack.phantom.make import make_phantom
from regtrack.phantom.mammo_params import MammoTruthParams, mammo_truth_params
from regtrack.phantom.params import PhantomParams, phantom_params

__all__ = ["MammoTruthParams", "PhantomParams", "make_phantom", "mammo_truth_params", "phantom_params"]

"""regtrack: track breast lesions between prone MRI and compressed mammograms.

The package mirrors the pipeline of Lapuebla-Ferri et al. ("Towards an in-plane
methodology to track breast lesions by using mammograms and patient-specific
finite element simulations"):

``case`` (inputs) -> ``imaging`` (MRI labels, real mammograms) -> ``model`` (tet mesh)
-> ``mechanics`` (compression) -> ``virtual`` (projection) -> ``registration``
-> ``metrics`` -> ``report``.  ``study`` and ``tracking`` build on top.

Units everywhere at the edges: mm, kPa, N, degrees.  Internally mm-N-MPa.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]

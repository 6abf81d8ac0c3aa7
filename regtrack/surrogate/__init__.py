"""Per-patient surrogates of the compression: parameters -> nodal displacement of a view.

:mod:`.pca` compresses simulated displacement fields, :mod:`.regression` regresses the PCA
coefficients on the parameters (Gaussian process with a linear trend, or extra trees),
:mod:`.model` holds the fitted :class:`Surrogate` (predict, save, load), :mod:`.design`
the Latin-hypercube designs, :mod:`.training` the case's simulations, :mod:`.validate`
the held-out and leave-one-out errors.
"""

from regtrack.surrogate.design import ParameterBox, default_box
from regtrack.surrogate.model import Surrogate, fit_surrogate

__all__ = ["ParameterBox", "Surrogate", "default_box", "fit_surrogate"]

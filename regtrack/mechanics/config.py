"""Configuration of the mechanics core: materials, skin membrane and step solver.

Every physical parameter is a :func:`regtrack.config.param` field with unit, range and
documentation, so ``case.toml [mechanics]`` and simulation configs are validated by
:func:`regtrack.config.parse_section` (e.g. negative stiffness or ``nu >= 0.5`` are
reported naming the key).  Units at this edge: kPa, Pa (skin), mm, kg/m^3; the solver
works internally in mm-N-MPa (1 kPa = 1e-3 MPa).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from regtrack.config import param

FORMULATIONS = ("p1-anp", "p1", "p2")
TISSUE_MODELS = ("homogeneous", "composition", "heterogeneous")


@dataclass(frozen=True)
class SolverOptions:
    """Options of the step solver (``[mechanics.solver]``, :mod:`.minimise`).

    An increment has converged when the residual on the free dofs meets ``||R||_2 <=
    force_tol * F_ref`` (``F_ref``: the largest of the weight, the contact force, the
    chest-wall reaction and ``||f_int||_2 / sqrt(ndof)``), its resultant is below
    ``balance_tol * F_ref``, and the Newton correction from there moves no node by more
    than ``disp_abs_tol_mm``.  A step's result is accepted only when its global force
    balance is within ``stall_force_tol`` of the largest load.  The other options choose
    the sparse solver and the element kernel's threads; the linear solver's internal
    settings (float32 factors, node ordering, factorisation re-use) are fixed in
    :mod:`.linsolve`, where their measurements are.
    """

    balance_tol: float = param(1e-3, "-", "an increment has converged only when the resultant of "
                               "the residual over the free nodes is below this fraction of the "
                               "force reference too (the global force balance)",
                               gt=0, lt=1)
    force_tol: float = param(1e-5, "-", "relative residual tolerance ||R_free||_2 <= force_tol F_ref "
                             "(F_ref: the largest of weight, contact force and chest-wall reaction)",
                             gt=0, lt=1)
    disp_abs_tol_mm: float = param(0.01, "mm", "an increment has converged only when the Newton "
                                   "correction from its state moves no node by more than this (a "
                                   "tenth of a 0.1 mm mammogram pixel): a small residual alone leaves "
                                   "soft modes undetermined", gt=0)
    max_iterations: int = param(100, "-", "an increment is halved when one of its minimisations "
                                "(one per contact-multiplier update) has not converged after 4 x "
                                "this many Newton iterations: every iteration lowers the potential, "
                                "so a slow path to an equilibrium (tissue sliding along a plate) is "
                                "followed to its end rather than cut back",
                                ge=2, le=200)
    stall_force_tol: float = param(5e-3, "-", "a step's result is accepted only when its global force "
                                   "balance (the residual's resultant over the free nodes) is within "
                                   "this fraction of the largest load (chest-wall reaction, plate "
                                   "force, weight); otherwise the run stops", ge=0, lt=1)
    initial_increment: float = param(0.25, "-", "pseudo-time increment of a gravity step (1 / the "
                                     "number of increments; plate moves use [contact] "
                                     "max_plate_increment_mm)", gt=0, le=1)
    max_augmentations: int = param(20, "-", "contact multiplier and friction-lag updates of an "
                                   "increment before it is cut back (at t = 1: before the step stops)", ge=1)
    linear_solver: str = param("auto", "", "sparse solver", choices=("auto", "pardiso", "splu"))
    assembly_threads: int = param(0, "-", "threads of the tetrahedron force/tangent kernel (0: the "
                                  "CPUs this process may use, at most 4, and at most a study worker's "
                                  "share of the cores).  Results are bit-identical for any count "
                                  "(see regtrack/mechanics/parallel.py)", ge=0, le=64)


@dataclass(frozen=True)
class MechanicsConfig:
    r"""Materials and formulation of the breast model.

    Tissue and tumour: nearly incompressible neo-Hookean

    .. math:: W = c_1(\bar I_1 - 3) + \tfrac{K}{2}(J-1)^2,\quad \bar I_1 = J^{-2/3}\operatorname{tr} C,
              \quad \mu = 2c_1,\quad K = \frac{2\mu(1+\nu)}{3(1-2\nu)}

    so that the small-strain limit has Young's modulus ``E = 2 mu (1 + nu)`` and Poisson
    ratio ``nu``.  Skin: incompressible plane-stress membrane (thickness ``skin_thickness_mm``)

    .. math:: \Psi = \sum_{1\le i+j\le 2} c_{ij}(I_1-3)^i(I_2-3)^j .
    """

    tissue_c1_kpa: float = param(0.54, "kPa", "neo-Hookean c1 of the tissue (paper: 0.54)", gt=0, le=1e4)
    tissue_model: str = param("homogeneous", "", "tissue stiffness: 'homogeneous' (tissue_c1_kpa "
                              "everywhere, the paper's model), 'composition' (one c1 for all tissue: the "
                              "volume-weighted mean of fat_c1_kpa / gland_c1_kpa over the model's "
                              "MRI labels) or 'heterogeneous' (c1 per element from its label)",
                              choices=TISSUE_MODELS)
    fat_c1_kpa: float | None = param(None, "kPa", "neo-Hookean c1 of fat (fat_labels, and tissue "
                                     "labels of no class, e.g. skin voxels); tissue_model != homogeneous",
                                     gt=0, le=1e4)
    gland_c1_kpa: float | None = param(None, "kPa", "neo-Hookean c1 of fibroglandular tissue "
                                       "(gland_labels); tissue_model != homogeneous", gt=0, le=1e4)
    fat_labels: tuple[int, ...] = param((5, 6, 7), "", "MRI label values of fat (default: the "
                                        "pelicano-detailed scheme)")
    gland_labels: tuple[int, ...] = param((1, 2, 3), "", "MRI label values of fibroglandular tissue")
    transition_labels: tuple[int, ...] = param((4,), "", "MRI label values between fat and gland "
                                               "(c1 = mean of fat and gland)")
    tumour_c1_kpa: float = param(5.44, "kPa", "neo-Hookean c1 of the tumour (paper: 5.44)", gt=0, le=1e5)
    nu: float = param(0.49, "-", "Poisson's ratio of the tissue", ge=0.0, lt=0.5)
    tumour_nu: float | None = param(None, "-", "Poisson's ratio of the tumour (default: nu)", ge=0.0, lt=0.5)
    density_kg_m3: float = param(1000.0, "kg/m^3", "tissue density", gt=0, le=1e4)
    formulation: str = param("p1-anp", "", "tet formulation: 'p1-anp' (average nodal pressure, "
                             "locking-free), 'p1' (plain displacement) or 'p2' (10-node tets, "
                             "plain displacement, no skin)", choices=FORMULATIONS)
    skin_enabled: bool = param(True, "", "add the skin membrane on the outer surface")
    skin_thickness_mm: float = param(1.0, "mm", "skin membrane thickness", gt=0, le=10)
    skin_wrinkling: bool = param(True, "", "the skin membrane wrinkles instead of carrying "
                                 "compression (tension-field theory, Pipkin's relaxed energy; "
                                 "false: the plain polynomial energy in compression too)")
    skin_c10_pa: float = param(31.0, "Pa", "skin c10", ge=0)
    skin_c01_pa: float = param(30.0, "Pa", "skin c01", ge=0)
    skin_c11_pa: float = param(22.5, "Pa", "skin c11", ge=0)
    skin_c20_pa: float = param(50.0, "Pa", "skin c20", ge=0)
    skin_c02_pa: float = param(60.0, "Pa", "skin c02", ge=0)
    solver: SolverOptions = field(default_factory=SolverOptions,
                                  metadata={"unit": "", "doc": "step solver options ([mechanics.solver])"})

    def problems(self) -> list[str]:
        """Cross-field checks (called by :func:`regtrack.config.parse_section`)."""
        out = []
        if self.tissue_model != "homogeneous":
            missing = [k for k in ("fat_c1_kpa", "gland_c1_kpa") if getattr(self, k) is None]
            if missing:
                out.append(f"tissue_model = '{self.tissue_model}' needs {' and '.join(missing)} (kPa): "
                           "give them, or use tissue_model = 'homogeneous' with tissue_c1_kpa")
            both = set(self.fat_labels) & set(self.gland_labels)
            if both:
                out.append(f"label value(s) {sorted(both)} are in both fat_labels and gland_labels")
        if self.formulation == "p2" and self.skin_enabled:
            out.append("formulation = 'p2' has no skin membrane: set skin_enabled = false")
        if self.skin_enabled and self.skin_c10_pa + self.skin_c01_pa <= 0:
            out.append("skin_c10_pa + skin_c01_pa must be > 0 (zero initial skin stiffness): "
                       "set skin_enabled = false instead")
        return out

"""Configuration of the mechanics core: materials, skin membrane and Newton solver.

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
    """Options of the step solvers (``[mechanics.solver]``).

    ``method = "energy"`` (the default, :mod:`.minimise`) uses the force and balance
    tolerances, ``max_iterations``, ``initial_increment``, ``max_augmentations``,
    ``stall_force_tol`` and the linear-solver options; the other options belong to the
    residual Newton solver (``"newton"``, :mod:`.solver`), kept for comparison.

    Convergence of a Newton increment requires *both*

    * force: ``||R_free||_2 <= force_tol * F_ref`` with ``F_ref = max(||f_ext||_2,
      ||reaction||_2, ||f_contact||_2, ||f_int||_2 / sqrt(ndof), force_floor_n)``;
    * displacement: ``||du||_inf <= disp_tol * max(||u - u_start||_inf, disp_floor_mm)`` or
      ``||du||_inf <= disp_abs_tol_mm``, where ``u_start`` is the state at the start of
      the increment.
    """

    method: str = param("energy", "", "'energy': each increment minimises the incremental "
                        "potential (regtrack.mechanics.minimise: Newton with inertia correction and "
                        "a line search on the potential, contact and friction as potentials); "
                        "'newton': the former residual-based Newton solver "
                        "(regtrack.mechanics.solver), kept for comparison until it is removed",
                        choices=("newton", "energy"))
    balance_tol: float = param(1e-3, "-", "method 'energy': an increment has converged only when "
                               "the resultant of the residual over the free nodes is below this "
                               "fraction of the force reference too (the global force balance)",
                               gt=0, lt=1)
    force_tol: float = param(1e-4, "-", "relative residual tolerance (vs external force / reaction); "
                             "1e-4 because frictional contact stalls at ~1e-5 (stick/slip switching), "
                             "while the displacement criterion keeps the solution accurate", gt=0, lt=1)
    disp_tol: float = param(1e-4, "-", "relative displacement-correction tolerance (the error left is "
                            "~ the next, quadratically smaller correction)", gt=0, lt=1)
    disp_abs_tol_mm: float = param(0.01, "mm", "a correction this small passes the displacement test "
                                   "whatever the increment's motion (a tenth of a 0.1 mm mammogram "
                                   "pixel; the force test must pass as well)", gt=0)
    force_floor_n: float = param(1e-9, "N", "absolute force floor of the residual reference", gt=0)
    disp_floor_mm: float = param(1e-6, "mm", "absolute displacement floor of the correction reference", gt=0)
    max_iterations: int = param(15, "-", "Newton iterations per increment before a cut-back", ge=2, le=200)
    extra_iterations: int = param(5, "-", "iterations allowed beyond max_iterations while the residual "
                                  "still falls by 10x per iteration (quadratic convergence about to "
                                  "finish: cheaper than a cut-back)", ge=0, le=50)
    stagnation_ratio: float = param(0.5, "-", "after 3 iterations, a residual above this fraction of the "
                                    "smallest of the 3 before it freezes the contact state (stick/slip "
                                    "chatter control, checked after convergence); from the 5th, three "
                                    "residuals none below this fraction of the one before them end a "
                                    "stalled increment (see stall_force_tol)", gt=0, le=1)
    stall_force_tol: float = param(5e-3, "-", "an increment whose Newton iterations stagnate or run "
                                   "out accepts its best iterate if that one's residual is below this "
                                   "fraction of F_ref (and the constraints are met), instead of cutting "
                                   "back; counted in the step's stalled_accepts (0: never).  Skin "
                                   "pinched between a plate edge and the fixed chest wall has a "
                                   "near-singular tangent on which Newton wanders at 1e-4 to 5e-3 "
                                   "F_ref; 5e-3 is Abaqus's default force criterion (R_n)", ge=0, lt=1)
    initial_increment: float = param(0.25, "-", "first pseudo-time increment of a step", gt=0, le=1)
    min_increment: float = param(1e-4, "-", "smallest increment before giving up", gt=0, le=1)
    max_increment: float = param(1.0, "-", "largest increment", gt=0, le=1)
    growth: float = param(1.5, "-", "increment growth factor after an easy increment", ge=1, le=4)
    cutback: float = param(0.5, "-", "increment cut-back factor after a failure", gt=0, lt=1)
    easy_iterations: int = param(5, "-", "an increment converging in at most this many iterations grows the next", ge=1)
    line_search: bool = param(True, "", "backtracking line search (acceptance test: line_search_merit)")
    line_search_ratio: float = param(0.8, "-", "accept a step when |du.R(a)| <= ratio |du.R(0)|", gt=0, lt=1)
    line_search_merit: str = param("auto", "", "line-search acceptance: 'residual' (Armijo on "
                                   "|R|: |R(u + a du)| <= (1 - 1e-4 a) |R(u)|, backtracking by "
                                   "quadratic interpolation), 'directional' (|du.R(a)| <= ratio "
                                   "|du.R(0)|, secant) or 'auto' (directional; a failed increment "
                                   "is retried once with 'residual' before a cut-back)",
                                   choices=("auto", "residual", "directional"))
    line_search_max: int = param(6, "-", "line-search trials per iteration", ge=1, le=30)
    extrapolation: str = param("linear", "", "starting guess of an increment's Newton iterations: "
                               "'linear' extrapolates the last converged increment, u_n + (dt / "
                               "dt_prev) (u_n - u_n-1) (Abaqus *STATIC's default), used when its "
                               "residual is below that of u_n and no element inverts; 'off': start "
                               "from u_n", choices=("linear", "off"))
    max_augmentations: int = param(20, "-", "augmented-Lagrangian updates per increment", ge=1)
    augmentation: str = param("final", "", "when augmented-Lagrangian multipliers are iterated: "
                              "'every' increment re-solves until penetration_tol_mm is met; "
                              "'final' (Uzawa across increments, 22 % fewer Newton iterations on "
                              "the Pelicano protocols): increments before t = 1 take one "
                              "multiplier update each, and the last iterates to the tolerance",
                              choices=("every", "final"))
    augmentation_force_tol: float = param(0.0, "-", "relative residual tolerance (like force_tol) "
                                          "of the Newton solves of an increment while its contact "
                                          "multipliers are still being updated; the state that "
                                          "meets penetration_tol_mm is then solved to force_tol "
                                          "and checked again (0: every solve to force_tol).  "
                                          "Opt-in: 1e-2 saves a third to a half of the "
                                          "iterations on most models but sent one real CC "
                                          "along another frictional path at 3.7x the cost",
                                          ge=0.0, lt=1.0)
    stabilisation: str = param("auto", "", "'auto': an increment that fails is solved again with "
                               "proximal (viscous-like) stabilisation before it is cut back, then "
                               "settled by an undamped solve at the same load; a step whose last "
                               "increment stayed damped ends with undamped equilibrium iterations at "
                               "t = 1 (a damped state is never returned); 'off': "
                               "line-search merit and contact-tangent retries instead (see solver.py)",
                               choices=("auto", "off"))
    stabilisation_factor: float = param(0.05, "-", "proximal weight alpha: the damping force of a "
                                        "stabilised increment is alpha diag(K) (u - u_start), with "
                                        "diag(K) the tissue and skin tangent's diagonal at the "
                                        "increment's start", gt=0, le=10)
    stabilisation_polish: int = param(8, "-", "proximal solves at t = 1 before a step whose last "
                                      "increment was stabilised gives up its undamped equilibrium",
                                      ge=1, le=100)
    settle_multipliers: str = param("stabilised", "", "the undamped settle solve after a "
                                    "stabilised increment starts from the stabilised solve's "
                                    "augmented-Lagrangian multipliers ('stabilised') or from the "
                                    "last committed ones ('committed'); "
                                    "either way a failed settle returns to the stabilised "
                                    "solve's multipliers (see solver.py)",
                                    choices=("stabilised", "committed"))
    stabilised_first_after: int = param(2, "-", "in a run of this many or more consecutive "
                                        "increments that each needed stabilisation, the next "
                                        "ones skip the undamped attempt (it failed in each of "
                                        "them) and are solved stabilised at once, but for every "
                                        "stabilised_probe-th one (0: off); about 15 % fewer "
                                        "Newton iterations on the real MLOs that need it, plate "
                                        "forces within 1 %", ge=0)
    stabilised_skip_settle: bool = param(True, "", "an increment that skips its undamped "
                                         "attempt (stabilised_first_after) skips the settle "
                                         "solve too and is committed stabilised (see solver.py)")
    stabilised_probe: int = param(4, "-", "in a stabilised run (stabilised_first_after), every "
                                  "this-many-th increment tries the undamped solve first, to "
                                  "find the run's end", ge=1, le=100)
    crawl_increments: int = param(6, "-", "crawl guard of the protocol engine's plate moves "
                                  "(only where a retry follows: "
                                  "ProtocolRunner._run_step_with_retry): after this many "
                                  "consecutive accepted increments that each needed "
                                  "stabilisation, a step whose rest would take more than "
                                  "crawl_remaining further increments of their mean size "
                                  "stops, to be retried from its start (0: off)", ge=0)
    crawl_remaining: float = param(40.0, "-", "crawl guard: the most further increments (of the "
                                   "stabilised ones' mean size) a stabilised run may still need "
                                   "(a run that finished had about 24 left, one that crawled "
                                   "about 137)", gt=0)
    linear_solver: str = param("auto", "", "sparse solver", choices=("auto", "pardiso", "splu"))
    assembly_threads: int = param(0, "-", "threads of the tetrahedron force/tangent kernel (0: the "
                                  "CPUs this process may use, at most 4, and at most a study worker's "
                                  "share of the cores).  Results are bit-identical for any count "
                                  "(see regtrack/mechanics/parallel.py)", ge=0, le=64)
    ordering: str = param("nodes", "", "fill-reducing ordering of the direct solver: 'nodes' (METIS nested "
                          "dissection of the node graph, a node's unknowns together: ~20 % faster "
                          "factorisations at 10k nodes) or 'pardiso' (PARDISO's METIS on the dof graph)",
                          choices=("nodes", "pardiso"))
    reuse_factorisation: bool = param(True, "", "re-use the last factorisation as the preconditioner of "
                                      "GMRES while that is cheaper than refactorising (inexact Newton; "
                                      "linsolve.py); false: factorise at every iteration (exact Newton)")
    precision: str = param("mixed", "", "PARDISO factorisation precision: 'mixed' (float32 factors as the "
                           "preconditioner of float64 GMRES: ~1.7x faster, half the memory; falls back to "
                           "'double' by itself on ill-conditioned systems) or 'double'",
                           choices=("mixed", "double"))
    preconditioner: str = param("fixed-bound", "", "matrix factorised to precondition GMRES when "
                                "sliding friction makes the tangent non-symmetric: 'fixed-bound' "
                                "(the tangent less the sliding nodes' friction-bound term "
                                "mu d(p)/du, which is symmetric; GMRES then needs 1-4 iterations "
                                "on fresh factors, against 1-16) or 'symmetric-part' "
                                "((K + K^T) / 2); linsolve.py",
                                choices=("fixed-bound", "symmetric-part"))
    forcing_max: float = param(1e-2, "-", "largest relative linear-solve tolerance of inexact Newton "
                               "(Eisenstat-Walker forcing term cap)", gt=0, lt=1)
    krylov_rtol: float = param(1e-10, "-", "smallest relative linear-solve tolerance of a re-used "
                               "factorisation", gt=0, lt=1e-3)
    reuse_budget: float = param(0.5, "-", "GMRES budget of a solve on a re-used factorisation "
                                "before it is refactorised, as a fraction of the estimated cost "
                                "ratio rho of a factorisation to a GMRES iteration: k_max = "
                                "clip(reuse_budget * rho, 4, krylov_max) (linsolve.py)",
                                gt=0.0, le=10.0)
    increment_refactor: str = param("adaptive", "", "fresh factorisation at the first Newton "
                                    "iteration of an increment (not of a re-solve after a "
                                    "multiplier update): 'adaptive' in every later increment of "
                                    "a step once an increment's first solve has failed on the "
                                    "re-used factors (plate moves: they fail there as a rule), "
                                    "'never' or 'always'",
                                    choices=("never", "adaptive", "always"))
    krylov_max: int = param(60, "-", "cap of the GMRES iterations on a re-used factorisation before "
                            "refactorising (the actual limit follows the estimated cost ratio and "
                            "reuse_budget)", ge=1, le=500)

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
        s = self.solver
        if s.min_increment > s.initial_increment:
            out.append(f"solver.min_increment = {s.min_increment} exceeds initial_increment = "
                       f"{s.initial_increment}: lower min_increment")
        if s.initial_increment > s.max_increment:
            out.append(f"solver.initial_increment = {s.initial_increment} exceeds max_increment = "
                       f"{s.max_increment}: raise max_increment")
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

"""Meshing settings (``[model]`` section of ``case.toml``).

Every field carries its unit, documentation and valid range (see :func:`regtrack.config.param`);
:func:`regtrack.config.parse_section` builds a :class:`MeshConfig` from a TOML table and
names the key of every bad value.  The defaults are the same for every exam (nothing is
tuned to one patient) and give a model of about 10,000 nodes, like the 9,678-node model of
Lapuebla-Ferri et al.
"""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param


@dataclass(frozen=True)
class MeshConfig:
    """Settings of :func:`regtrack.model.build_model`.

    Size control: when ``element_size_mm`` is given it wins; otherwise the element size
    ``h`` is chosen so the mesh has about ``target_nodes`` nodes.  For a quasi-uniform
    Delaunay mesh of a volume ``V`` (mm^3) the node count is ``N ~ c V / h^3`` with
    ``c ~ 1.0`` (measured on remeshed gmsh meshes); ``h`` is re-estimated from the measured count
    when the first mesh misses the target by more than ``node_tolerance``.
    """

    # size
    target_nodes: int = param(10000, "nodes", "approximate number of mesh nodes (used when element_size_mm is not set)", ge=200, le=2_000_000)
    element_size_mm: float | None = param(None, "mm", "target tetrahedron edge length; overrides target_nodes", gt=0.3, le=50.0)
    node_tolerance: float = param(0.35, "-", "relative miss of target_nodes that triggers one re-sizing pass", gt=0.0, le=5.0)
    refine_tumours: bool = param(True, "-", "refine the mesh around tumours")
    tumour_size_factor: float = param(0.5, "-", "element size at tumour surfaces, as a fraction of the global size", gt=0.05, le=1.0)
    tumour_min_elements: float = param(4.0, "-", "at least this many elements across a tumour's equivalent diameter", ge=1.0, le=20.0)
    refine_distance_mm: float = param(15.0, "mm", "distance over which the size grows from the tumour size back to the global size", gt=0.0, le=200.0)
    # selection and crop
    margin_mm: float = param(5.0, "mm", "margin around the breast when cropping the label map", ge=0.0, le=100.0)
    min_breast_prominence_mm: float = param(15.0, "mm", "two anterior peaks this prominent mean a bilateral map (split at the midline)", gt=0.0, le=200.0)
    # chest wall
    chest_wall_percentile: float = param(10.0, "%", "the chest-wall plane lies at this percentile (towards anterior) of the muscle's anterior face under the breast", ge=0.0, le=100.0)
    chest_wall_offset_mm: float = param(0.0, "mm", "extra shift of the chest-wall plane towards anterior", ge=-50.0, le=100.0)
    chest_wall_tilt_max_deg: float = param(45.0, "degrees", "largest accepted tilt of the fitted chest-wall normal from the patient anterior axis (beyond it the patient axis is used and a warning logged)", ge=0.0, le=90.0)
    fold_fraction: float = param(0.4, "-", "the breast ends cranially/caudally (inframammary fold) where its protrusion anterior of the chest wall falls below this fraction of the apex protrusion", ge=0.0, lt=1.0)
    fix_extra: bool = param(False, "-", "also fix nodes near the cranial top and the medial (sagittal) cut, as in Lapuebla-Ferri et al.")
    fix_extra_band_mm: float = param(5.0, "mm", "width of the extra fixed bands (fix_extra)", gt=0.0, le=100.0)
    # nipple
    nipple_depth_mm: float = param(3.0, "mm", "skin points within this depth of the most anterior point form the nipple cap whose centre is the nipple", gt=0.0, le=30.0)
    # tumours
    min_tumour_volume_mm3: float = param(50.0, "mm^3", "tumour components smaller than this are removed (with a logged warning)", ge=0.0)
    tumour_clearance_mm: float = param(1.0, "mm", "smallest gap kept between a tumour surface and the outer surface (tumours reaching the skin or the cut are trimmed)", ge=0.2, le=20.0)
    # surfaces
    smoothing_mm: float = param(1.5, "mm", "Gaussian sigma applied to the breast mask before marching cubes", ge=0.0, le=10.0)
    tumour_smoothing_mm: float = param(0.8, "mm", "Gaussian sigma applied to each tumour mask before marching cubes", ge=0.0, le=10.0)
    surface_step_vox: int = param(0, "voxels", "marching-cubes step of the outer surface before remeshing (0: from the element size, round(h / 2.5 voxel))", ge=0, le=8)
    feature_fraction: float = param(0.4, "-", "crevices and ridges narrower than about twice this fraction of the element size are removed (closing/opening of the breast mask) before remeshing", ge=0.0, le=2.0)
    min_triangle_angle_deg: float = param(5.0, "degrees", "remeshed boundary triangles must have no smaller angle (else the remeshing is retried)", ge=0.0, lt=60.0)
    feature_angle_deg: float = param(40.0, "degrees", "angle between triangles above which an edge is a sharp feature (gmsh classifySurfaces)", gt=5.0, lt=180.0)
    # gmsh
    algorithm: str = param("delaunay", "-", "first 3-D algorithm to try", choices=("delaunay", "hxt", "netgen"))
    threads: int = param(2, "-", "gmsh threads (HXT)", ge=1, le=256)
    optimize_netgen: bool = param(True, "-", "run Netgen's optimiser after gmsh's")
    timeout_s: float = param(300.0, "s", "a gmsh attempt running longer than this is killed and the next setting tried", gt=1.0)
    max_attempts: int = param(5, "-", "meshing attempts (other algorithm, rounded rim, smoothing, size; regtrack.model.build.attempt_plan) before MeshQualityError", ge=1, le=10)
    retry_rim_fraction: float = param(0.5, "-", "from the third attempt on, the rim where the skin meets a cut plane is rounded over this fraction of the element size (a thinner wedge between skin and cut plane folds when remeshed)", ge=0.0, le=2.0)
    # checks
    min_dihedral_deg: float = param(5.0, "degrees", "smallest accepted dihedral angle", ge=0.0, lt=60.0)
    min_gamma_p5: float = param(0.3, "-", "smallest accepted 5th percentile of gmsh's gamma quality", ge=0.0, lt=1.0)
    max_volume_error: float = param(0.03, "-", "accepted relative error of the mesh volume vs the voxel volume", gt=0.0, le=1.0)
    max_tumour_volume_error: float = param(0.10, "-", "accepted relative error of each tumour's meshed volume against its voxel volume (tumours >= check_tumour_min_ml)", gt=0.0, le=1.0)
    check_tumour_min_ml: float = param(0.0, "ml", "tumours at least this large have their volume checked (0: every tumour kept, i.e. >= min_tumour_volume_mm3)", ge=0.0)
    tumour_refinements: int = param(3, "-", "rounds of local refinement of the tumours whose meshed volume misses max_tumour_volume_error (element size and smoothing of those tumours times tumour_refine_factor per round) before the attempt counts as failed", ge=0, le=10)
    tumour_refine_factor: float = param(0.7, "-", "factor on a missing tumour's element size and smoothing per refinement round", gt=0.1, lt=1.0)
    max_mean_surface_distance_vox: float = param(1.0, "voxels", "accepted mean distance of the mesh surface to the segmentation boundary", gt=0.0, le=10.0)

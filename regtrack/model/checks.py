"""Mesh checks: orientation, element quality, volumes, distance to the segmentation.

Quality measures (per tetrahedron, ``V`` volume, ``A_i`` face areas, ``l`` edge lengths):

* signed volume ``V = (x_1 - x_0) . ((x_2 - x_0) x (x_3 - x_0)) / 6`` (must be > 0);
* dihedral angles between the six pairs of faces, ``cos theta = -n_i . n_j`` with outward
  face normals ``n_i``;
* gmsh's ``gamma`` = ``3 r_in / R_circ`` (1 for the regular tetrahedron), with
  ``r_in = 3V / sum A_i`` and ``R_circ = sqrt((aA+bB+cC)(aA+bB-cC)(aA-bB+cC)(-aA+bB+cC)) / (24 V)``
  (``a, A`` etc. lengths of opposite edges).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

# faces of tet (0,1,2,3) opposite to each vertex, ordered so their normals point outward
# for a positively oriented tet
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tet volumes (mm^3)."""
    p = points[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def dihedral_angles(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(E, 6) interior dihedral angles (degrees) of positively oriented tets."""
    p = points[tets]
    normals = []
    for f in TET_FACES:
        a, b, c = p[:, f[0]], p[:, f[1]], p[:, f[2]]
        n = np.cross(b - a, c - a)
        normals.append(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300))
    out = []
    for i in range(4):
        for j in range(i + 1, 4):
            cosv = -np.einsum("ij,ij->i", normals[i], normals[j])
            out.append(np.degrees(np.arccos(np.clip(cosv, -1.0, 1.0))))
    return np.stack(out, axis=1)


def gamma_quality(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """gmsh's gamma = 3 r_in / R_circ per tet (0 degenerate, 1 regular)."""
    p = points[tets]
    v = np.abs(tet_volumes(points, tets))
    area = np.zeros(len(tets))
    for f in TET_FACES:
        area += 0.5 * np.linalg.norm(np.cross(p[:, f[1]] - p[:, f[0]], p[:, f[2]] - p[:, f[0]]), axis=1)
    r_in = 3.0 * v / np.maximum(area, 1e-300)

    def ln(i, j):
        return np.linalg.norm(p[:, i] - p[:, j], axis=1)

    aA, bB, cC = ln(0, 1) * ln(2, 3), ln(0, 2) * ln(1, 3), ln(0, 3) * ln(1, 2)
    prod = (aA + bB + cC) * (aA + bB - cC) * (aA - bB + cC) * (-aA + bB + cC)
    r_circ = np.sqrt(np.maximum(prod, 0.0)) / np.maximum(24.0 * v, 1e-300)
    return np.where(v > 0, 3.0 * r_in / np.maximum(r_circ, 1e-300), 0.0)


def boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces used by exactly one tet, outward oriented, and the index of that tet."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(len(tets)), 4)
    key = np.sort(faces, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = cnt[inv.ravel()] == 1
    return faces[once], owner[once]


def cut_faces(tets: np.ndarray, skin: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """Outer faces (K, 3) that are neither skin nor chest wall (a face of three ``fixed``
    nodes): where the MRI's field of view cut the breast.  The mesh ends there without a
    skin membrane; pictures draw these faces apart so that the cut is not read as a hole."""
    faces, _ = boundary_faces(tets)
    skin_keys = {tuple(f) for f in np.sort(np.asarray(skin, np.int64).reshape(-1, 3), axis=1)}
    keep = [k for k, f in enumerate(np.sort(faces, axis=1))
            if tuple(f) not in skin_keys and not np.all(fixed[f])]
    return faces[keep]


def interface_faces(tets: np.ndarray, tumour_id: np.ndarray) -> np.ndarray:
    """Faces shared by a tumour tet and a tet of another region (tumour surfaces)."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    tid = np.repeat(tumour_id, 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    ks = key[order]
    same = np.all(ks[1:] == ks[:-1], axis=1)
    a, b = order[:-1][same], order[1:][same]
    diff = tid[a] != tid[b]
    return faces[a[diff]]


@dataclass
class SignedDistance:
    """Signed distance (mm, positive outside) to a voxel mask's boundary, sampled at voxel
    centres: ``phi = edt_out - s/2`` outside, ``-(edt_in - s/2)`` inside, with ``s`` the
    mean voxel size (the boundary lies half a voxel from the boundary voxel centres)."""

    phi: np.ndarray
    affine: np.ndarray

    @classmethod
    def of_mask(cls, mask: np.ndarray, affine: np.ndarray) -> "SignedDistance":
        sp = np.linalg.norm(affine[:3, :3], axis=0)
        half = 0.5 * float(np.mean(sp))
        pad = np.pad(mask, 2)
        out = ndimage.distance_transform_edt(~pad, sampling=sp)
        inn = ndimage.distance_transform_edt(pad, sampling=sp)
        phi = np.where(pad, -(inn - half), out - half)[2:-2, 2:-2, 2:-2]
        return cls(phi.astype(np.float32), affine)

    def __call__(self, xyz: np.ndarray) -> np.ndarray:
        inv = np.linalg.inv(self.affine)
        ijk = np.asarray(xyz, float) @ inv[:3, :3].T + inv[:3, 3]
        return ndimage.map_coordinates(self.phi, ijk.T, order=1, mode="nearest")


def quality_figures(points: np.ndarray, tets: np.ndarray, gamma: np.ndarray | None = None) -> dict:
    """Orientation and quality statistics of a tet mesh."""
    v = tet_volumes(points, tets)
    dih = dihedral_angles(points, tets)
    g = gamma_quality(points, tets) if gamma is None else np.asarray(gamma)
    return {
        "n_nodes": int(len(points)), "n_tets": int(len(tets)),
        "n_inverted": int(np.count_nonzero(v <= 0)),
        "min_tet_volume_mm3": float(v.min()),
        "min_dihedral_deg": float(dih.min()), "max_dihedral_deg": float(dih.max()),
        "gamma_min": float(g.min()), "gamma_p1": float(np.percentile(g, 1)),
        "gamma_p5": float(np.percentile(g, 5)), "gamma_median": float(np.median(g)),
    }

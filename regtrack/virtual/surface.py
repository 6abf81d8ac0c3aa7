"""Boundary faces of tetrahedral sub-meshes, oriented outwards."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

#: Faces of tetrahedron (0, 1, 2, 3); face k is opposite vertex k.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def boundary_faces(tets: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Faces that belong to exactly one of ``tets``, oriented with outward normals.

    Parameters
    ----------
    tets : (E, 4) int
        Tetrahedra (any orientation).
    points : (N, 3) float
        Node coordinates used to orient the faces (mm): a face's normal
        ``(b - a) x (c - a)`` is made to point away from the tet's fourth vertex.

    Returns
    -------
    (F, 3) int
    """
    tets = np.ascontiguousarray(tets, np.int64).reshape(-1, 4)
    if len(tets) == 0:
        return np.zeros((0, 3), np.int64)
    faces, opposite = _topology(hashlib.blake2b(tets.tobytes(), digest_size=16).digest(), tets)
    p = np.asarray(points, float)
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    n = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", n, p[opposite] - a) > 0
    faces = faces.copy()
    faces[inward, 1], faces[inward, 2] = faces[inward, 2], faces[inward, 1].copy()
    return faces


_TOPOLOGY: OrderedDict = OrderedDict()  # digest of the tets -> (faces, opposite vertices)
_LOCK = threading.Lock()


def _topology(digest: bytes, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces in exactly one tet, unoriented, and the vertex opposite each; computed once per
    connectivity (the last 8 kept: a calibration projects one mesh at many shapes)."""
    with _LOCK:
        hit = _TOPOLOGY.get(digest)
        if hit is not None:
            _TOPOLOGY.move_to_end(digest)
            return hit
    faces = tets[:, _TET_FACES].reshape(-1, 3)
    opposite = tets.reshape(-1)  # vertex k of tet e is opposite face (e, k)
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                               return_counts=True)
    once = counts[inv.reshape(-1)] == 1
    hit = (faces[once], opposite[once])
    with _LOCK:
        _TOPOLOGY[digest] = hit
        while len(_TOPOLOGY) > 8:
            _TOPOLOGY.popitem(last=False)
    return hit


def face_normals(faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unnormalised normals ``(b - a) x (c - a)`` of triangles (mm^2; length = 2 x area)."""
    p = np.asarray(points, float)[np.asarray(faces, np.int64)]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])

"""Small reference meshes for verification tests and benchmarks (not patient models).

* :func:`box_model`: structured Kuhn (6 tets per hexahedron) mesh of a box, conforming;
* :func:`hemisphere_model`: gmsh Delaunay mesh of a hemisphere on a chest wall (z = 0),
  the benchmark geometry of docs/design.md;
* :func:`boundary_faces`: outward-oriented boundary triangles of a tet mesh.
"""

from __future__ import annotations

import itertools

import numpy as np

from regtrack._gmsh import gmsh_session
from regtrack.model.types import AnatomicalFrame, BreastModel



def _kuhn_tets() -> np.ndarray:
    out = []
    for perm in itertools.permutations(range(3)):
        v = np.zeros(3, int)
        path = [0]
        for ax in perm:
            v[ax] = 1
            path.append(int(v[0] + 2 * v[1] + 4 * v[2]))
        out.append(path)
    return np.array(out)


def box_model(lengths=(1.0, 1.0, 1.0), divisions=(2, 2, 2), *, origin=(0.0, 0.0, 0.0),
              fixed: np.ndarray | None = None) -> BreastModel:
    """Box ``[0, lx] x [0, ly] x [0, lz]`` (mm) in Kuhn tetrahedra, all region 1 (tissue).

    Skin = all boundary faces; ``fixed`` (N,) bool defaults to none.
    """
    nx, ny, nz = divisions
    xs = [np.linspace(0, L, n + 1) + o for L, n, o in zip(lengths, divisions, origin)]
    P = np.stack(np.meshgrid(*xs, indexing="ij"), axis=-1).reshape(-1, 3)

    def nid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    corners = []
    for c in range(8):
        dx, dy, dz = c & 1, (c >> 1) & 1, (c >> 2) & 1
        corners.append((dx, dy, dz))
    I, J, K = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    I, J, K = I.ravel(), J.ravel(), K.ravel()
    hexn = np.stack([nid(I + dx, J + dy, K + dz) for dx, dy, dz in corners], axis=1)
    tets = hexn[:, _kuhn_tets()].reshape(-1, 4)
    tets = orient_tets(P, tets)
    n = len(P)
    return BreastModel(points=P, tets=tets, region=np.ones(len(tets), int), tumour_id=np.zeros(len(tets), int),
                       skin=boundary_faces(P, tets), fixed=np.zeros(n, bool) if fixed is None else fixed,
                       nipple=int(np.argmax(P[:, 0])), frame=AnatomicalFrame(np.zeros(3), np.eye(3), "R"))


def orient_tets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two nodes of negatively oriented tetrahedra."""
    tets = np.array(tets, np.int64)
    p = points[tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    neg = vol < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def boundary_faces(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Triangles on the boundary (faces used by one tet), oriented with outward normals."""
    loc = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward for positive tets
    faces = tets[:, loc].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[cnt[inv.ravel()] == 1]


def hemisphere_model(radius: float = 50.0, lc: float = 5.0, *, tumour_radius: float = 0.0) -> BreastModel:
    """gmsh tet mesh of the hemisphere ``x >= 0``, ``|p| <= radius`` (mm), chest wall x = 0 fixed.

    The nipple is the pole (radius, 0, 0) (the model frame has x anterior).  With
    ``tumour_radius > 0`` a spherical tumour (region 2) is embedded at (radius/2, 0, 0).
    """
    with gmsh_session() as gmsh:
        gmsh.model.add("hemisphere")
        occ = gmsh.model.occ
        s = occ.addSphere(0, 0, 0, radius)
        b = occ.addBox(0, -radius, -radius, radius, 2 * radius, 2 * radius)
        hemi, _ = occ.intersect([(3, s)], [(3, b)])
        vols = [v for _, v in hemi]
        tum = []
        if tumour_radius > 0:
            t = occ.addSphere(radius / 2, 0, 0, tumour_radius)
            out, m = occ.fragment(hemi, [(3, t)])
            tum = [v for _, v in m[1]]
            vols = [v for d, v in out if d == 3 and v not in tum]
        occ.synchronize()
        gmsh.model.addPhysicalGroup(3, vols, 1)
        if tum:
            gmsh.model.addPhysicalGroup(3, tum, 2)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMin", lc)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", lc)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        P = coords.reshape(-1, 3)
        idx = np.full(int(tags.max()) + 1, -1)
        idx[tags.astype(int)] = np.arange(len(tags))
        tets, region = [], []
        for dim, tag in gmsh.model.getPhysicalGroups(3):
            for v in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
                et, _, en = gmsh.model.mesh.getElements(3, v)
                for t_, n_ in zip(et, en):
                    if t_ == 4:
                        tt = idx[n_.astype(int)].reshape(-1, 4)
                        tets.append(tt)
                        region.append(np.full(len(tt), tag))
    tets = np.concatenate(tets)
    region = np.concatenate(region)
    used = np.unique(tets)
    remap = np.full(len(P), -1)
    remap[used] = np.arange(len(used))
    P = P[used]
    tets = orient_tets(P, remap[tets])
    faces = boundary_faces(P, tets)
    on_wall = np.all(np.abs(P[faces][:, :, 0]) < 1e-6 * radius, axis=1)
    fixed = np.abs(P[:, 0]) < 1e-6 * radius
    return BreastModel(points=P, tets=tets, region=region, tumour_id=(region == 2).astype(int),
                       skin=faces[~on_wall], fixed=fixed, nipple=int(np.argmax(P[:, 0])),
                       frame=AnatomicalFrame(np.zeros(3), np.eye(3), "R"))

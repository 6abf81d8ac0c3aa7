"""Test meshes made with gmsh: a half-ellipsoid breast with a spherical tumour."""

from __future__ import annotations

import numpy as np
import pytest

from regtrack._gmsh import gmsh_session


def half_ellipsoid_with_tumour(axes, tumour_centre, tumour_radius, *, h: float, ht: float):
    """Tet mesh of the half-ellipsoid ``x in [-a, 0]`` (semi-axes ``axes = (a, b, c)`` mm,
    flat face at ``x = -a``) holding a spherical tumour.

    Returns ``(points (N, 3), tets (E, 4), region (E,))`` with region 2 in the tumour and
    1 elsewhere; ``h`` is the largest element size, ``ht`` the size on the tumour surface.
    """
    pytest.importorskip("gmsh")
    A, B, C = axes
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        s = occ.addSphere(0, 0, 0, 1.0)
        occ.dilate([(3, s)], 0, 0, 0, A, B, C)
        occ.translate([(3, s)], -A, 0, 0)
        box = occ.addBox(-A, -2 * B, -2 * C, 2 * A, 4 * B, 4 * C)
        body, _ = occ.intersect([(3, s)], [(3, box)])
        occ.fragment(body, [(3, occ.addSphere(*tumour_centre, tumour_radius))])
        occ.synchronize()
        vols = [e[1] for e in gmsh.model.getEntities(3)]
        tv = min(vols, key=lambda v: occ.getMass(3, v))
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.mesh.setSize(gmsh.model.getBoundary([(3, tv)], recursive=True), ht)
        gmsh.model.mesh.generate(3)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        lookup = np.zeros(int(tags.max()) + 1, np.int64)
        lookup[tags.astype(np.int64)] = np.arange(len(tags))
        tets, reg = [], []
        for v in vols:
            _, _, en = gmsh.model.mesh.getElements(3, v)
            t = lookup[en[0].astype(np.int64)].reshape(-1, 4)
            tets.append(t)
            reg.append(np.full(len(t), 2 if v == tv else 1))
    return xyz.reshape(-1, 3), np.concatenate(tets), np.concatenate(reg)

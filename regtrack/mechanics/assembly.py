"""Sparsity pattern and scatter maps of the global tangent (built once per mesh).

The tangent is stored as a CSR matrix over dofs ``3*node + component`` whose pattern is
node-blocked: row ``3p+i`` holds the columns ``3q+k`` for every node ``q`` adjacent to
``p`` (sorted), ``k = 0..2``.  So the value of entry ``(3p+i, 3q+k)`` lives at

    9 * nptr[p] + 3 * i * deg(p) + 3 * j(p, q) + k,

with ``nptr/nidx`` the node adjacency (CSR) and ``j(p, q)`` the position of ``q`` in the
row of ``p``.  Element kernels scatter straight into the CSR values with precomputed
``base = 9 nptr[p] + 3 j`` maps; the pattern never changes, so the sparse factorisation
analysis is done once.  Adjacency: the 1-ring (nodes sharing a tetrahedron) for plain
P1; the 2-ring of the average-nodal-pressure groups for ANP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass
class Pattern:
    """Node-blocked CSR pattern (see module docstring)."""

    n_nodes: int
    nptr: np.ndarray  # (N+1,) int64
    nidx: np.ndarray  # (nnz_nodes,) int64, sorted per row
    indptr: np.ndarray  # (3N+1,) int64 dof CSR
    indices: np.ndarray  # (9*nnz_nodes,) int32 dof CSR
    rowstride: np.ndarray  # (N,) int64: 3 * deg(p)
    keys: np.ndarray  # (nnz_nodes,) int64 sorted p * N + q

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """CSR matrix sharing this pattern (no copy of ``data``)."""
        n = 3 * self.n_nodes
        m = sp.csr_matrix((data, self.indices, self.indptr), shape=(n, n), copy=False)
        m.has_sorted_indices = True
        return m

    def node_positions(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Position ``j(p, q)`` of node ``q`` in the row of ``p``; -1 where not adjacent."""
        k = np.asarray(p, np.int64) * self.n_nodes + np.asarray(q, np.int64)
        idx = np.searchsorted(self.keys, k)
        idx_c = np.minimum(idx, len(self.keys) - 1)
        ok = self.keys[idx_c] == k
        return np.where(ok, idx_c - self.nptr[np.asarray(p, np.int64)], -1)

    def base(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Value offset ``9 nptr[p] + 3 j(p, q)`` of the 3x3 block (p, q)."""
        j = self.node_positions(p, q)
        if np.any(j < 0):
            raise ValueError("node pair outside the sparsity pattern")
        return 9 * self.nptr[np.asarray(p, np.int64)] + 3 * j

    def dof_positions(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Value positions of dof entries (rows, cols); -1 where outside the pattern."""
        rows = np.asarray(rows, np.int64)
        cols = np.asarray(cols, np.int64)
        p, i = rows // 3, rows % 3
        q, k = cols // 3, cols % 3
        j = self.node_positions(p, q)
        pos = 9 * self.nptr[p] + i * self.rowstride[p] + 3 * j + k
        return np.where(j >= 0, pos, -1)

    def diagonal_positions(self) -> np.ndarray:
        d = np.arange(3 * self.n_nodes)
        return self.dof_positions(d, d)


def node_adjacency(n_nodes: int, cells: list[np.ndarray]) -> sp.csr_matrix:
    """Boolean node adjacency (incl. the diagonal) of the given cell arrays."""
    adj = sp.identity(n_nodes, dtype=np.int8, format="csr")
    for c in cells:
        if len(c) == 0:
            continue
        nc, k = c.shape
        inc = sp.csr_matrix((np.ones(nc * k, np.int8), c.reshape(-1), np.arange(0, nc * k + 1, k)),
                            shape=(nc, n_nodes))
        adj = adj + (inc.T @ inc)
    adj = adj.tocsr()
    adj.sort_indices()
    return adj


def build_pattern(adj: sp.csr_matrix) -> Pattern:
    """Node-blocked dof CSR pattern from a node adjacency matrix."""
    adj = adj.tocsr()
    adj.sort_indices()
    n = adj.shape[0]
    nptr = adj.indptr.astype(np.int64)
    nidx = adj.indices.astype(np.int64)
    deg = np.diff(nptr)
    rowlen = np.repeat(3 * deg, 3)
    indptr = np.zeros(3 * n + 1, np.int64)
    np.cumsum(rowlen, out=indptr[1:])
    # columns of a node row: 3q+k for q in row, k = 0..2; repeated for the 3 dof rows
    cols_node = (3 * nidx[:, None] + np.arange(3)[None, :]).reshape(-1)  # per node row block
    row_of = np.repeat(np.arange(n), deg)
    start = 3 * nptr[:-1]
    # for dof row (p, i): cols_node[3 nptr[p] : 3 nptr[p+1]]
    seg_idx = np.arange(3 * len(nidx))
    seg_node = np.repeat(np.arange(n), 3 * deg)
    local = seg_idx - start[seg_node]
    indices = np.empty(9 * len(nidx), np.int64)
    for i in range(3):
        # dof rows 3p+i: offset 9 nptr[p] + i * 3 deg(p) + local
        pos = 9 * nptr[seg_node] + i * 3 * deg[seg_node] + local
        indices[pos] = cols_node
    keys = row_of * n + nidx
    # one index dtype for indptr and indices, so scipy never copies them (the solver relies
    # on the matrix sharing the pattern arrays)
    idx_dtype = np.int32 if len(indices) < 2**31 - 1 else np.int64
    return Pattern(n, nptr, nidx, indptr.astype(idx_dtype), indices.astype(idx_dtype), 3 * deg, keys)


def element_bases(pattern: Pattern, cells: np.ndarray) -> np.ndarray:
    """``base[e, a, b]`` value offsets of the node blocks of each cell (E, k, k)."""
    k = cells.shape[1]
    p = np.repeat(cells, k, axis=1).reshape(-1)
    q = np.tile(cells, (1, k)).reshape(-1)
    return pattern.base(p, q).reshape(len(cells), k, k)


@dataclass
class AnpGroups:
    """Average-nodal-pressure groups: one per (node, material group) pair.

    ``of[e, i]`` is the group of element ``e``'s local node ``i``; ``vol0`` the group's
    reference volume ``V_g = sum V_e / 4`` (mm^3) and ``kappa`` its bulk modulus (MPa).
    ``sptr/snodes``: the nodes of each group; ``mptr/members``: its (e*4 + i) members.
    """

    of: np.ndarray
    vol0: np.ndarray
    kappa: np.ndarray
    sptr: np.ndarray
    snodes: np.ndarray
    mptr: np.ndarray
    members: np.ndarray
    pos: np.ndarray

    @property
    def n_groups(self) -> int:
        return len(self.vol0)


def anp_groups(tets: np.ndarray, vol: np.ndarray, kappa: np.ndarray, group: np.ndarray,
               n_nodes: int) -> AnpGroups:
    """Build the ANP groups of a tet mesh (vectorised)."""
    ne = len(tets)
    key = tets.astype(np.int64) * (int(group.max(initial=0)) + 1) + group[:, None]
    uniq, of = np.unique(key.reshape(-1), return_inverse=True)
    of = of.reshape(ne, 4)
    ng = len(uniq)
    vol0 = np.bincount(of.reshape(-1), weights=np.repeat(vol / 4.0, 4), minlength=ng)
    kap = np.zeros(ng)
    kap[of.reshape(-1)] = np.repeat(kappa, 4)
    # members sorted by group
    flat = of.reshape(-1)
    order = np.argsort(flat, kind="stable")
    mptr = np.zeros(ng + 1, np.int64)
    np.cumsum(np.bincount(flat, minlength=ng), out=mptr[1:])
    members = order.astype(np.int64)  # e*4 + i
    # node set of each group: unique (group, node) over member elements' nodes
    gm = np.repeat(flat[order], 4)
    nm = tets[members // 4].reshape(-1).astype(np.int64)
    gn = np.unique(gm * n_nodes + nm)
    sg, sn = gn // n_nodes, gn % n_nodes
    sptr = np.zeros(ng + 1, np.int64)
    np.cumsum(np.bincount(sg, minlength=ng), out=sptr[1:])
    # pos[e, i, a]: index of tets[e, a] within the node list of group of[e, i]
    g_ei = np.repeat(of.reshape(-1), 4)
    n_ea = np.tile(tets, (1, 4)).reshape(-1).astype(np.int64)
    loc = np.searchsorted(gn, g_ei * n_nodes + n_ea) - sptr[g_ei]
    pos = loc.reshape(ne, 4, 4).astype(np.int32)
    return AnpGroups(of, vol0, kap, sptr, sn, mptr, members, pos)


@dataclass
class SystemLayout:
    """CSR layout of the matrix the solver factorises.

    Plain P1: the tangent itself (``k_pos`` None).  ANP: the augmented system
    ``[[K, B^T], [B, -D]]`` of size 3N + G; ``k_pos`` maps the tangent's values into it,
    ``b_pos/bt_pos`` the entries of ``B`` (E*48, layout order of
    :func:`regtrack.mechanics.problem.evaluate`) and of ``B^T``, ``d_pos`` the diagonal of
    the pressure block; ``b_dest/bt_dest`` each distinct entry of ``B`` once and its
    transposed position (``B^T`` is filled by copying ``B``'s sums).
    """

    n: int
    indptr: np.ndarray
    indices: np.ndarray
    k_pos: np.ndarray | None = None
    b_rows: np.ndarray | None = None
    b_cols: np.ndarray | None = None
    b_pos: np.ndarray | None = None
    bt_pos: np.ndarray | None = None
    d_pos: np.ndarray | None = None
    b_dest: np.ndarray | None = None
    bt_dest: np.ndarray | None = None


def system_layout(pattern: Pattern, tets: np.ndarray, groups: AnpGroups | None) -> SystemLayout:
    """Build the solver matrix layout (see :class:`SystemLayout`) directly from the
    structure (no searching): a dof row ``3p+k`` holds the tangent's columns, then one
    pressure column ``3N+g`` per group containing node ``p`` (increasing ``g``); a pressure
    row ``3N+g`` holds the dofs of the group's nodes, then its diagonal."""
    n3 = 3 * pattern.n_nodes
    if groups is None:
        return SystemLayout(n3, pattern.indptr, pattern.indices)
    N, ng, ne = pattern.n_nodes, groups.n_groups, len(tets)
    scount = np.diff(groups.sptr)  # nodes per group
    # groups containing each node, in increasing g: stable sort of the (g, node) pairs by node
    pair_g = np.repeat(np.arange(ng), scount)
    by_node = np.argsort(groups.snodes, kind="stable")
    gcount = np.bincount(groups.snodes, minlength=N)
    gptr = np.zeros(N + 1, np.int64)
    np.cumsum(gcount, out=gptr[1:])
    rank = np.empty(len(pair_g), np.int64)
    rank[by_node] = np.arange(len(pair_g)) - gptr[groups.snodes[by_node]]
    kdeg = np.diff(pattern.indptr).astype(np.int64)  # 3 deg(p) per dof row
    rowlen = np.concatenate([kdeg + np.repeat(gcount, 3), 3 * scount + 1])
    indptr = np.zeros(n3 + ng + 1, np.int64)
    np.cumsum(rowlen, out=indptr[1:])
    indices = np.empty(indptr[-1], np.int64)
    # dof rows: tangent columns, then pressure columns
    kr = np.repeat(np.arange(n3), kdeg)
    k_pos = indptr[kr] + (np.arange(len(kr)) - pattern.indptr[kr].astype(np.int64))
    indices[k_pos] = pattern.indices
    gnode_sorted = pair_g[by_node]  # groups of node 0, then node 1, ...
    nodes_rep = np.repeat(np.arange(N), gcount)
    for k in range(3):
        r = 3 * nodes_rep + k
        pos = indptr[r] + kdeg[r] + (np.arange(len(r)) - gptr[nodes_rep])
        indices[pos] = n3 + gnode_sorted
    # pressure rows: dofs of the group's nodes, then the diagonal
    prow = n3 + pair_g
    local = np.arange(len(pair_g)) - groups.sptr[pair_g]
    for k in range(3):
        indices[indptr[prow] + 3 * local + k] = 3 * groups.snodes + k
    d_pos = indptr[n3 + np.arange(ng)] + 3 * scount
    indices[d_pos] = n3 + np.arange(ng)
    # B entries in evaluate() order: (e, i, a, k) -> row g = of[e, i], column 3 tets[e, a] + k
    g_ei = groups.of[:, :, None, None]
    loc = groups.pos[:, :, :, None].astype(np.int64)
    kk = np.arange(3)[None, None, None, :]
    b_pos = (indptr[n3 + g_ei] + 3 * loc + kk).reshape(-1)
    pair_idx = groups.sptr[g_ei] + loc  # index of (g, node a) in the group node lists
    node_a = tets[:, None, :, None]
    bt_pos = (indptr[3 * node_a + kk] + kdeg[3 * node_a + kk] + rank[pair_idx]).reshape(-1)
    b_rows = np.broadcast_to(groups.of[:, :, None, None], (ne, 4, 4, 3)).reshape(-1)
    b_cols = np.broadcast_to(3 * node_a + kk, (ne, 4, 4, 3)).reshape(-1)
    b_dest, first = np.unique(b_pos, return_index=True)
    idx_dtype = np.int32 if len(indices) < 2**31 - 1 else np.int64
    return SystemLayout(n3 + ng, indptr.astype(idx_dtype), indices.astype(idx_dtype), k_pos, b_rows, b_cols,
                        b_pos, bt_pos, d_pos, b_dest, bt_pos[first])

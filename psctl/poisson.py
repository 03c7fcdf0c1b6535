"""The linear solve behind normal integration (``psctl.depth``): a weighted graph Laplacian over
the valid pixels, one pinned pixel per connected component, solved by conjugate gradients with a
small smoothed-aggregation multigrid V-cycle as preconditioner.

Why not a direct solver: scipy has no sparse Cholesky, and its sparse LU is slow and
memory-hungry at millions of unknowns. Pure functions of arrays and a config dict (the keys of
``psctl.depth.DEFAULT_CONFIG``: cg_rtol, cg_maxiter, amg_*); scipy is imported where used.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy is imported where used
    from scipy.sparse import csr_matrix

__all__ = ["solve_laplacian", "solve_system", "laplacian", "laplacian_pattern", "pcg", "SmoothedAggregation"]


def solve_laplacian(npix: int, ei: np.ndarray, ej: np.ndarray, c: np.ndarray, b: np.ndarray, pins: np.ndarray,
                    coords: tuple[np.ndarray, np.ndarray], x0: np.ndarray | None, cfg: dict,
                    amg: "SmoothedAggregation | None" = None
                    ) -> tuple[np.ndarray, int, "SmoothedAggregation | None", bool]:
    """min sum_e c_e (z_j - z_i)^2 - 2 b_e (z_j - z_i), one pinned pixel per component.

    ``npix`` unknowns; edge e joins pixels ``ei[e]`` -> ``ej[e]`` [E] with weight ``c[e]`` and
    right-hand side ``b[e]`` [E]; ``pins``: one pixel per connected component (z_p = 0 there);
    ``coords``: (row, col) of each unknown [npix], for the multigrid's aggregates; ``x0``: a
    starting point [npix] or None.

    ``amg``: a preconditioner built for an earlier matrix of the same graph (any SPD
    preconditioner keeps CG correct; a stale one only costs iterations). Returns
    (z, cg iterations, preconditioner used, whether CG met cg_rtol)."""
    if len(ei) == 0:  # isolated pixels only
        return np.zeros(npix), 0, None, True
    return solve_system(laplacian(npix, ei, ej, c, pins), np.bincount(ej, b, npix) - np.bincount(ei, b, npix),
                        coords, x0, cfg, amg)


def solve_system(L: csr_matrix, rhs: np.ndarray, coords: tuple[np.ndarray, np.ndarray], x0: np.ndarray | None, cfg: dict,
                 amg: "SmoothedAggregation | None" = None, release_stale: bool = False
                 ) -> tuple[np.ndarray, int, "SmoothedAggregation | None", bool]:
    """``solve_laplacian`` from its matrix ``L`` (``laplacian``) and right-hand side ``rhs`` [npix]:
    a caller that has no more use for the edges' arrays frees them before the solve (poisson in
    ``psctl.depth.integrate``: with its other per-edge arrays, 4.2 -> 2.4 GB on 12 MP of normals).

    ``release_stale``: where ``amg`` is not good enough and a new one is built, empty ``amg`` first
    (its matrices go although the caller still holds it: two hierarchies, the old one with its
    own copy of the matrix, were alive at bilateral's peak). The caller must not use it again."""
    npix = L.shape[0]
    if npix <= cfg["amg_max_coarse"]:
        import scipy.linalg

        return scipy.linalg.solve(L.toarray(), rhs, assume_a="pos"), 0, None, True
    its = 0
    if amg is not None:  # try the old preconditioner for a few iterations first
        x0, its, done = pcg(L, rhs, amg, x0, cfg["cg_rtol"], cfg["amg_rebuild_iters"])
        if done:
            return x0, its, amg, True
        if release_stale:
            amg.release()
    amg = SmoothedAggregation(L, coords, cfg)
    z, more, done = pcg(L, rhs, amg, x0, cfg["cg_rtol"], cfg["cg_maxiter"])
    return z, its + more, amg, done


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    # einsum, not np.dot: OpenBLAS threads its dot product, and on a busy 2-core machine that is
    # 10x slower than a plain loop
    return float(np.einsum("i,i->", a, b))


def pcg(A: csr_matrix, b: np.ndarray, M: Callable[[np.ndarray], np.ndarray], x0: np.ndarray | None, rtol: float,
        maxiter: int) -> tuple[np.ndarray, int, bool]:
    """Preconditioned conjugate gradients until max_i |r_i| / a_ii <= rtol max_i |b_i| / a_ii.

    The stopping rule is per unknown (r_i / a_ii is how far a Jacobi step would move z_i), not
    on |r|: a pixel that bilateral weights have nearly cut loose has a tiny row, and a global
    residual norm would stop before that pixel has settled. Returns (x, iterations, converged).
    """
    dinv = 1.0 / A.diagonal()
    x = np.zeros_like(b) if x0 is None else x0.copy()
    r = b - A @ x
    tmp = np.empty_like(b)

    def scaled_max(v: np.ndarray) -> float:
        np.multiply(v, dinv, out=tmp)
        return float(np.max(np.abs(tmp, out=tmp)))

    stop = rtol * scaled_max(b)
    if scaled_max(r) <= stop:
        return x, 0, True
    y = M(r)
    p = y.copy()
    ry = _dot(r, y)
    del y  # (each iteration's y and q are let go before the next are made: two vectors fewer at the peak)
    for it in range(1, maxiter + 1):
        q = A @ p
        alpha = ry / _dot(p, q)
        x += np.multiply(p, alpha, out=tmp)
        r -= np.multiply(q, alpha, out=tmp)
        del q
        if scaled_max(r) <= stop:
            return x, it, True
        y = M(r)
        ry, ry_old = _dot(r, y), ry
        p *= ry / ry_old
        p += y
        del y
    return x, maxiter, False


def laplacian(npix: int, ei: np.ndarray, ej: np.ndarray, c: np.ndarray, pins: np.ndarray,
              pattern: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> csr_matrix:
    """Weighted graph Laplacian + 1 equation z_p = 0 per pinned pixel (weight: the mean degree).

    ``pattern``: ``laplacian_pattern(npix, ei, ej)``, to fill this graph's matrix again with other
    weights without the COO arrays and their conversion (the same matrix to the bit; it shares the
    pattern's index arrays, which nothing writes to)."""
    import scipy.sparse as sp

    diag = (np.bincount(ei, c, npix) + np.bincount(ej, c, npix)).astype(np.float64, copy=False)  # (no edge: int64 zeros)
    diag[pins] += max(float(diag.mean()), 1e-12)
    diag = np.maximum(diag, 1e-300)  # isolated pixels are pinned, so only a guard
    if pattern is not None:
        indptr, indices, slot = pattern
        e = len(c)
        data = np.zeros(len(slot))
        data[slot[:e]] = c
        data[slot[e:2 * e]] = c
        np.negative(data, out=data)  # -c in place (exact), not another edge array
        data[slot[2 * e:]] = diag
        return sp.csr_matrix((data, indices, indptr), shape=(npix, npix))
    rows = np.concatenate([ei, ej, np.arange(npix, dtype=ei.dtype)])  # (32-bit indices stay 32-bit)
    cols = np.concatenate([ej, ei, np.arange(npix, dtype=ei.dtype)])
    return sp.csr_matrix((np.concatenate([-c, -c, diag]), (rows, cols)), shape=(npix, npix))


def laplacian_pattern(npix: int, ei: np.ndarray, ej: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``laplacian``'s sparsity for the graph (ei, ej), for matrices of it with other weights:
    (indptr, indices, slot), slot[k] = where the k-th of the COO entries (edges i -> j, edges
    j -> i, the diagonal) lands in the matrix's data. 4 bytes an entry kept, to spare each later
    matrix 16 bytes an entry of COO arrays (bilateral builds one a round, while the last one and
    its multigrid are still alive). None where the graph repeats an edge (entries are summed)."""
    import scipy.sparse as sp

    nnz = 2 * len(ei) + npix
    itype = np.int32 if nnz < 2**31 - 1 else np.int64
    rows = np.concatenate([ei, ej, np.arange(npix, dtype=ei.dtype)])
    cols = np.concatenate([ej, ei, np.arange(npix, dtype=ei.dtype)])
    # laplacian's own conversion, with each entry's COO position as its value
    m = sp.csr_matrix((np.arange(nnz, dtype=itype), (rows, cols)), shape=(npix, npix))
    del rows, cols
    if m.nnz != nnz:
        return None
    slot = np.empty(nnz, itype)
    slot[m.data] = np.arange(nnz, dtype=itype)
    return m.indptr, m.indices, slot


class SmoothedAggregation:
    """A V-cycle of smoothed-aggregation multigrid, used as the CG preconditioner.

    Aggregates: within each 3 x 3 block of a level's grid, the nodes joined by strong couplings
    (so a depth jump that bilateral weights have cut is never averaged over). Prolongation
    P = (I - omega D^-1 A) P0 with P0 the aggregates' indicator; coarse A = P^T A P; damped
    Jacobi smoothing (symmetric, so the V-cycle is a valid CG preconditioner).
    ``coords``: (row, col) of each unknown on the pixel grid.
    """

    def __init__(self, A, coords: tuple[np.ndarray, np.ndarray], cfg: dict):
        import scipy.sparse as sp
        import scipy.sparse.linalg as sla

        self.sweeps = cfg["amg_sweeps"]
        self.levels = []
        while A.shape[0] > cfg["amg_max_coarse"]:
            n = A.shape[0]
            agg, coarse_coords = _aggregate(A, coords, cfg["amg_strength"])
            nc = int(agg.max()) + 1
            if nc > 0.8 * n:  # coarsening has stalled (very sparse or cut-up graph): stop here
                break
            dinv = 1.0 / A.diagonal()
            omega = (4.0 / 3.0) / _jacobi_radius_bound(A, dinv)
            P0 = sp.csr_matrix((np.ones(n), (np.arange(n), agg)), shape=(n, nc))
            # copied: the difference's arrays have room for both operands' entries (a third more)
            P = (P0 - sp.diags(omega * dinv) @ (A @ P0)).tocsr().copy()
            del P0
            # the restriction R = P^T is P's arrays read by column (csc_matvec sums each coarse entry
            # over the fine ones in the same order as R's csr_matvec: the same numbers), not a copy
            self.levels.append((A, omega * dinv, P, P.T))
            R = P.T.tocsr()  # a csr R for the Galerkin product only: as before
            A, coords = (R @ (A @ P)).tocsr(), coarse_coords
            del R
        # sparse LU: single-threaded and tiny here (a dense Cholesky calls multithreaded BLAS,
        # which is slow on a busy 2-core machine); also copes when coarsening stalled early
        self.coarse = sla.splu(A.tocsc()).solve

    def __call__(self, b: np.ndarray) -> np.ndarray:
        return self._vcycle(0, b)

    def release(self) -> None:
        """Let go of the levels' matrices (``solve_system``'s release_stale); unusable after."""
        self.levels, self.coarse = [], None

    def _vcycle(self, k: int, b: np.ndarray) -> np.ndarray:
        if k == len(self.levels):
            return self.coarse(b)
        A, wd, P, R = self.levels[k]

        def residual(x: np.ndarray) -> np.ndarray:  # b - A x in A x's own array (one temporary)
            t = A @ x
            return np.subtract(b, t, out=t)

        x = wd * b
        for _ in range(self.sweeps - 1):
            x += _scaled(residual(x), wd)
        x += P @ self._vcycle(k + 1, R @ residual(x))
        for _ in range(self.sweeps):
            x += _scaled(residual(x), wd)
        return x


def _scaled(t: np.ndarray, wd: np.ndarray) -> np.ndarray:
    t *= wd
    return t


def _jacobi_radius_bound(A, dinv: np.ndarray) -> float:
    """Gershgorin bound on the spectral radius of D^-1 A (2 for a graph Laplacian)."""
    absrow = np.asarray(abs(A).sum(axis=1)).ravel()
    return float(np.max(absrow * dinv))


def _aggregate(A, coords: tuple[np.ndarray, np.ndarray], theta: float):
    """Aggregates: connected groups of strongly coupled nodes (-a_ij >= theta sqrt(a_ii a_jj))
    inside each 3 x 3 block of the nodes' (row, col) grid coordinates.

    Returns (aggregate of each node, (row, col) of each aggregate on the next, coarser grid)."""
    import scipy.sparse as sp
    import scipy.sparse.csgraph as csgraph

    r, c = coords
    n = A.shape[0]
    # A's entries in its own order (as A.tocoo() gives them, without copying A), tested a slice at a
    # time: the whole test's temporaries took several arrays of A's size at the solve's peak
    j, v = A.indices, A.data
    i = np.repeat(np.arange(n, dtype=j.dtype), np.diff(A.indptr))
    d = A.diagonal()
    keep = np.empty(len(v), bool)
    for s in range(0, len(v), 1 << 20):
        ii, jj = i[s:s + (1 << 20)], j[s:s + (1 << 20)]
        keep[s:s + (1 << 20)] = ((ii != jj) & (-v[s:s + (1 << 20)] >= theta * np.sqrt(d[ii] * d[jj]))
                                 & (r[ii] // 3 == r[jj] // 3) & (c[ii] // 3 == c[jj] // 3))
    graph = sp.csr_matrix((np.ones(int(keep.sum()), np.int8), (i[keep], j[keep])), shape=(n, n))
    _, agg = csgraph.connected_components(graph, directed=False)
    first = np.unique(agg, return_index=True)[1]
    return agg, (r[first] // 3, c[first] // 3)

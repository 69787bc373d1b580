"""View-factor operators: the exact sparse matrix and a hierarchically compressed one, one interface.

Both are :class:`ViewFactorOperator` objects: ``F @ x`` (= :meth:`~ViewFactorOperator.matvec`, x of
shape (n,) or (n, k)), :meth:`~ViewFactorOperator.rmatvec` (``F^T y``), :meth:`~ViewFactorOperator.row_sums`,
``shape``, ``nbytes``.  ``F[i, j]`` is the fraction of the radiation leaving facet ``i`` that reaches
facet ``j``, and the irradiance on ``i`` from exitances ``B`` [W m-2] is ``(F @ B)_i``
(:mod:`crater_thermal.viewfactors`).

Compressed operator (``method = "compressed"``)
----------------------------------------------
What is stored is the symmetric matrix ``G = diag(A) F`` (``G_ij = A_i A_j K_ij`` [m2], reciprocity is
its symmetry), in blocks of a hierarchical partition:

* **Cluster tree.** A kd-tree on the facet centroids (median split of the longest bounding-box side)
  down to :data:`LEAF_SIZE` facets; facets are renumbered so that every cluster is an index range.
* **Block partition.** Starting from (root, root), a pair of clusters ``(s, t)`` is *admissible* (far)
  when the distance between their centroid bounding boxes is at least ``max(diam_s, diam_t) /``
  :data:`ADMISSIBILITY` and at least ``NEAR_DISTANCE_FACTOR`` facet sizes (so that every pair of it is a
  far pair of the exact matrix, centroid kernel); otherwise both clusters are split.  Non-admissible
  leaf pairs are *near blocks*.
* **Near blocks** are computed exactly like the exact matrix (near-pair quadrature, one visibility ray
  per candidate pair) and kept as sparse entries.
* **Far blocks** are computed once, entry by entry (centroid kernel, one visibility ray per facing pair,
  at most :data:`MAX_BLOCK_ENTRIES` entries at a time) and compressed right away by adaptive cross
  approximation with full pivoting (the block is in memory, so the residual and its Frobenius norm are
  exact at every step): crosses are added until ``||M - U V^T||_F <= tolerance * ||M||_F``, then the
  factors are recompressed to the shortest truncated SVD whose exact error against ``M`` is still within
  that bound (:func:`_recompress`; crosses are not orthogonal).  The factors are stored as int16, each
  column scaled to the int16 range, with one float32 weight per term (``U D V^T``, :func:`_quantized`;
  half the bytes of float32 factors, issue 24): the truncation leaves 2 % of the block's squared budget
  to that rounding, and the stored block's error against ``M`` is computed exactly and must stay within
  the whole budget (else the truncation is redone with half, then the block is split).  The factors
  are kept when they take less memory than the block's non-zeros would as sparse entries; otherwise the
  block is split
  into its children blocks (reusing the computed entries, no new rays) and, at leaf level, kept sparse.
  All-zero blocks (facets that face away from each other, coplanar plains, fully occluded pairs) cost
  nothing.
* **Occlusion proved, not traced** (:data:`OCCLUSION_PROOF`, issue 24). On a mesh that is a height field
  (:class:`_HeightFloor`: every facet facing up, no two facets over the same point), a lower bound of
  the terrain per cell of half a facet's size lets a far block, then its children's pairs down to
  :data:`PROOF_MIN_PAIRS` pairs, be proven occluded: on one of :data:`PROOF_CUTS` lines across the
  corridor between the two clusters, the terrain's bound everywhere a segment between them can cross
  exceeds the highest that segment can be there (the clusters' xy discs and highest points bound it).
  A segment that starts and ends above the surface and passes below it crosses it, so no ray is traced
  for those pairs; the rest of the block is traced as before. The operator is the same, bit for bit
  (tested): only the rays are fewer, about 45 % fewer at 20k facets of rough crater terrain.

Row-relative variant (``tolerance_mode="row"``, issue 24): each far block's budget is instead a share
of ``tolerance`` times the row sums of the rows it touches (:meth:`_Builder.budget`; row sums estimated
with :data:`ROWSUM_RAYS` cosine-weighted rays per facet), so blocks of tiny grazing entries get a loose
budget: low rank, their smallest sparse entries dropped, or dropped whole.  Not the default: measured
against the exact matrix in ``docs/performance.md`` (memory, F x error, night temperatures).

Row blocks (a distributed run's workers, :mod:`crater_thermal.cluster_run`): some rows of the operator
held alone (:class:`RowBlock`), loaded from a saved operator (:func:`save_operator`,
:func:`load_row_block`) or built from the mesh without the rest (:class:`CompressedPlan`: the tree, the
partition and the work units, deterministic from the mesh; :meth:`CompressedPlan.row_block` builds the
blocks that meet the rows, so a block meeting two row ranges is built for both); the rescale below then
needs every row's sum (:func:`rowsum_scale`, :meth:`RowBlock.with_scale`).

Error control: every far block satisfies ``||M - M~||_F <= tol ||M||_F`` and near blocks are exact, so
``||G - G~||_F <= tol ||G||_F``; products with the smooth, positive fields the model uses (emitted IR,
scattered sunlight) come out far more accurate than this bound (measured in
``bench/viewfactor_operator.py``).  Reciprocity ``A_i F_ij = A_j F_ji`` is exact by construction (only
blocks above the diagonal are stored; the lower ones are their transposes).  Row sums ``F @ 1`` are those
of the exact matrix to the tolerance; if any exceeds 1 (closed cavities, discretisation), ``G`` is
scaled to ``D G D`` with ``d_i = min(1, 1 / rowsum_i)``, which keeps the symmetry and every row sum
<= 1 (the exact matrix uses ``min(s_i, s_j)``; both only act on rows above 1).

Cost: memory and product cost grow like the number of stored entries: near blocks O(N * LEAF_SIZE),
far blocks O(N log N * rank) when visibility is smooth.  On crater terrain occlusion raises the ranks
with block size, and blocks above MAX_BLOCK_ENTRIES are split, so memory grows faster than N log N (about
N^1.75 on the generator's crater terrain from 25k to 100k facets; the measured sizes and build times
against the exact matrix are in ``docs/performance.md``); the build evaluates every facing pair once
(rays like the exact matrix, O(N^2) time, but never more than one block of entries in memory per thread)
plus the cross
approximation and its recompression (O(entries * rank)).  Products run in numba
(:mod:`crater_thermal.kernels.vfoperator`), one pass over the stored entries per product, for any
number of right-hand sides at once, split between :data:`PRODUCT_THREADS` threads (rows of the sparse
part and runs of low-rank blocks balanced by stored entries, each thread adding into its own array), with
several right-hand sides in :data:`PRODUCT_DTYPE` arithmetic.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from crater_thermal import io
from crater_thermal.choices import VIEW_FACTOR_METHODS as METHODS
from crater_thermal.errors import ConfigError, InternalError, MeshError
from crater_thermal.geometry import Mesh
from crater_thermal.pools import process_pool

__all__ = [
    "METHODS",
    "DEFAULT_TOLERANCE",
    "TOLERANCE_MODES",
    "AUTO_COMPRESSED_MIN_FACETS",
    "ViewFactorOperator",
    "SparseViewFactors",
    "CompressedViewFactors",
    "as_operator",
    "compressed_view_factors",
    "view_factor_operator",
]

# METHODS ("auto", "exact", "compressed"), the accepted ``view_factors`` methods, is declared in
# crater_thermal.choices (the case schema's list) and re-exported here.
#: Default relative Frobenius tolerance of each compressed far block (the case schema's default too).
DEFAULT_TOLERANCE = 1e-3
#: ``"auto"`` uses the compressed operator from this many facets on (exact below).  Measured
#: (bench/viewfactor_operator.py): at 10k facets the exact matrix builds in about half the CPU time but
#: takes 6x the memory (9x at 25k), and above 8,000 facets its scattering solve is a sparse LU of a
#: matrix with 0.05-0.12 N^2 non-zeros; below, the exact matrix and its dense LU are cheaper.
AUTO_COMPRESSED_MIN_FACETS = 10_000
#: Far-block error control: ``"block"`` (each block to ``tolerance`` of its own norm, the default) or
#: ``"row"`` (to ``tolerance`` of the row sums of the rows it touches; :func:`compressed_view_factors`).
TOLERANCE_MODES = ("block", "row")
#: Cosine-weighted rays per facet of the row-sum estimate behind ``tolerance_mode="row"``.
ROWSUM_RAYS = 64
#: Facets per leaf cluster of the kd-tree.
LEAF_SIZE = 32
#: Admissibility: far when ``max(diam_s, diam_t) <= ADMISSIBILITY * distance``.
ADMISSIBILITY = 1.0
#: Largest far block computed at once (entries; 8 bytes each plus rays).
MAX_BLOCK_ENTRIES = 1 << 21
#: Rays traced per call.
RAY_CHUNK = 1 << 19
#: Near blocks per work unit (candidate pairs).
NEAR_BATCH_PAIRS = 1 << 18
#: Threads per product (the numba kernels release the GIL; each thread adds its share of the stored
#: entries into its own array, the arrays are summed).
PRODUCT_THREADS = max(1, min(os.cpu_count() or 1, 8))
#: Multiply-adds (stored entries x right-hand sides) below which a product stays on one thread.  The
#: pool's threads are kept, so a split costs little; the threshold was set by timing products on the
#: generator crater at 5k and 10k facets (docs/performance.md).
PARALLEL_MIN_WORK = 500_000
#: Arithmetic of the products with several right-hand sides (the stored values are float32 or int16 either way;
#: inputs and results stay float64; one right-hand side is always float64). float32: 1.57x faster with 64
#: right-hand sides at 30k facets, each facet within 3.2e-6 of its float64 product (docs/performance.md),
#: far below the operator's own error (its tolerance 1e-3; ~1e-4 measured against the exact matrix).
#: np.float64 gives the float64 products.
PRODUCT_DTYPE = np.float32
#: Largest magnitude of a stored low-rank factor's int16 numbers (each column scaled to it).
QUANT_MAX = 32767
#: Shares of a far block's error budget left to its truncated SVD before the factors are rounded to int16
#: (the stored block's exact error must stay within the whole budget; the second share is a retry).
QUANT_SHARES = (0.98, 0.5)
#: Seconds between the checkpoints of a resumable build (:func:`compressed_view_factors` ``resume_dir``).
CHECKPOINT_S = 30.0
#: A run's compressed operator whose build took at least this long [s] is kept in its view-factor cache
#: (:func:`view_factor_operator`): 100k facets build in ~2 minutes and are rebuilt; 400k take ~34 minutes
#: and are kept (~2.4 GB on disk), 1M would take hours.
KEEP_BUILD_S = 600.0
#: Bytes per low-rank number that the choice between a far block's factors and its sparse entries
#: (8 bytes each) assumes.
LOWRANK_CHOICE_BYTES = 4
#: Part of the cache key of a compressed operator: bump it when the numbers change.
ALGORITHM_VERSION = "c3"
#: Prove far sub-blocks occluded by the terrain before tracing them (:class:`_HeightFloor`), on meshes
#: that are height fields; the operator is the same, with fewer rays.
OCCLUSION_PROOF = True
#: Lines across the corridor between two clusters tried by the proof, and the smallest sub-block (pairs)
#: it is tried on.
PROOF_CUTS = 16
PROOF_MIN_PAIRS = 256


# --------------------------------------------------------------------------------------------- interface


class ViewFactorOperator:
    """A linear operator ``x -> F x`` on per-facet fields (see the module docstring).

    Subclasses implement :meth:`matvec`, :meth:`rmatvec`, :attr:`nbytes`; ``F @ x`` calls
    :meth:`matvec`.
    """

    kind = "abstract"
    shape: tuple[int, int]
    #: Largest ``rowsum - 1`` before the rescaling that keeps row sums <= 1 (0 if none was needed).
    rowsum_excess: float = 0.0
    #: True where :meth:`submit` returns before its product is made (the products run elsewhere, on a
    #: cluster's workers): a caller with independent products then keeps two in flight.
    asynchronous = False

    @property
    def n_facets(self) -> int:
        return int(self.shape[0])

    def matvec(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        """``F x`` for x of shape (n,) or (n, k) [any unit]; same shape back."""
        raise NotImplementedError

    def rmatvec(self, y: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        """``F^T y`` for y of shape (n,) or (n, k); same shape back."""
        raise NotImplementedError

    @property
    def nbytes(self) -> int:  # pragma: no cover - interface
        """Bytes held by the operator's arrays."""
        raise NotImplementedError

    @property
    def is_zero(self) -> bool:
        """True when no facet sees any other (flat ground): no exchange at all."""
        raise NotImplementedError  # pragma: no cover

    def row_sums(self) -> np.ndarray:
        """(n,) float [-]: ``sum_j F_ij``, the fraction of facet i's emission that stays in the scene."""
        return self.matvec(np.ones(self.shape[0]))

    def __matmul__(self, x):
        return self.matvec(x)

    def submit(self, x: np.ndarray):
        """``F x`` begun (``x`` as for :meth:`matvec`): an object whose ``result()`` is the product. Made at
        once here; an :attr:`asynchronous` operator returns while its product runs elsewhere."""
        return _Made(self.matvec(x))

    def _check(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if x.ndim not in (1, 2) or x.shape[0] != self.shape[1]:
            raise ConfigError(
                f"view-factor product: operand has shape {x.shape}; expected ({self.shape[1]},) or ({self.shape[1]}, k)"
            )
        return x


class _Made:
    """A product made at once (:meth:`ViewFactorOperator.submit`)."""

    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


class SparseViewFactors(ViewFactorOperator):
    """The exact sparse matrix (:func:`crater_thermal.viewfactors.view_factor_matrix`) as an operator.

    Parameters
    ----------
    F : (n, n) scipy.sparse matrix [-]
    """

    kind = "exact"

    def __init__(self, F):
        self.matrix = sp.csr_matrix(F, dtype=np.float64)
        if self.matrix.shape[0] != self.matrix.shape[1]:
            raise ConfigError(f"view-factor matrix has shape {self.matrix.shape}; expected square (nf, nf)")
        self.shape = self.matrix.shape
        self.rowsum_excess = float(getattr(F, "rowsum_excess", 0.0))
        self._T = None

    def matvec(self, x):
        return np.asarray(self.matrix @ self._check(x))

    def rmatvec(self, y):
        if self._T is None:
            self._T = self.matrix.T.tocsr()
        return np.asarray(self._T @ self._check(y))

    @property
    def nbytes(self) -> int:
        m = self.matrix
        return int(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes)

    @property
    def is_zero(self) -> bool:
        return self.matrix.nnz == 0

    @property
    def nnz(self) -> int:
        return int(self.matrix.nnz)


def as_operator(F) -> ViewFactorOperator:
    """``F`` as a :class:`ViewFactorOperator` (sparse or dense arrays are wrapped as exact matrices)."""
    if isinstance(F, ViewFactorOperator):
        return F
    if sp.issparse(F):
        return SparseViewFactors(F)
    a = np.asarray(F, dtype=float)
    if a.ndim != 2:
        raise ConfigError(f"view-factor matrix has shape {a.shape}; expected (nf, nf)")
    return SparseViewFactors(sp.csr_matrix(a))


class CompressedViewFactors(ViewFactorOperator):
    """Hierarchically compressed view factors (module docstring); build with :func:`compressed_view_factors`.

    Attributes
    ----------
    tolerance : float [-]
        Relative Frobenius tolerance of each far block.
    stats : dict
        Build statistics: block counts, ranks, stored entries, seconds.
    """

    kind = "compressed"

    def __init__(self, perm, areas, sparse, lowrank, scale, tolerance, stats):
        n = len(perm)
        self.shape = (n, n)
        self.perm = np.ascontiguousarray(perm, np.int64)
        self.areas_perm = np.ascontiguousarray(areas[self.perm], np.float64)
        self.indptr, self.indices, self.data = sparse
        (self.r0, self.r1, self.c0, self.c1, self.rank, self.uoff, self.voff, self.woff, self.U, self.V, self.W) = (
            lowrank
        )
        self.scale = scale  # None or (n,) in cluster order
        self.tolerance = float(tolerance)
        self.stats = dict(stats)
        self._max_rank = int(self.rank.max()) if len(self.rank) else 1
        self._split: list | None = None
        self._entries = 0
        #: arithmetic of this operator's products (:data:`PRODUCT_DTYPE`)
        self.product_dtype = PRODUCT_DTYPE

    @property
    def nbytes(self) -> int:
        arrs = [
            self.perm,
            self.areas_perm,
            self.indptr,
            self.indices,
            self.data,
            self.r0,
            self.r1,
            self.c0,
            self.c1,
            self.rank,
            self.uoff,
            self.voff,
            self.woff,
            self.U,
            self.V,
            self.W,
        ]
        if self.scale is not None:
            arrs.append(self.scale)
        return int(sum(a.nbytes for a in arrs))

    @property
    def is_zero(self) -> bool:
        return len(self.data) == 0 and len(self.rank) == 0

    def _parts(self, k: int) -> list[tuple[int, int, int, int]]:
        """Work split of a product with k right-hand sides between threads: (row range of the sparse
        part, range of low-rank blocks) per thread, balanced by stored entries; a single part when the
        product is smaller than :data:`PARALLEL_MIN_WORK`."""
        nr, nb = len(self.indptr) - 1, len(self.rank)
        if self._split is None:
            lr_work = (self.r1 - self.r0 + self.c1 - self.c0) * self.rank.astype(np.int64)
            self._entries = int(self.indptr[-1]) + int(lr_work.sum())
            nt = PRODUCT_THREADS
            if nt == 1:
                self._split = [(0, nr, 0, nb)]
            else:
                q = np.arange(1, nt) / nt
                rows = np.searchsorted(self.indptr, q * self.indptr[-1])
                cum = np.cumsum(lr_work)
                blocks = np.searchsorted(cum, q * (cum[-1] if nb else 0))
                rb = [0, *np.minimum(rows, nr).tolist(), nr]
                bb = [0, *np.minimum(blocks, nb).tolist(), nb]
                self._split = [(rb[t], rb[t + 1], bb[t], bb[t + 1]) for t in range(nt)]
        if self._entries * k < PARALLEL_MIN_WORK:
            return [(0, nr, 0, nb)]
        return self._split

    def _apply_part(self, X: np.ndarray, part) -> np.ndarray:
        """One thread's share of ``G X`` (X (n, k) in cluster order), into a fresh array."""
        from crater_thermal.kernels import vfoperator as kv

        i0, i1, b0, b1 = part
        b = slice(b0, b1)
        lr = (
            *(x[b] for x in (self.r0, self.r1, self.c0, self.c1, self.rank, self.uoff, self.voff, self.woff)),
            self.U,
            self.V,
            self.W,
        )
        Y = np.zeros_like(X)
        if X.shape[1] == 1:
            x1, y1 = np.ascontiguousarray(X[:, 0]), np.zeros(X.shape[0], X.dtype)
            kv.sym_sparse_matvec1(self.indptr, self.indices, self.data, x1, y1, i0, i1)
            if b1 > b0:
                kv.lowrank_matvec1(*lr, x1, y1, np.empty(2 * self._max_rank, X.dtype))
            Y[:, 0] = y1
        else:
            kv.sym_sparse_matvec(self.indptr, self.indices, self.data, X, Y, i0, i1)
            if b1 > b0:
                kv.lowrank_matvec(*lr, X, Y, np.empty((2 * self._max_rank, X.shape[1]), X.dtype))
        return Y

    def _apply_G(self, X: np.ndarray) -> np.ndarray:
        """``G X`` for X (n, k) in cluster order (D G D when rescaled); the kernels release the GIL,
        so the parts of :meth:`_parts` run on threads and their sums are added."""
        if self.scale is not None:
            X = X * self.scale[:, None]
        # several right-hand sides in the products' arithmetic (PRODUCT_DTYPE); one in float64 (float32 was
        # no faster there: 0.95x at 30k facets, bench/operator_products.py)
        X = np.ascontiguousarray(X, self.product_dtype if X.shape[1] > 1 else np.float64)
        parts = self._parts(X.shape[1])
        if len(parts) == 1:
            Y = self._apply_part(X, parts[0])
        else:
            # a pool kept for the process: starting threads per product costs ~0.1 ms
            Ys = list(process_pool("vfproduct", len(parts)).map(lambda part: self._apply_part(X, part), parts))
            Y = Ys[0]
            for other in Ys[1:]:
                Y += other
        Y = Y.astype(np.float64, copy=False)
        if self.scale is not None:
            Y *= self.scale[:, None]
        return Y

    def matvec(self, x):
        x = self._check(x)
        X = np.ascontiguousarray(x.reshape(x.shape[0], -1)[self.perm])
        Y = self._apply_G(X)
        Y /= self.areas_perm[:, None]
        out = np.empty_like(Y)
        out[self.perm] = Y
        return out.reshape(x.shape)

    def rmatvec(self, y):
        y = self._check(y)
        Y = np.ascontiguousarray(y.reshape(y.shape[0], -1)[self.perm]) / self.areas_perm[:, None]
        X = self._apply_G(Y)
        out = np.empty_like(X)
        out[self.perm] = X
        return out.reshape(y.shape)


# --------------------------------------------------------------------------------------------- cluster tree


class _Tree:
    """kd-tree on points: node ranges in the permuted order, bounding boxes, children (-1 for leaves)."""

    def __init__(self, C: np.ndarray, S: np.ndarray, leaf: int):
        n = C.shape[0]
        self.perm = np.arange(n)
        lo, hi, left, right = [], [], [], []

        def build(a, b):
            k = len(lo)
            lo.append(a)
            hi.append(b)
            left.append(-1)
            right.append(-1)
            if b - a > leaf:
                idx = self.perm[a:b]
                pts = C[idx]
                axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
                mid = (b - a) // 2
                part = np.argpartition(pts[:, axis], mid)
                self.perm[a:b] = idx[part]
                left[k] = build(a, a + mid)
                right[k] = build(a + mid, b)
            return k

        build(0, n)
        self.lo = np.array(lo)
        self.hi = np.array(hi)
        self.left = np.array(left)
        self.right = np.array(right)
        Cp = C[self.perm]
        Sp = S[self.perm]
        m = len(lo)
        self.bmin = np.empty((m, 3))
        self.bmax = np.empty((m, 3))
        self.smax = np.empty(m)
        for k in range(m):
            seg = Cp[self.lo[k] : self.hi[k]]
            self.bmin[k] = seg.min(axis=0)
            self.bmax[k] = seg.max(axis=0)
            self.smax[k] = Sp[self.lo[k] : self.hi[k]].max()
        self.diam = np.linalg.norm(self.bmax - self.bmin, axis=1)

    def size(self, k) -> int:
        return int(self.hi[k] - self.lo[k])

    def is_leaf(self, k) -> bool:
        return self.left[k] < 0

    def children(self, k):
        return (int(self.left[k]), int(self.right[k])) if self.left[k] >= 0 else (int(k),)

    def distance(self, s, t) -> float:
        gap = np.maximum(0.0, np.maximum(self.bmin[t] - self.bmax[s], self.bmin[s] - self.bmax[t]))
        return float(np.sqrt(gap @ gap))


class _HeightFloor:
    """A lower bound of the terrain's height on a grid of cells, for proving far sub-blocks occluded
    (:func:`kernels.vfoperator.hidden`): every segment between two clusters that passes below a
    continuous height field, starting and ending above it, crosses it.

    Only for meshes that are height fields: every facet faces up (normal z > 0), every edge is shared by
    at most two facets, and no cell centre lies inside two facets' xy projections. Per cell
    the lowest vertex of the facets that meet it; cells that the mesh's boundary
    meets, or that no facet meets, have no bound (-inf). Cells are half a facet's size, so that a cell's
    bound comes from the few facets around it.
    """

    def __init__(self, x0, y0, h, floor, tree, cx, cy, rho, ztop, margin):
        self.x0, self.y0, self.h, self.floor = x0, y0, h, floor
        self.tree, self.cx, self.cy, self.rho, self.ztop, self.margin = tree, cx, cy, rho, ztop, margin

    @classmethod
    def of(cls, mesh: Mesh, V: np.ndarray, P: np.ndarray, tree: "_Tree") -> "_HeightFloor | None":
        """The floor of ``mesh`` (vertices ``V`` and ray origins ``P`` [m] in the tracer's centred frame,
        ``P`` in cluster order), or None when the mesh is not a height field."""
        from crater_thermal.kernels import vfoperator as kv

        faces = np.ascontiguousarray(mesh.faces, np.int64)
        if len(faces) < 2 or not bool(np.all(np.asarray(mesh.normals)[:, 2] > 1e-6)):
            return None
        # undirected edges as one integer each (as geometry's mesh check codes them): np.unique on codes
        # instead of on rows takes a few ms rather than ~0.15 s at 100k facets
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        nv = np.int64(len(V))
        codes, count = np.unique(edges[:, 0] * nv + edges[:, 1], return_counts=True)
        if count.max() > 2:
            return None
        boundary = np.column_stack(np.divmod(codes[count == 1], nv))  # edges of one facet: (a, b), a < b
        h = 0.5 * float(np.sqrt(2.0 * np.median(mesh.areas)))  # half a grid step of a triangulated grid
        lo, hi = V[:, :2].min(axis=0), V[:, :2].max(axis=0)
        nx, ny = (int(np.floor(w / h)) + 1 for w in hi - lo)
        if h <= 0.0 or nx * ny > 64 * len(faces) + 1024:  # a few long thin facets: no useful grid
            return None
        zmin = np.full((ny, nx), np.inf)
        cover = np.zeros((ny, nx), np.int32)
        kv.height_floor(V, faces, float(lo[0]), float(lo[1]), h, nx, ny, zmin, cover)
        if cover.max() > 1:
            return None
        kv.floor_unknown(V, boundary, float(lo[0]), float(lo[1]), h, nx, ny, zmin)
        zmin[~np.isfinite(zmin)] = -np.inf
        k = len(tree.lo)
        cx, cy, rho, ztop = (np.empty(k) for _ in range(4))
        kv.node_discs(tree.lo, tree.hi, P, cx, cy, rho, ztop)
        # float32 rays: a segment must pass clearly below the bound (1e-5 of the extent; 0.2 m over 20 km)
        margin = max(1e-3, 1e-5 * float(np.max(hi - lo)))
        return cls(float(lo[0]), float(lo[1]), h, zmin, tree, cx, cy, rho, ztop, margin)

    def unproven(self, s: int, t: int) -> np.ndarray:
        """Rows ``(r0, r1, c0, c1)`` (cluster order) covering the far block (s, t) less its sub-blocks
        proven occluded."""
        from crater_thermal.kernels import vfoperator as kv

        tr = self.tree
        out = np.empty((tr.size(s) * tr.size(t) // 16 + 4, 4), np.int64)
        k = kv.unproven_rects(
            s, t, tr.left, tr.right, tr.lo, tr.hi, self.cx, self.cy, self.rho, self.ztop,
            self.x0, self.y0, self.h, self.floor, PROOF_CUTS, self.margin, PROOF_MIN_PAIRS, out,
        )  # fmt: skip
        if k < 0:  # more rectangles than room for them (cannot happen with leaves of 16 facets or more)
            return np.array([[tr.lo[s], tr.hi[s], tr.lo[t], tr.hi[t]]], np.int64)
        return out[:k]


def _partition(tree: _Tree, near_factor: float, admissibility: float, max_entries: int):
    """Upper-triangle block partition: (far blocks [(s, t)], near blocks [(s, t, diagonal)])."""
    far, near = [], []
    stack = [(0, 0)]
    while stack:
        s, t = stack.pop()
        if s == t:
            if tree.is_leaf(s):
                near.append((s, s, True))
            else:
                a, b = tree.children(s)
                stack += [(a, a), (a, b), (b, b)]
            continue
        d = tree.distance(s, t)
        adm = (
            d > 0.0
            and max(tree.diam[s], tree.diam[t]) <= admissibility * d
            and d >= near_factor * max(tree.smax[s], tree.smax[t])
        )
        if adm and tree.size(s) * tree.size(t) <= max_entries:
            far.append((s, t))
            continue
        if tree.is_leaf(s) and tree.is_leaf(t):
            if adm:
                far.append((s, t))
            else:
                near.append((s, t, False))
            continue
        # split the larger cluster (both when of similar size)
        cs, ct = tree.children(s), tree.children(t)
        if len(cs) > 1 and len(ct) > 1 and 0.5 <= tree.size(s) / tree.size(t) <= 2.0:
            stack += [(a, b) for a in cs for b in ct]
        elif len(cs) > 1 and (tree.size(s) >= tree.size(t) or len(ct) == 1):
            stack += [(a, t) for a in cs]
        else:
            stack += [(s, b) for b in ct]
    return far, near


# --------------------------------------------------------------------------------------------- compression


def _recompress(U: np.ndarray, V: np.ndarray, R: np.ndarray, budget: float) -> tuple[np.ndarray, np.ndarray]:
    """The shortest truncated SVD of a cross approximation ``U V^T`` whose exact error stays in budget.

    ``U`` (m, r), ``V`` (n, r): the factors found by :func:`~crater_thermal.kernels.vfoperator.aca_full`
    for a block ``M``; ``R = M - U V^T`` its residual (in memory); ``budget`` [m4]: the allowed
    ``||M - M~||_F^2``.  The error of each truncation is exact, not bounded
    (:func:`~crater_thermal.kernels.vfoperator.recompress`: the SVD through the QR factors of U and V,
    O((m + n) r^2), and one product ``R B``, O(m n r), about one cross of the approximation).
    Full-pivot crosses are not orthogonal, so the SVD usually needs fewer terms for the same bound:
    12-23 % fewer stored numbers on the 20k-facet site and crater, 14 % less memory at 100k.  Returns the
    factors ``(A_k diag(s_k), B_k)``, or ``(U, V)`` when nothing can be dropped.
    """
    from crater_thermal.kernels import vfoperator as kv

    _, Uk, Vk = kv.recompress(np.ascontiguousarray(U), np.ascontiguousarray(V), R, float(budget))
    return Uk, Vk


def _quantized(Uk: np.ndarray, Vk: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Factors ``Uk`` (m, r), ``Vk`` (n, r) [float] as stored: ``Uk Vk^T ~ Uq diag(w) Vq^T`` with each
    column of ``Uq``, ``Vq`` (int16, C order) rounded from its column scaled to the largest magnitude
    :data:`QUANT_MAX`, and ``w`` (r,) float32 the product of the two scales [units of ``Uk Vk^T``].
    Each number is then within ``0.5 / QUANT_MAX`` (1.5e-5) of its column's largest."""
    su = np.abs(Uk).max(axis=0)
    sv = np.abs(Vk).max(axis=0)
    su[su == 0.0] = 1.0
    sv[sv == 0.0] = 1.0
    Uq = np.ascontiguousarray(np.rint(Uk * (QUANT_MAX / su)).astype(np.int16))
    Vq = np.ascontiguousarray(np.rint(Vk * (QUANT_MAX / sv)).astype(np.int16))
    return Uq, Vq, (su * sv / (QUANT_MAX * QUANT_MAX)).astype(np.float32)


class _Builder:
    """Computes the blocks of one operator (shared geometry in cluster order, the tracer, settings)."""

    def __init__(self, mesh: Mesh, tracer, tree: _Tree, tolerance: float, mode: str = "block"):
        from crater_thermal import viewfactors as vf

        p = tree.perm
        centre = tracer.centre
        self.tree = tree
        self.tracer = tracer
        self.tol = float(tolerance)
        self.C = np.ascontiguousarray((mesh.centroids - centre)[p])
        self.N = np.ascontiguousarray(mesh.normals[p])
        self.S = np.ascontiguousarray(mesh.facet_size[p])
        self.A = np.ascontiguousarray(mesh.areas[p])
        self.P = np.ascontiguousarray((tracer.origins - centre)[p])
        self.V = np.ascontiguousarray(mesh.vertices - centre)
        self.floor = _HeightFloor.of(mesh, self.V, self.P, tree) if OCCLUSION_PROOF else None
        self.Fc = np.ascontiguousarray(mesh.faces[p])
        self.bary = vf.subtriangle_barycentrics(vf.NEAR_SUBDIVISIONS)
        self.near_factor = float(vf.NEAR_DISTANCE_FACTOR)
        self.cos_cut = float(vf.COS_CUTOFF)
        self.ones = np.ones(RAY_CHUNK, np.float32)
        #: trace each batch in the calling thread (set by :meth:`CompressedPlan.build` while its own threads
        #: run the work units: the tracer's pool inside them would only oversubscribe the cores)
        self.serial_trace = False
        self.mode = mode
        self.g2cum = None  # row mode: prefix sums of the estimated G row sums squared [m4]
        # build totals, set by CompressedPlan.build from the units' own counts (:meth:`_count`)
        self.dropped_blocks = 0
        self.dropped_pairs = 0
        self.quantized_retries = 0  # far blocks whose int16 factors needed a tighter truncation, or failed
        self._unit = threading.local()  # the counts of the unit that this thread computes

    def _count(self, name: str, k: int = 1) -> None:
        counts = self._unit.__dict__.setdefault("counts", {})
        counts[name] = counts.get(name, 0) + k

    def unit_counts(self) -> dict:
        """The counts of the unit this thread just computed (dropped blocks and pairs, quantization
        retries), reset: each unit carries its own, so that a resumed build counts each unit once."""
        return self._unit.__dict__.pop("counts", {})

    # ---- row-relative budgets
    def estimate_row_sums(self, n_rays: int = ROWSUM_RAYS, seed: int = 0) -> np.ndarray:
        """Monte-Carlo row sums of F [-] (cluster order): the fraction of ``n_rays`` cosine-weighted rays
        from each facet that hit the scene (stratified in azimuth and cos^2 of the zenith angle, one
        random rotation per facet).  Sets the budgets of ``mode="row"``; returns (n,) float."""
        n = len(self.A)
        k = int(n_rays)
        # stratified cosine-weighted directions in the local frame: sin^2(zenith) uniform, azimuth uniform
        q = int(np.ceil(np.sqrt(k)))
        a, b = np.meshgrid((np.arange(q) + 0.5) / q, (np.arange(q) + 0.5) / q)
        u1, u2 = a.ravel()[:k], b.ravel()[:k]
        rs = np.sqrt(u1)
        local = np.column_stack([rs * np.cos(2 * np.pi * u2), rs * np.sin(2 * np.pi * u2), np.sqrt(1.0 - u1)])
        rng = np.random.default_rng(seed)
        hits = np.zeros(n)
        per = max(1, RAY_CHUNK // k)
        for f0 in range(0, n, per):
            f1 = min(n, f0 + per)
            nrm = self.N[f0:f1]
            helper = np.where(np.abs(nrm[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
            e1 = np.cross(nrm, helper)
            e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
            e2 = np.cross(nrm, e1)
            phi = rng.uniform(0.0, 2 * np.pi, f1 - f0)[:, None]
            c, sn = np.cos(phi), np.sin(phi)
            lx = c * local[None, :, 0] - sn * local[None, :, 1]
            ly = sn * local[None, :, 0] + c * local[None, :, 1]
            d = lx[..., None] * e1[:, None] + ly[..., None] * e2[:, None] + local[None, :, 2, None] * nrm[:, None]
            o32 = np.ascontiguousarray(np.repeat(self.P[f0:f1], k, axis=0), np.float32)
            d32 = np.ascontiguousarray(d.reshape(-1, 3), np.float32)
            blocked = self.tracer.run_raw(o32, d32, None, "OCCLUDED")
            hits[f0:f1] = (blocked.reshape(f1 - f0, k) != -1).sum(axis=1)
        return hits / k

    def set_row_sums(self, rowsum: np.ndarray) -> None:
        """Row mode: budgets from row sums of F (cluster order) [-]."""
        g = self.A * np.asarray(rowsum, float)
        self.g2cum = np.concatenate([[0.0], np.cumsum(g * g)])

    def budget(self, s: int, t: int, fro2: float) -> float:
        """Allowed ``||M - M~||_F^2`` [m4] of the block (s, t) whose ``||M||_F^2`` is fro2.

        ``"block"``: ``tol^2 fro2``.  ``"row"``: ``tol^2 / N^2 min(n_t sum_{i in s} g_i^2,
        n_s sum_{j in t} g_j^2)`` with ``g_i = A_i rowsum_i`` (N facets, n_s and n_t the block's rows and
        columns): each block gets the share ``n_t / N`` of the budget ``tol^2 g_i^2 / N`` of its rows,
        summed over the rows of the cluster.  If that held row by row (it holds for the cluster's rows
        together, and the row sums are Monte-Carlo estimates), Cauchy-Schwarz would give
        ``|(G x - G~ x)_i| <= tol g_i rms(x)`` for each triangle; the measured errors are far below
        (bench/viewfactor_operator.py)."""
        if self.mode == "block":
            return self.tol * self.tol * fro2
        tr = self.tree
        r0, r1, c0, c1 = int(tr.lo[s]), int(tr.hi[s]), int(tr.lo[t]), int(tr.hi[t])
        n = len(self.A)
        gs = self.g2cum[r1] - self.g2cum[r0]
        gt = self.g2cum[c1] - self.g2cum[c0]
        return self.tol * self.tol / (n * n) * min((c1 - c0) * gs, (r1 - r0) * gt)

    def _trace(self, o32, d32, n):
        return self.tracer.run_raw(o32[:n], d32[:n], self.ones[:n], "OCCLUDED", parallel=not self.serial_trace)

    # ---- far blocks
    def far_block(self, s: int, t: int):
        from crater_thermal.kernels import vfoperator as kv

        tr = self.tree
        r0, r1, c0, c1 = int(tr.lo[s]), int(tr.hi[s]), int(tr.lo[t]), int(tr.hi[t])
        m, n = r1 - r0, c1 - c0
        M = np.zeros(m * n)
        # the rectangles of the block not proven occluded by the terrain (all of it without a proof)
        if self.floor is None:
            rects = np.array([[r0, r1, c0, c1]], np.int64)
        else:
            rects = self.floor.unproven(s, t)
        cap = max(n, min(RAY_CHUNK, m * n))
        o32 = np.empty((cap, 3), np.float32)
        d32 = np.empty((cap, 3), np.float32)
        pos = np.empty(cap, np.int64)
        val = np.empty(cap)
        rays, q, a = 0, 0, -1
        while q < len(rects):
            k, q, a = kv.far_rects_rays(
                rects, q, a, r0, c0, n, self.C, self.N, self.P, self.A, self.cos_cut, o32, d32, pos, val
            )
            if k:
                blocked = self._trace(o32, d32, k)
                kv.scatter_visible(k, pos, val, blocked, M)
                rays += k
        M = M.reshape(m, n)
        lowrank, coo = [], []
        self._compress(M, s, t, lowrank, coo)
        return lowrank, coo, rays, 0

    def _compress(self, M, s, t, lowrank, coo):
        from crater_thermal.kernels import vfoperator as kv

        tr = self.tree
        m, n = M.shape
        nz = np.count_nonzero(M)
        if nz == 0:
            return
        fro2 = float(np.einsum("ij,ij->", M, M))
        budget = self.budget(s, t, fro2)
        if fro2 <= budget:  # row mode only: the whole block is within its share of the rows' budget
            self._count("dropped_blocks")
            self._count("dropped_pairs", nz)
            return
        # int16 factors (2 bytes per number) and a float32 weight per term against 8 bytes per sparse
        # non-zero (value + column)
        rmax = min(int(8 * nz / (LOWRANK_CHOICE_BYTES * (m + n) + 4)), min(m, n) // 2)
        if rmax >= 1:
            U = np.empty((m, rmax))
            V = np.empty((n, rmax))
            R = M.copy()
            r = kv.aca_full(R, budget, rmax, U, V)
            if r >= 0:
                # the truncation leaves a little of the budget to the rounding of the factors to int16,
                # and the error of what is stored is then computed exactly; if over (seldom), the
                # truncation leaves half, then the block is split as below
                for share in QUANT_SHARES:
                    Uq, Vq, w = _quantized(*_recompress(U[:, :r], V[:, :r], R, share * budget))
                    D = M - (Uq * w.astype(np.float64)) @ Vq.T.astype(np.float64)
                    if float(np.einsum("ij,ij->", D, D)) <= budget:
                        lowrank.append((int(tr.lo[s]), int(tr.lo[t]), Uq, Vq, w))
                        return
                    self._count("quantized_retries")
        cs, ct = tr.children(s), tr.children(t)
        if len(cs) > 1 or len(ct) > 1:
            for a in cs:
                ra = slice(tr.lo[a] - tr.lo[s], tr.hi[a] - tr.lo[s])
                for b in ct:
                    rb = slice(tr.lo[b] - tr.lo[t], tr.hi[b] - tr.lo[t])
                    self._compress(M[ra, rb], a, b, lowrank, coo)
            return
        i, j = np.nonzero(M)
        v = M[i, j]
        if self.mode == "row":  # drop the smallest entries while their sum of squares is within budget
            order = np.argsort(v * v)
            keep = order[np.cumsum(v[order] ** 2) > budget]
            self._count("dropped_pairs", len(v) - len(keep))
            i, j, v = i[keep], j[keep], v[keep]
        coo.append((i + int(tr.lo[s]), j + int(tr.lo[t]), v))

    # ---- near blocks
    def near_blocks(self, blocks):
        from crater_thermal.kernels import vfoperator as kv
        from crater_thermal.kernels import viewfactors as kvf

        tr = self.tree
        cap = sum(tr.size(s) * tr.size(t) for s, t, _ in blocks)
        o32 = np.empty((cap, 3), np.float32)
        d32 = np.empty((cap, 3), np.float32)
        pi_ = np.empty(cap, np.int64)
        pj_ = np.empty(cap, np.int64)
        gg = np.empty(cap)
        need = np.empty(cap, np.bool_)
        n = 0
        for s, t, diag in blocks:
            n += kvf.block_pairs(
                int(tr.lo[s]),
                int(tr.hi[s]),
                int(tr.lo[t]),
                int(tr.hi[t]),
                diag,
                self.C,
                self.N,
                self.S,
                self.A,
                self.P,
                self.V,
                self.Fc,
                self.bary,
                self.near_factor,
                self.cos_cut,
                o32[n:],
                d32[n:],
                pi_[n:],
                pj_[n:],
                gg[n:],
                need[n:],
                True,
            )
        if n == 0:
            return [], [], 0, 0
        blocked = np.empty(n, np.int32)
        for a in range(0, n, RAY_CHUNK):
            b = min(n, a + RAY_CHUNK)
            blocked[a:b] = self.tracer.run_raw(
                o32[a:b], d32[a:b], self.ones[: b - a], "OCCLUDED", parallel=not self.serial_trace
            )
        m = kv.keep_visible(n, blocked, need, pi_, pj_, gg)
        return [], [(pi_[:m].copy(), pj_[:m].copy(), gg[:m].copy())], n, m


def compressed_view_factors(
    mesh: Mesh,
    tracer=None,
    tolerance: float = DEFAULT_TOLERANCE,
    progress: Callable | None = None,
    n_threads: int | None = None,
    leaf_size: int = LEAF_SIZE,
    admissibility: float = ADMISSIBILITY,
    max_block_entries: int = MAX_BLOCK_ENTRIES,
    tolerance_mode: str = "block",
    spill_dir=None,
    resume_dir=None,
    keep_after_s: float | None = None,
) -> CompressedViewFactors:
    """Build the compressed view-factor operator (module docstring) without holding the full matrix.

    Parameters
    ----------
    mesh : Mesh
    tracer : RayTracer, optional
        Built from ``mesh`` if not given.
    tolerance : float [-]
        Relative Frobenius error allowed per far block, in (0, 0.1].
    progress : callable, optional
        ``progress(done, total)`` in work units (blocks), called as they finish.
    n_threads : int, optional
        Worker threads (default: the tracer's).
    leaf_size, admissibility, max_block_entries :
        Tuning (see :data:`LEAF_SIZE`, :data:`ADMISSIBILITY`, :data:`MAX_BLOCK_ENTRIES`).
    tolerance_mode : {"block", "row"}
        ``"block"`` (default): every far block to ``tolerance`` of its own Frobenius norm.  ``"row"``:
        far blocks to a budget relative to the row sums of the rows they touch
        (:meth:`_Builder.budget`: about ``|(F x - F~ x)_i| <= tolerance rowsum_i rms(x)`` per row),
        so that far blocks of tiny (grazing) entries are stored at low rank, truncated or dropped;
        the row sums come from :data:`ROWSUM_RAYS` cosine-weighted rays per facet.  Near blocks are
        exact in both modes.
    spill_dir : path, optional
        Folder of the build's temporary files (default: the system's temporary folder, ``TMPDIR``):
        the blocks go to disk as they are made and are read back once, so the build needs free disk
        about the operator's size (:attr:`~CompressedViewFactors.nbytes`) and holds it in memory once.
    resume_dir : path, optional
        Make the build resumable: its files go to a folder in ``resume_dir`` named for the mesh and the
        settings (instead of ``spill_dir``), with a checkpoint every :data:`CHECKPOINT_S` seconds; the
        folder is removed when the build finishes and kept when it fails or is interrupted, and the next
        build of the same operator continues from its last checkpoint (bit for bit the operator of an
        uninterrupted build). A folder in use by another process is left alone (that build starts
        afresh in ``spill_dir``). :func:`view_factor_operator` uses its ``cache_dir``.
    keep_after_s : float [s], optional
        With ``resume_dir``: keep the folder of a finished build whose units took at least this long (over
        every build that contributed), so that the next build of the same operator only reads it back
        (seconds, instead of the build's minutes or hours); it then holds about the operator's size on
        disk. :func:`view_factor_operator` keeps builds of :data:`KEEP_BUILD_S` and more.

    Returns
    -------
    CompressedViewFactors
    """
    t_start = time.perf_counter()
    plan = CompressedPlan(mesh, tracer, tolerance, leaf_size, admissibility, max_block_entries, tolerance_mode)
    nf = mesh.n_facets
    settings = (ALGORITHM_VERSION, plan.tolerance, tolerance_mode, leaf_size, admissibility, max_block_entries)
    key = "-".join(str(x) for x in (mesh.hash, *settings))
    resume = None
    if resume_dir is not None:
        import hashlib

        resume = os.path.join(str(resume_dir), "compressed-build-" + hashlib.sha1(key.encode()).hexdigest()[:16])
    with _Spill(nf, folder=spill_dir, resume=resume, key=key) as spill:
        rays, near_pairs = plan.build(plan.units(), spill, n_threads, progress)
        spill.keep = keep_after_s is not None and spill.units_s >= float(keep_after_s)
        # sparse part: the upper triangle (i < j by construction), CSR, float32 values; then the low-rank
        # part, packed: each read back from the spill files, so that nothing is held twice
        sparse = spill.csr()
        packed = spill.lowrank()
    n_sparse = len(sparse[1])
    rank, U, V = packed[4], packed[8], packed[9]
    nb = len(rank)
    builder = plan.builder
    stats = {
        "facets": nf,
        "tolerance": plan.tolerance,
        "leaf_size": int(leaf_size),
        "admissibility": float(admissibility),
        "far_blocks": len(plan.far),
        "near_blocks": len(plan.near),
        "lowrank_blocks": nb,
        "mean_rank": float(rank.mean()) if nb else 0.0,
        "max_rank": int(rank.max()) if nb else 0,
        "lowrank_numbers": int(U.size + V.size),
        "sparse_pairs": n_sparse,
        "near_pairs": int(near_pairs),
        "rays": int(rays),
        "tolerance_mode": tolerance_mode,
        "dropped_blocks": int(builder.dropped_blocks),
        "dropped_pairs": int(builder.dropped_pairs),
        "quantized_retries": int(builder.quantized_retries),
        "rowsum_estimate_s": plan.rowsum_estimate_s,
        "resumed_units": int(spill.resumed_units),
        "units_s": float(spill.units_s),
        "kept": bool(spill.keep and resume is not None),
    }
    op = CompressedViewFactors(plan.tree.perm, np.asarray(mesh.areas), sparse, packed, None, plan.tolerance, stats)
    op.product_dtype = np.float64  # the rescale from float64 row sums, as the workers' row blocks sum them
    scale, excess = rowsum_scale(op.row_sums()[plan.tree.perm])
    op.product_dtype = PRODUCT_DTYPE
    if scale is not None:
        op.scale = scale
        op.rowsum_excess = excess
    op.stats["build_s"] = time.perf_counter() - t_start
    op.stats["nbytes"] = op.nbytes
    return op


def rowsum_scale(rowsums: np.ndarray) -> tuple[np.ndarray | None, float]:
    """The rescaling that keeps every row sum <= 1 (module docstring: ``G -> D G D``).

    Parameters
    ----------
    rowsums : (n,) float [-]
        Row sums of the unscaled operator, in any order.

    Returns
    -------
    (d, excess) : ``d_i = min(1, 1 / rowsum_i)`` in the same order (None when no row sum exceeds 1),
        and the largest ``rowsum - 1`` (0 when none exceeds 1).
    """
    rs = np.asarray(rowsums, np.float64)
    excess = float(rs.max() - 1.0) if len(rs) else 0.0
    if excess <= 0.0:
        return None, 0.0
    return np.minimum(1.0, 1.0 / np.maximum(rs, 1e-300)), excess


def _lowrank_arrays(meta: list, U: np.ndarray, V: np.ndarray, W: np.ndarray) -> tuple:
    """``(r0, r1, c0, c1, rank, uoff, voff, woff, U, V, W)`` from ``meta = [(r0, c0, m, n, rank)]`` of
    blocks whose factors follow each other in ``U`` and ``V`` (flat, row-major (m, rank) and (n, rank),
    int16) and their weights in ``W`` (rank each, float32)."""
    nb = len(meta)
    info = np.array(meta, np.int64).reshape(nb, 5)
    r0, c0, m, n, rank = (np.ascontiguousarray(info[:, q]) for q in range(5))
    usz, vsz = m * rank, n * rank
    uoff = np.concatenate([[0], np.cumsum(usz)[:-1]]).astype(np.int64) if nb else np.empty(0, np.int64)
    voff = np.concatenate([[0], np.cumsum(vsz)[:-1]]).astype(np.int64) if nb else np.empty(0, np.int64)
    woff = np.concatenate([[0], np.cumsum(rank)[:-1]]).astype(np.int64) if nb else np.empty(0, np.int64)
    if int(usz.sum()) != len(U) or int(vsz.sum()) != len(V) or int(rank.sum()) != len(W):
        raise InternalError("compressed view factors: the low-rank factors do not match their blocks")
    return r0, r0 + m, c0, c0 + n, rank, uoff, voff, woff, U, V, W


class _Spill:
    """Where a build puts its blocks as they are made: on disk, in a temporary folder, so that the build
    holds what it stores once, and not its pieces besides (issue 24: before, the lists of pieces and
    their concatenation held 2.7x the stored operator at 400k facets).

    Low-rank blocks append their int16 factors and float32 weights to three files, in the order they
    come, and sparse
    entries ``(row, column, value)`` (int32, int32, float32) to three; :meth:`lowrank` reads the factors
    back as the packed arrays, :meth:`csr` counts, places and sorts the entries into canonical CSR arrays
    (:func:`kernels.vfoperator.csr_scatter`, :func:`~kernels.vfoperator.csr_sort_merge`: those of scipy's
    COO to CSR conversion), a bounded number of entries at a time.

    ``rows=(a, b)`` keeps rows ``a .. b-1`` of a symmetric operator of ``n`` rows stored above its
    diagonal, as a worker's row block needs them: each entry ``(i, j)`` lands in row ``i - a`` if ``i``
    is one of the rows and, transposed, in row ``j - a`` if ``j`` is; the low-rank blocks that meet
    neither the rows nor, transposed, the columns are not kept. ``folder``: where the temporary folder
    goes (default: the system's, ``TMPDIR``); it needs free space about the size of what is kept.
    """

    #: entries per read while assembling the CSR arrays (12 bytes each)
    CHUNK = 1 << 22
    NAMES = ("U", "V", "W", "M", "I", "J", "G")  # M: (r0, c0, m, n, rank) int64 of each kept block
    MANIFEST = "manifest.json"

    def __init__(self, n: int, rows: tuple[int, int] | None = None, folder=None, resume=None, key: str = ""):
        self.n = int(n)
        self.a, self.b = (0, self.n) if rows is None else (int(rows[0]), int(rows[1]))
        self.whole = rows is None
        self.key = key
        self.entries = 0
        self.blocks = 0
        #: what an interrupted build of the same operator had finished (:meth:`checkpoint`), if resumed
        self.resumed: dict = {}
        self.resumed_units = 0  # units skipped (set by CompressedPlan.build)
        self.units_s = 0.0  # seconds of the build's units, over every build of this folder (the same)
        #: keep a ``resume`` folder after a finished build (its files are then the operator, which the
        #: next build of the same operator reads back instead of building it)
        self.keep = False
        self._tmp = None
        self._lock = None
        self._files: dict = {}
        self._where = self._resumable(resume) if resume is not None else None
        if self._where is None:
            try:
                self._tmp = tempfile.TemporaryDirectory(prefix="crater_thermal-operator-", dir=folder)
            except OSError as exc:
                where = folder or tempfile.gettempdir()
                raise ConfigError(
                    f"view-factor operator: cannot make a temporary folder in {where} ({exc.strerror}); "
                    "set TMPDIR to a writable folder"
                ) from None
            self._where = self._tmp.name
        try:
            sizes = self.resumed.get("bytes", {})
            for name in self.NAMES:
                path = os.path.join(self._where, name)
                f = open(path, "r+b" if name in sizes else "wb", buffering=1 << 22)
                if name in sizes:  # drop what was written after the last checkpoint
                    f.truncate(int(sizes[name]))
                    f.seek(0, os.SEEK_END)
                self._files[name] = f
        except BaseException:
            self.close()
            raise

    def _resumable(self, folder) -> str | None:
        """Use ``folder`` (kept after a failed or interrupted build) and what it holds of this build;
        None if it cannot be made or another process holds it (the build then spills to a temporary
        folder and starts from the beginning)."""
        import fcntl
        import json

        try:
            os.makedirs(folder, exist_ok=True)
            lock = open(os.path.join(folder, "lock"), "a")
        except OSError:
            return None
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            return None
        self._lock = lock
        try:
            state = json.loads(open(os.path.join(folder, self.MANIFEST)).read())
            sizes = state["bytes"]
            if state.get("key") == self.key and all(
                os.path.getsize(os.path.join(folder, name)) >= int(sizes[name]) for name in self.NAMES
            ):
                self.resumed = state
                self.entries, self.blocks = int(state["entries"]), int(state["blocks"])
        except (OSError, ValueError, KeyError, TypeError):
            self.resumed = {}
        return str(folder)

    def checkpoint(self, state: dict) -> None:
        """Record that what was added so far is a finished prefix of the build (``state``: the units done
        and the build's counters), for a resumed build (only with ``resume``)."""
        import json

        if self._lock is None:
            return
        sizes = {}
        for name, f in self._files.items():
            f.flush()
            sizes[name] = f.tell()
        record = {**state, "key": self.key, "bytes": sizes, "entries": self.entries, "blocks": self.blocks}
        tmp = os.path.join(self._where, self.MANIFEST + ".tmp")
        with open(tmp, "w") as f:
            f.write(json.dumps(record))
        os.replace(tmp, os.path.join(self._where, self.MANIFEST))

    def _write(self, name: str, arr: np.ndarray) -> None:
        try:
            self._files[name].write(np.ascontiguousarray(arr).data)
        except OSError as exc:
            self.close(finished=False)
            raise ConfigError(
                f"view-factor operator: cannot write the build's blocks in {self._where} ({exc.strerror}); "
                "set TMPDIR to a folder with free space about the size of the operator"
            ) from None

    def add(self, lowrank: list, coo: list) -> None:
        """One work unit's results: ``[(r0, c0, U, V, W)]`` (int16 factors (m, r) and (n, r), float32
        weights (r,)) and ``[(i, j, g)]`` (cluster order, i < j)."""
        a, b = self.a, self.b
        for r0, c0, U, V, W in lowrank:
            if not self.whole and not ((r0 < b and r0 + U.shape[0] > a) or (c0 < b and c0 + V.shape[0] > a)):
                continue
            self._write("M", np.array([r0, c0, U.shape[0], V.shape[0], U.shape[1]], np.int64))
            self.blocks += 1
            self._write("U", np.asarray(U, np.int16))
            self._write("V", np.asarray(V, np.int16))
            self._write("W", np.asarray(W, np.float32))
        for i, j, g in coo:
            if len(i) and bool(np.any(i >= j)):
                raise InternalError("compressed view factors: a sparse entry below the diagonal")
            g = np.asarray(g, np.float32)
            if self.whole:
                parts = [(i, j, g)]
            else:
                up = (i >= a) & (i < b)
                down = (j >= a) & (j < b)
                parts = [(i[up] - a, j[up], g[up]), (j[down] - a, i[down], g[down])]
            for rr, cc, vv in parts:
                self._write("I", np.asarray(rr, np.int32))
                self._write("J", np.asarray(cc, np.int32))
                self._write("G", vv)
                self.entries += len(rr)

    def _flush(self) -> None:
        for f in self._files.values():
            if not f.closed:
                f.close()

    def _meta(self) -> list:
        return self._read("M", np.int64).reshape(-1, 5)[: self.blocks].tolist()

    def _read(self, name: str, dtype, count: int = -1, f=None) -> np.ndarray:
        if f is not None:
            return np.fromfile(f, dtype, count)
        return np.fromfile(os.path.join(self._where, name), dtype, count)

    def lowrank(self) -> tuple:
        """The kept low-rank blocks packed (:func:`_lowrank_arrays`), read back from disk."""
        self._flush()
        meta = self._meta()
        rank = np.array([m[4] for m in meta], np.int64)
        nu = int(sum(m[2] * m[4] for m in meta))
        nv = int(sum(m[3] * m[4] for m in meta))
        U, V = self._read("U", np.int16, nu), self._read("V", np.int16, nv)
        W = self._read("W", np.float32, int(rank.sum()))
        return _lowrank_arrays(meta, U, V, W)

    def csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(indptr int64, indices int32, data float32)`` of the kept sparse entries, ``b - a`` rows,
        columns sorted in each row and repeated entries summed."""
        from crater_thermal.kernels import vfoperator as kv

        self._flush()
        rows, total, step = self.b - self.a, self.entries, self.CHUNK
        counts = np.zeros(rows, np.int64)
        with open(os.path.join(self._where, "I"), "rb") as fi:
            for _ in range(0, total, step):
                counts += np.bincount(self._read("I", np.int32, step, fi), minlength=rows)
        indptr = np.zeros(rows + 1, np.int64)
        np.cumsum(counts, out=indptr[1:])
        del counts
        indices = np.empty(total, np.int32)
        data = np.empty(total, np.float32)
        cursor = indptr[:-1].copy()
        with (
            open(os.path.join(self._where, "I"), "rb") as fi,
            open(os.path.join(self._where, "J"), "rb") as fj,
            open(os.path.join(self._where, "G"), "rb") as fg,
        ):
            for _ in range(0, total, step):
                i = self._read("I", np.int32, step, fi)
                j = self._read("J", np.int32, step, fj)
                g = self._read("G", np.float32, step, fg)
                kv.csr_scatter(i, j, g, cursor, indices, data)
        del cursor
        kept = kv.csr_sort_merge(indptr, indices, data)
        if kept < total:  # repeated entries were summed (none by construction: the blocks are disjoint)
            indices, data = indices[:kept].copy(), data[:kept].copy()
        return indptr, indices, data

    def close(self, finished: bool = True) -> None:
        """Remove the folder: a temporary one always (also when the build failed or was interrupted), a
        ``resume`` folder only when the build ``finished`` (else it is kept, with its last checkpoint,
        for the next build of the same operator)."""
        self._flush()
        if self._tmp is not None:
            self._tmp.cleanup()
        elif self._lock is not None:
            if finished and not self.keep:
                import shutil

                for name in (*self.NAMES, self.MANIFEST):
                    if os.path.exists(os.path.join(self._where, name)):
                        os.unlink(os.path.join(self._where, name))
                shutil.rmtree(self._where, ignore_errors=True)
            self._lock.close()
            self._lock = None

    def __enter__(self) -> "_Spill":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(finished=exc_type is None)


class CompressedPlan:
    """What every build of one compressed operator starts from, deterministic from the mesh and the
    settings: the cluster tree, the block partition, the block builder and its work units.

    :func:`compressed_view_factors` builds every unit; :meth:`row_block` only those that some rows need
    (a distributed run's worker builds its own rows: :func:`crater_thermal.cluster_run`).  Parameters as
    :func:`compressed_view_factors`.
    """

    def __init__(
        self,
        mesh: Mesh,
        tracer=None,
        tolerance: float = DEFAULT_TOLERANCE,
        leaf_size: int = LEAF_SIZE,
        admissibility: float = ADMISSIBILITY,
        max_block_entries: int = MAX_BLOCK_ENTRIES,
        tolerance_mode: str = "block",
    ):
        from crater_thermal import viewfactors as vf

        if not isinstance(mesh, Mesh):
            raise MeshError(f"compressed_view_factors needs a geometry.Mesh, got {type(mesh).__name__}")
        tolerance = float(tolerance)
        if not (0.0 < tolerance <= 0.1):
            raise ConfigError(f"view-factor tolerance = {tolerance!r} is outside (0, 0.1]")
        if tolerance_mode not in TOLERANCE_MODES:
            raise ConfigError(f"tolerance_mode = {tolerance_mode!r}; allowed: {', '.join(TOLERANCE_MODES)}")
        if tracer is None:
            from crater_thermal.raytrace import RayTracer

            tracer = RayTracer(mesh)
        elif tracer.mesh.hash != mesh.hash:
            raise MeshError("tracer was built for a different mesh")
        self.mesh, self.tracer, self.tolerance, self.tolerance_mode = mesh, tracer, tolerance, tolerance_mode
        self.tree = _Tree(np.asarray(mesh.centroids), np.asarray(mesh.facet_size), int(leaf_size))
        self.far, self.near = _partition(
            self.tree, float(vf.NEAR_DISTANCE_FACTOR), float(admissibility), int(max_block_entries)
        )
        # far blocks are built largest first (the thread pool's tail is then short)
        self.far.sort(key=lambda st: -self.tree.size(st[0]) * self.tree.size(st[1]))
        self.builder = _Builder(mesh, tracer, self.tree, tolerance, tolerance_mode)
        self.rowsum_estimate_s = 0.0
        if tolerance_mode == "row":
            t0 = time.perf_counter()
            self.builder.set_row_sums(self.builder.estimate_row_sums())
            self.rowsum_estimate_s = time.perf_counter() - t0

    @property
    def n_facets(self) -> int:
        return int(self.mesh.n_facets)

    def units(self, a: int = 0, b: int | None = None) -> list:
        """The work units (far blocks one by one, near blocks batched) of the blocks whose rows or
        columns meet rows ``a .. b-1`` (positions in the cluster order; default all): those that the
        rows' products need, a block above the diagonal serving its rows and, transposed, its columns."""
        tree = self.tree
        b = self.n_facets if b is None else int(b)
        lo, hi = tree.lo, tree.hi

        def meets(s) -> bool:
            return bool(lo[s] < b and hi[s] > a)

        whole = a <= 0 and b >= self.n_facets
        far = self.far if whole else [st for st in self.far if meets(st[0]) or meets(st[1])]
        near = self.near if whole else [blk for blk in self.near if meets(blk[0]) or meets(blk[1])]
        units = [("far", st) for st in far]
        batch, acc = [], 0
        for blk in near:
            batch.append(blk)
            acc += tree.size(blk[0]) * tree.size(blk[1])
            if acc >= NEAR_BATCH_PAIRS:
                units.append(("near", batch))
                batch, acc = [], 0
        if batch:
            units.append(("near", batch))
        return units

    def build(self, units: list, spill: "_Spill", n_threads: int | None = None, progress: Callable | None = None):
        """Compute work units on ``n_threads`` threads (default: the tracer's), each unit's blocks handed
        to ``spill`` (:meth:`_Spill.add`: low-rank blocks ``(r0, c0, U, V, W)`` in cluster order, sparse
        entries ``(i, j, g)`` above the diagonal [m2]) as it finishes, in the order of ``units``; every
        :data:`CHECKPOINT_S` seconds the finished prefix is recorded (:meth:`_Spill.checkpoint`), and a
        spill resumed from a kept folder starts after the units it had finished.

        Returns
        -------
        (rays, near_pairs) : rays traced, near pairs kept.
        """
        builder = self.builder

        def work(u):
            kind, arg = u
            builder.unit_counts()  # nothing left over from a unit that failed in this thread
            out = builder.far_block(*arg) if kind == "far" else builder.near_blocks(arg)
            return (*out, builder.unit_counts())

        n_threads = max(1, int(n_threads or self.tracer.n_threads))
        # a resumed build (spill.resumed: a kept folder's last checkpoint) skips the units it had finished
        counters = ("dropped_blocks", "dropped_pairs", "quantized_retries")
        state = dict.fromkeys(("units", "rays", "near_pairs", *counters), 0)
        state.update({k: int(v) for k, v in spill.resumed.items() if k in state})
        state["units_s"] = float(spill.resumed.get("units_s", 0.0))  # the units' seconds, over every build
        spill.resumed_units = state["units"]
        t0 = time.perf_counter() - state["units_s"]
        if state["units"] > len(units):
            raise InternalError("compressed view factors: a kept build has more units than this one")
        rays, near_pairs, done = state["rays"], state["near_pairs"], state["units"]
        last = time.monotonic()
        pool = ThreadPoolExecutor(n_threads) if n_threads > 1 else None
        # the units run on this pool's threads, each tracing its batches itself (measured at 30k facets,
        # alternating: 12.4 / 12.5 s against 14.7 / 17.0 s with the tracer's threads started inside them)
        builder.serial_trace = pool is not None
        # one BLAS thread while the units run: each far block's recompression (kernels.vfoperator.recompress)
        # makes QR, SVD and products of blocks of ~60 x 60 at rank ~4, which OpenBLAS's own threads only
        # slow down, spinning beside the build's threads (30k facets, alternating: recompression 2.1-2.8 s
        # -> 0.5 s in all, the operator 9.6 -> 7.2 s; the same numbers)
        try:
            with threadpool_limits(1, user_api="blas"):
                todo = units[done:]
                results = pool.map(work, todo) if pool is not None else map(work, todo)
                for lr, cc, nr, npairs, counts in results:
                    spill.add(lr, cc)
                    rays += nr
                    near_pairs += npairs
                    done += 1
                    for name, k in counts.items():
                        state[name] += k
                    if time.monotonic() - last >= CHECKPOINT_S:
                        last = time.monotonic()
                        state["units_s"] = time.perf_counter() - t0
                        spill.checkpoint({**state, "units": done, "rays": rays, "near_pairs": near_pairs})
                    if progress is not None:
                        progress(done, len(units))
                # every unit done: a failure while the arrays are assembled then redoes none of them
                state["units_s"] = spill.units_s = time.perf_counter() - t0
                spill.checkpoint({**state, "units": done, "rays": rays, "near_pairs": near_pairs})
        finally:
            builder.serial_trace = False
            for name in counters:
                setattr(builder, name, state[name])
            if pool is not None:
                pool.shutdown(cancel_futures=True)
        return rays, near_pairs

    def row_block(self, a: int, b: int, n_threads: int | None = None, spill_dir=None) -> "RowBlock":
        """Rows ``a .. b-1`` (cluster order, :func:`row_order`) of the operator built alone, without the
        rest of it: the units of :meth:`units` (a block meeting other rows too is built here as well as
        there), kept as :func:`load_row_block` keeps them from the whole operator (its near rows and,
        transposed, columns; the low-rank blocks meeting them), **unscaled**: give it the scale of every
        row sum with :meth:`RowBlock.with_scale` (:func:`rowsum_scale` of all blocks' :meth:`RowBlock.row_sums`).

        Equal to :func:`load_row_block` of :func:`compressed_view_factors` (same settings) on these rows
        to round-off: the same units built the same way.  ``stats`` of the block: units, rays, near pairs,
        seconds (wall, and CPU of this process).
        """
        n = self.n_facets
        if not (0 <= a < b <= n):
            raise ConfigError(f"row block {a}:{b} outside the operator's {n} rows")
        t0, c0 = time.perf_counter(), time.process_time()
        units = self.units(a, b)
        # near part: rows a..b-1 of S + S^T, S the entries above the diagonal (float32 as stored); far
        # part: the low-rank blocks that meet the rows or, transposed, the columns (a far block split
        # into children may leave some that meet neither); both kept by the spill as the units finish
        with _Spill(n, rows=(a, b), folder=spill_dir) as spill:
            rays, near_pairs = self.build(units, spill, n_threads)
            indptr, indices, data = spill.csr()
            near = sp.csr_matrix((data, indices, indptr), shape=(b - a, n))
            lowrank = spill.lowrank()
        perm = self.tree.perm
        block = RowBlock(
            n,
            perm[a:b].copy(),
            near,
            a=a,
            b=b,
            areas=np.ascontiguousarray(np.asarray(self.mesh.areas)[perm[a:b]], np.float64),
            perm=np.ascontiguousarray(perm, np.int64),
            lowrank=lowrank,
        )
        block.stats = {"units": len(units), "rays": int(rays), "near_pairs": int(near_pairs)}
        block.stats["build_s"] = time.perf_counter() - t0
        block.stats["build_cpu_s"] = time.process_time() - c0  # this process's threads, all of them
        return block


# --------------------------------------------------------------------------------------------- entry point


def resolve_method(method: str, n_facets: int) -> str:
    """``"exact"`` or ``"compressed"`` for a configured method and facet count."""
    if method not in METHODS:
        raise ConfigError(f"view_factors = {method!r}; allowed: {', '.join(METHODS)}")
    if method == "auto":
        return "compressed" if n_facets >= AUTO_COMPRESSED_MIN_FACETS else "exact"
    return method


def view_factor_operator(
    mesh: Mesh,
    tracer=None,
    method: str = "auto",
    tolerance: float = DEFAULT_TOLERANCE,
    cache_dir=None,
    progress: Callable | None = None,
    tolerance_mode: str = "block",
) -> ViewFactorOperator:
    """The view-factor operator of a mesh: exact sparse matrix or compressed (module docstring).

    Parameters
    ----------
    mesh : Mesh
    tracer : RayTracer, optional
    method : {"auto", "exact", "compressed"}
        ``"auto"``: exact below :data:`AUTO_COMPRESSED_MIN_FACETS` facets, compressed from there on.
    tolerance : float [-]
        Compressed operator only: relative Frobenius error per far block.
    cache_dir : path-like, optional
        Exact matrix: its ``.npz`` cache folder. Compressed operator: where an interrupted build keeps
        what it had finished, for the next build to continue, and where a build of
        :data:`KEEP_BUILD_S` or more is kept (``resume_dir``, ``keep_after_s`` of
        :func:`compressed_view_factors`).
    progress : callable, optional
        ``progress(done, total)`` (:mod:`crater_thermal.progress` contract).
    tolerance_mode : {"block", "row"}
        Compressed operator only: see :func:`compressed_view_factors`.

    Returns
    -------
    ViewFactorOperator
    """
    from crater_thermal import viewfactors as vf

    if not isinstance(mesh, Mesh):
        raise MeshError(f"view_factor_operator needs a geometry.Mesh, got {type(mesh).__name__}")
    kind = resolve_method(method, mesh.n_facets)
    if kind == "exact":
        return SparseViewFactors(vf.view_factor_matrix(mesh, tracer, cache_dir=cache_dir, progress=progress))
    return compressed_view_factors(
        mesh,
        tracer,
        tolerance,
        progress=progress,
        tolerance_mode=tolerance_mode,
        resume_dir=cache_dir,
        keep_after_s=KEEP_BUILD_S,
    )


# --------------------------------------------------------------------------------------------- row blocks


#: Arrays of a saved compressed operator (:func:`save_operator`), in its folder as ``NAME.npy``.
_COMPRESSED_ARRAYS = (
    "perm",
    "areas_perm",
    "indptr",
    "indices",
    "data",
    "r0",
    "r1",
    "c0",
    "c1",
    "rank",
    "uoff",
    "voff",
    "woff",
    "U",
    "V",
    "W",
)


def row_order(F: ViewFactorOperator) -> np.ndarray:
    """The facet order in which contiguous runs of rows make cheap row blocks [-] (int64 facet indices):
    the cluster order of a compressed operator (a run of it is a union of clusters, so few far blocks
    touch it), the facet order of an exact matrix."""
    if isinstance(F, CompressedViewFactors):
        return F.perm.copy()
    return np.arange(F.shape[0], dtype=np.int64)


def save_operator(F: ViewFactorOperator, folder) -> None:
    """Write ``F`` into ``folder`` (one ``.npy`` file per array and ``meta.json``) so that each worker of a
    distributed run reads only its own rows (:func:`load_row_block`, memory-mapped reads).

    Raises
    ------
    ConfigError
        ``F`` is neither an exact nor a compressed operator.
    """
    import json
    from pathlib import Path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if isinstance(F, CompressedViewFactors):
        for name in _COMPRESSED_ARRAYS:
            np.save(folder / f"{name}.npy", getattr(F, name))
        if F.scale is not None:
            np.save(folder / "scale.npy", F.scale)
        meta = {"kind": "compressed", "n": int(F.shape[0]), "scaled": F.scale is not None}
    elif isinstance(F, SparseViewFactors):
        m = F.matrix
        for name in ("indptr", "indices", "data"):
            np.save(folder / f"{name}.npy", getattr(m, name))
        meta = {"kind": "exact", "n": int(F.shape[0])}
    else:
        raise ConfigError(f"cannot save a {type(F).__name__} for a distributed run; use an exact or compressed one")
    (folder / "meta.json").write_text(json.dumps(meta))


def load_row_block(folder, a: int, b: int) -> "RowBlock":
    """Rows ``a .. b-1`` (positions in :func:`row_order`) of the operator saved in ``folder``: only the
    stored entries those rows need are read into memory."""
    import json
    from pathlib import Path

    folder = Path(folder)
    meta = json.loads((folder / "meta.json").read_text())

    def arr(name):
        return io.load_npy(folder / f"{name}.npy", mmap_mode="r")

    n = int(meta["n"])
    if not (0 <= a < b <= n):
        raise ConfigError(f"row block {a}:{b} outside the operator's {n} rows")
    if meta["kind"] == "exact":
        indptr = arr("indptr")
        lo, hi = int(indptr[a]), int(indptr[b])
        sub = sp.csr_matrix(
            (np.array(arr("data")[lo:hi]), np.array(arr("indices")[lo:hi]), np.array(indptr[a : b + 1]) - lo),
            shape=(b - a, n),
        )
        return RowBlock(n, np.arange(a, b, dtype=np.int64), sub)
    perm = arr("perm")
    areas = np.array(arr("areas_perm")[a:b])
    scale = np.array(arr("scale")) if meta.get("scaled") else None
    # near part: rows a..b-1 of S + S^T, S strictly upper-triangular CSR in cluster order
    indptr, indices, data = arr("indptr"), arr("indices"), arr("data")
    lo, hi = int(indptr[a]), int(indptr[b])
    upper = sp.csr_matrix(
        (np.array(data[lo:hi], np.float32), np.array(indices[lo:hi]), np.array(indptr[a : b + 1]) - lo),
        shape=(b - a, n),
    )
    # entries (i, j) of S with j in a..b-1 are entries (j, i) of S^T: one pass over the columns, in pieces
    rows_t, cols_t, vals_t = [], [], []
    step = 1 << 22
    row_of = np.repeat(np.arange(n, dtype=np.int64), np.diff(np.asarray(indptr)))
    for q0 in range(0, len(indices), step):
        j = np.asarray(indices[q0 : q0 + step])
        hit = np.flatnonzero((j >= a) & (j < b))
        if hit.size:
            rows_t.append(j[hit] - a)
            cols_t.append(row_of[q0 + hit])
            vals_t.append(np.asarray(data[q0 : q0 + step], np.float32)[hit])
    del row_of
    near = upper
    if rows_t:
        lower = sp.csr_matrix(
            (np.concatenate(vals_t), (np.concatenate(rows_t), np.concatenate(cols_t))), shape=(b - a, n)
        )
        near = (upper + lower).tocsr()
    # far part: the low-rank blocks whose rows or columns meet a..b-1, factors copied out
    r0, r1, c0, c1 = (np.asarray(arr(k)) for k in ("r0", "r1", "c0", "c1"))
    keep = np.flatnonzero(((r0 < b) & (r1 > a)) | ((c0 < b) & (c1 > a)))
    rank, uoff, voff, woff = (np.asarray(arr(k))[keep] for k in ("rank", "uoff", "voff", "woff"))
    U, V, W = arr("U"), arr("V"), arr("W")
    meta = np.column_stack([r0[keep], c0[keep], r1[keep] - r0[keep], c1[keep] - c0[keep], rank])
    m, nn = meta[:, 2] * rank, meta[:, 3] * rank
    Uk = np.concatenate([U[uoff[q] : uoff[q] + m[q]] for q in range(len(keep))] + [np.empty(0, np.int16)])
    Vk = np.concatenate([V[voff[q] : voff[q] + nn[q]] for q in range(len(keep))] + [np.empty(0, np.int16)])
    Wk = np.concatenate([W[woff[q] : woff[q] + rank[q]] for q in range(len(keep))] + [np.empty(0, np.float32)])
    lowrank = _lowrank_arrays(meta.tolist(), Uk, Vk, Wk)
    return RowBlock(
        n, np.array(perm[a:b]), near, a=a, b=b, areas=areas, perm=np.array(perm), scale=scale, lowrank=lowrank
    )


class RowBlock:
    """Some rows of a view-factor operator, held alone (a distributed run's worker holds those of its
    facets): ``block.apply(X)`` is ``(F @ X)[block.facets]`` for X (n, k) over all facets, [unit of X].

    Built by :func:`load_row_block` (from a saved operator) or :meth:`CompressedPlan.row_block` (from
    the mesh, without the whole operator). For a compressed operator the product applies the halves of the
    low-rank blocks that land in these rows (:func:`kernels.vfoperator.lowrank_matvec_rows`: a block
    spanning two chunks costs each chunk half of it), so ``apply`` equals the whole operator's product on
    these rows to round-off.
    """

    def __init__(self, n, facets, near, a=None, b=None, areas=None, perm=None, scale=None, lowrank=None):
        if perm is not None and near.dtype != np.float32:
            # a compressed operator's near entries are float32 as stored (both builders keep them so; an
            # empty block or another caller's float64 matrix is converted here, exactly)
            near = sp.csr_matrix((near.data.astype(np.float32), near.indices, near.indptr), shape=near.shape)
        self.n, self.facets, self.near = int(n), np.asarray(facets, np.int64), near
        self.a, self.b, self.areas, self.perm, self.scale, self.lowrank = a, b, areas, perm, scale, lowrank
        self.stats: dict = {}

    def with_scale(self, scale) -> "RowBlock":
        """These rows of the operator rescaled by ``scale`` ((n,) [-] in cluster order, the
        :func:`rowsum_scale` of every row's sum; None: unscaled), sharing the stored arrays."""
        if self.perm is None and scale is not None:
            raise ConfigError("an exact matrix's row block takes no scale")  # pragma: no cover - internal
        out = RowBlock(self.n, self.facets, self.near, self.a, self.b, self.areas, self.perm, scale, self.lowrank)
        out.stats = dict(self.stats)
        return out

    def row_sums(self) -> np.ndarray:
        """(rows,) float [-]: ``sum_j F_ij`` of the block's rows (:attr:`facets`)."""
        return self.apply(np.ones((self.n, 1)))[:, 0]

    @property
    def nbytes(self) -> int:
        """Bytes held [B]."""
        total = self.near.data.nbytes + self.near.indices.nbytes + self.near.indptr.nbytes + self.facets.nbytes
        for x in (self.areas, self.perm, self.scale, *(self.lowrank or ())):
            total += 0 if x is None else x.nbytes
        return int(total)

    def apply(self, X: np.ndarray) -> np.ndarray:
        """``(F @ X)[facets]``: X (n, k) over all facets in facet order -> (len(facets), k) float64.

        As the whole compressed operator computes them: several right-hand sides in
        :data:`PRODUCT_DTYPE` arithmetic, one in float64 (an exact matrix's rows: float64)."""
        X = np.asarray(X)
        if X.ndim != 2 or X.shape[0] != self.n:
            raise ConfigError(f"row block product: operand has shape {X.shape}; expected ({self.n}, k)")
        if self.perm is None:  # exact matrix: its rows
            return np.asarray(self.near @ np.asarray(X, np.float64))
        from crater_thermal.kernels import vfoperator as kv

        # in the products' type from the gather on (a float32 operand, as a cluster sends it, is never
        # copied to float64: a window's emission of every facet is the largest array a worker holds)
        dtype = PRODUCT_DTYPE if X.shape[1] > 1 else np.float64
        Xc = np.ascontiguousarray(X[self.perm], dtype)
        if self.scale is not None:
            Xc *= self.scale.astype(dtype)[:, None]
        Y = np.zeros((self.b - self.a, Xc.shape[1]), Xc.dtype)
        one = Xc.shape[1] == 1  # one right-hand side: the one-vector kernels (the held pass's products)
        if one:
            kv.csr_matvec1(self.near.indptr, self.near.indices, self.near.data, Xc.reshape(-1), Y.reshape(-1))
        else:
            kv.csr_matmat(self.near.indptr, self.near.indices, self.near.data, Xc, Y)
        if len(self.lowrank[4]):  # only the halves of the far blocks that land in these rows
            far = np.zeros_like(Y)
            rmax = 2 * int(self.lowrank[4].max())
            if one:
                tmp = np.empty(rmax, Xc.dtype)
                kv.lowrank_matvec_rows1(*self.lowrank, Xc.reshape(-1), far.reshape(-1), tmp, self.a, self.b)
            else:
                tmp = np.empty((rmax, Xc.shape[1]), Xc.dtype)
                kv.lowrank_matvec_rows(*self.lowrank, Xc, far, tmp, self.a, self.b)
            Y += far
        Y = Y.astype(np.float64, copy=False)
        if self.scale is not None:
            Y *= self.scale[self.a : self.b, None]
        return Y / self.areas[:, None]

"""The stage-1 regulariser of the paper (Eq. geo_regular) at the coarse size: a 6-D Chamfer distance
between the two views' point sets (xyz of X_t, rgb of the pixel),

    CD(i -> j) = 1/|P_i| sum_{p in P_i} min_{q in P_j} ||p - q||_2,   L_CD = CD(l -> r) + CD(r -> l),

exact, without a brute-force distance matrix. Two 256x144 point maps are 36,864 points each: all
pairs are 1.4 G distances, and autograd through a chunked `cdist` keeps every chunk's distance
matrix for the backward pass (5.4 GB in float32). Here the nearest neighbours are found without
gradients, and only the N chosen distances ||p - q(p)|| are recomputed with autograd: the value and
the gradient are those of the brute-force min (the gradient of a min flows to its argmin), with
O(N + M) memory for autograd.

The search is exact and prunes with bounding boxes (`nearest_indices`):
1. each set is split into a balanced k-d tree (median splits along the widest of the six
   dimensions, colours included) down to 2^k leaves of at most `leaf` points, equal in size (a
   set is padded with copies of its own points, which change no nearest distance);
2. an upper bound per query: its distance to the points of the two leaves of the other set whose
   centres lie nearest its own leaf's centre;
3. leaf pairs (query leaf, point leaf) whose box-to-box distance exceeds the query leaf's largest
   upper bound are dropped; of the rest, per query, the leaves whose box lies within the query's
   own upper bound are kept (on the simulator's point maps 2-3 leaves per query);
4. the distances to the points of those leaves, by differences (exact: no |p|^2 + |q|^2 - 2 p.q
   cancellation), and per query the least.
Cost, N and M points, L = N / leaf leaves a side: the trees O(N log^2 N); the box pairs O(L^2 D);
the query-box bounds O(P leaf D) for the P surviving leaf pairs; the distances O(N k leaf D) for
k leaves per query. The last two are data dependent: small on point maps of one scene, at worst
(sets far apart, or uniform noise in 6-D) the order of brute force. Memory beyond the inputs and
the result: every temporary is bounded by `budget` elements (4 M by default), plus O(N k) for the
candidates; autograd keeps O(N + M). Figures at the coarse size: the module's test file.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

SLACK = 1e-5  # relative: box bounds and distances round differently; keep a leaf that ties
LEAF = 32  # points per leaf: measured fastest at the coarse size (16: 3x slower, 64: about the same)


def kd_leaves(x: torch.Tensor, leaf: int) -> torch.Tensor:
    """Indices (L, S) into the points x (N, D): L = 2^k leaves of S points each (leaf/2 < S <=
    leaf, or S = N <= leaf), spatially coherent (a balanced k-d tree's leaves). Indices repeat
    (modulo N) to fill the last slots: a copy of a point is as near as the point."""
    if leaf < 2:
        raise ValueError(f"leaf must be at least 2, got {leaf}")
    n = x.shape[0]
    levels = max(0, math.ceil(math.log2(n / leaf))) if n > leaf else 0
    size = math.ceil(n / 2**levels)
    groups = (torch.arange(size * 2**levels, device=x.device) % n).reshape(1, -1)
    for _ in range(levels):
        g, m = groups.shape
        pts = x[groups]  # (G, m, D)
        dim = (pts.amax(1) - pts.amin(1)).argmax(1)  # the widest dimension of each group
        vals = pts.gather(2, dim.reshape(g, 1, 1).expand(g, m, 1))[..., 0]
        groups = groups.gather(1, vals.argsort(1)).reshape(2 * g, m // 2)  # median split
    return groups


def _box_gap(lo: torch.Tensor, hi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Squared distance from points x (..., D) to boxes [lo, hi] (..., D) (0 inside)."""
    gap = (lo - x).clamp(min=0.0) + (x - hi).clamp(min=0.0)
    return (gap * gap).sum(-1)


@torch.no_grad()
def nearest_indices(a: torch.Tensor, b: torch.Tensor, leaf: int = LEAF, budget: int = 1 << 22) -> torch.Tensor:
    """For each point of a (N, D), the index of its nearest point in b (M, D), M > 0. `budget`
    bounds the elements of each temporary (memory, not the result)."""
    if b.shape[0] == 0:
        raise ValueError("nearest_indices: the searched set is empty")
    a, b = a.detach(), b.detach()
    dims = a.shape[1]
    la, lb = kd_leaves(a, leaf), kd_leaves(b, leaf)
    ap, bp = a[la], b[lb]  # (LA, SA, D), (LB, SB, D): the points of each leaf
    alo, ahi, blo, bhi = ap.amin(1), ap.amax(1), bp.amin(1), bp.amax(1)
    n_a, size_a = la.shape
    n_b, size_b = lb.shape

    # 1. An upper bound per query: its distance to the points of the two b leaves whose centres
    #    lie nearest its own leaf's centre (on aligned point maps, usually the neighbour itself).
    near = torch.cdist(ap.mean(1), bp.mean(1)).topk(min(2, n_b), dim=1, largest=False).indices  # (LA, 2)
    upper = ((bp[near].reshape(n_a, 1, -1, dims) - ap[:, :, None, :]) ** 2).sum(-1).amin(2)  # (LA, SA)
    # 2. Leaf pairs that can matter: the box-to-box distance does not exceed the leaf's largest
    #    query upper bound.
    rows = max(1, budget // (n_b * dims))
    pairs = []
    for s in range(0, n_a, rows):
        gap = (blo[None] - ahi[s:s + rows, None]).clamp(min=0.0) + (alo[s:s + rows, None] - bhi[None]).clamp(min=0.0)
        keep = (gap * gap).sum(-1) <= upper[s:s + rows].amax(1, keepdim=True) * (1.0 + SLACK)
        li, lj = keep.nonzero(as_tuple=True)
        pairs.append(torch.stack([li + s, lj]))
    li, lj = torch.cat(pairs, 1)
    # 3. Per query, the leaves of such pairs whose box lies within its own upper bound; then the
    #    distances to their points, by differences (no |q|^2 + |p|^2 - 2 q.p cancellation).
    ids, dists, cands = [], [], []
    step = max(1, budget // (size_a * dims))
    for s in range(0, li.shape[0], step):
        pa, pb = li[s:s + step], lj[s:s + step]
        lower = _box_gap(blo[pb][:, None, :], bhi[pb][:, None, :], ap[pa])  # (P, SA)
        pi, qi = (lower <= upper[pa] * (1.0 + SLACK)).nonzero(as_tuple=True)
        qa, qb = pa[pi], pb[pi]
        sub = max(1, budget // (size_b * dims))
        for t in range(0, qa.shape[0], sub):
            d2 = ((bp[qb[t:t + sub]] - ap[qa[t:t + sub], qi[t:t + sub]][:, None, :]) ** 2).sum(-1)  # (Q, SB)
            m, k = d2.min(1)
            ids.append(la[qa[t:t + sub], qi[t:t + sub]])
            dists.append(m)
            cands.append(lb[qb[t:t + sub], k])
    ids, dists, cands = torch.cat(ids), torch.cat(dists), torch.cat(cands)
    # 4. Per query, the candidate at the least distance.
    least = torch.full((a.shape[0],), float("inf"), dtype=dists.dtype, device=a.device).scatter_reduce(0, ids, dists, "amin")
    win = dists == least[ids]
    out = torch.empty(a.shape[0], dtype=torch.int64, device=a.device)
    out[ids[win]] = cands[win]  # of tied candidates one is written, as min picks one
    return out


def _distances(a: torch.Tensor, b: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """||a_i - b_index[i]|| with autograd; a zero distance has a zero gradient (as torch.cdist's)."""
    d2 = ((a - b[index]) ** 2).sum(-1)
    return torch.where(d2 > 0, d2.clamp(min=1e-30).sqrt(), torch.zeros_like(d2))


def directed_chamfer(a: torch.Tensor, b: torch.Tensor, weight_a: Optional[torch.Tensor] = None,
                     weight_b: Optional[torch.Tensor] = None, leaf: int = LEAF) -> torch.Tensor:
    """CD(a -> b) per batch item (B,): the (weight_a-weighted) mean over a's points (B, N, D) of the
    distance to the nearest of b's points (B, M, D) that have weight_b > 0. A set with no point
    to match (all weight_b zero) contributes 0."""
    out = []
    for i in range(a.shape[0]):
        bi = b[i] if weight_b is None else b[i][weight_b[i] > 0]
        if bi.shape[0] == 0:
            out.append(a.new_zeros(()))
            continue
        d = _distances(a[i], bi, nearest_indices(a[i], bi, leaf))
        if weight_a is None:
            out.append(d.mean())
        else:
            out.append((d * weight_a[i]).sum() / weight_a[i].sum().clamp(min=1e-6))
    return torch.stack(out)


def chamfer_6d(a: torch.Tensor, b: torch.Tensor, weight_a: Optional[torch.Tensor] = None,
               weight_b: Optional[torch.Tensor] = None, leaf: int = LEAF) -> torch.Tensor:
    """L_CD = CD(a -> b) + CD(b -> a) of point sets (B, N, D) and (B, M, D), averaged over the
    batch; weights (B, N) / (B, M): queries are weighted by them, points with weight 0 are never
    a nearest neighbour (invalid pixels). Same arguments as inference.train.losses.chamfer_6d."""
    return (directed_chamfer(a, b, weight_a, weight_b, leaf) + directed_chamfer(b, a, weight_b, weight_a, leaf)).mean()


def chamfer_reference(a: torch.Tensor, b: torch.Tensor, weight_a: Optional[torch.Tensor] = None,
                      weight_b: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The same, brute force: every pair's distance (torch.cdist without the matrix-product
    shortcut), min over the other set. O(N M) time and memory: small sets only."""

    def directed(x, y, wx, wy):
        out = []
        for i in range(x.shape[0]):
            yi = y[i] if wy is None else y[i][wy[i] > 0]
            if yi.shape[0] == 0:
                out.append(x.new_zeros(()))
                continue
            d = torch.cdist(x[i][None], yi[None], compute_mode="donot_use_mm_for_euclid_dist")[0].amin(1)
            out.append(d.mean() if wx is None else (d * wx[i]).sum() / wx[i].sum().clamp(min=1e-6))
        return torch.stack(out)

    return (directed(a, b, weight_a, weight_b) + directed(b, a, weight_b, weight_a)).mean()

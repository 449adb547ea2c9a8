"""Screening's TIN kept from round to round, only its holes re-triangulated.

A screening round deletes a few vertices of a TIN of thousands. ``Tin.without``
fills the holes they leave with a small triangulation of the rims, but then
renumbers and copies the whole mesh, and the next round's judging reads the whole
mesh's adjacency again: on sparse tiles (about 10 k vertices, 20-30 rounds per
screen) that was most of the ground stage's screening. Here triangles live in
slots that never move and vertices keep their ids: a round marks the holes'
triangles dead, appends the fill and links it to the triangles around, and only
the vertices around the holes have their neighbours gathered (``rows``).

The fill is ``Tin.without``'s (the same Delaunay of the same rim points, the same
walk picking the triangles inside the holes, the same checks), and the live slots
in order are the triangles of ``Tin.without``'s TIN in its order, so ``tin()``
gives the TIN ``Tin.without`` would have given, bit for bit. Where ``Tin.without``
would rebuild the TIN from scratch (rims too large, a fill that does not check
out) ``patch`` returns None, changes nothing, and the caller hands over to it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import QhullError

from terrasift.workers.ground._kernels import _fans, _walk_kernel
from terrasift.workers.ground.tin import REBUILD_SHARE, Mesh, Tin, _area, _transforms, delaunay


class HoledTin:
    """A TIN whose vertices keep their ids and triangles their slots while
    vertices are deleted (``patch``); ``tin()`` is the current TIN."""

    def __init__(self, tin: Tin, uses: NDArray[np.int64]):
        mesh = tin.tri
        m, n = mesh.simplices.shape[0], tin.n_vertices
        cap = m + m // 8 + 64  # slots past ``slots`` are never read; more on demand
        self.simp = np.empty((cap, 3), dtype=np.int32)
        self.simp[:m] = mesh.simplices
        self.nbr = np.empty((cap, 3), dtype=np.int32)
        self.nbr[:m] = mesh.neighbors
        self.trans = np.empty((cap, 6))
        self.trans[:m] = tin._transform()
        self.live = np.zeros(cap, dtype=bool)
        self.live[:m] = True
        self.slots = m  # slots in use, live or dead
        self.origin, self.xy, self.z = tin.origin, tin.xy, tin.z
        self.alive = np.ones(n, dtype=bool)
        self.vt = np.zeros(n, dtype=np.int64)  # a live triangle holding each vertex
        self.vt[mesh.simplices.ravel()] = np.repeat(np.arange(m), 3)
        self.uses = uses  # live triangles holding each vertex
        self.n_alive, self.m_alive = n, m
        self.open = int(np.count_nonzero(mesh.neighbors < 0))  # hull edges
        self.changed = False
        self._tin = tin
        self._in_hole = np.zeros(cap, dtype=bool)
        self._start = np.zeros(n, dtype=np.int64)

    @classmethod
    def of(cls, tin: Tin) -> HoledTin | None:
        """The holed TIN of ``tin``, or None where ``Tin.without`` would rebuild
        every round (a scipy triangulation, or a vertex in no triangle)."""
        if not isinstance(tin.tri, Mesh):
            return None
        uses = np.bincount(np.asarray(tin.tri.simplices).ravel(), minlength=tin.n_vertices)
        if uses.size != tin.n_vertices or not uses.all():
            return None
        return cls(tin, uses.astype(np.int64))

    def rows(self, verts: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
        """CSR neighbours of ``verts`` (row i: those of ``verts[i]``, ascending ids),
        or None when a fan could not be walked whole."""
        _, _, nptr, nidx, ok = _fans(verts, self.vt, self.simp, self.nbr, self.uses)
        return (nptr, nidx) if ok else None

    def patch(self, drop: NDArray[np.int64]) -> NDArray[np.int64] | None:
        """Delete the vertices ``drop`` (ascending ids, alive) and fill their holes as
        ``Tin.without`` does; the rim vertices (ascending), or None (nothing
        changed) where ``Tin.without`` would rebuild the TIN or a fan is not whole."""
        _, tris, _, _, ok = _fans(drop, self.vt, self.simp, self.nbr, self.uses)
        if not ok:
            return None
        dropped = np.zeros(self.xy.shape[0], dtype=bool)
        dropped[drop] = True
        hole = np.unique(tris)
        hs = self.simp[hole]
        rim = np.unique(hs[~dropped[hs]])
        n_new = self.n_alive - drop.size
        if rim.size < 3 or rim.size > REBUILD_SHARE * n_new:
            return None
        try:
            sub = delaunay(self.xy[rim])
        except QhullError:
            return None
        ss = rim[sub.simplices]
        self._start[hs.ravel()] = np.repeat(hole, 3)
        t = self._start[ss[:, 0]].copy()
        _walk_kernel(
            np.ascontiguousarray(self.xy[ss].mean(axis=1)),
            t, self.trans, self.nbr.ravel(), np.empty(t.size), np.empty(t.size),
        )  # fmt: skip
        in_hole = self._in_hole
        in_hole[hole] = True
        fill = ss[(t >= 0) & in_hole[np.maximum(t, 0)]]
        links = self._links(hole, fill, in_hole)
        in_hole[hole] = False
        if links is None:
            return None
        border, border_to, fill_nb, unmatched = links
        # Euler's count, every rim vertex still in a triangle, the area (as Mesh.patched, Tin.without).
        nb_h = self.nbr[hole]
        open_new = self.open - int(np.count_nonzero(nb_h < 0)) + unmatched
        m_new = self.m_alive - hole.size + fill.shape[0]
        if m_new != 2 * n_new - 2 - open_new:
            return None
        kept = hs[~dropped[hs]]
        uses = (
            self.uses[rim]
            - np.bincount(np.searchsorted(rim, kept), minlength=rim.size)
            + np.bincount(np.searchsorted(rim, fill.ravel()), minlength=rim.size)
        )
        if not uses.all():
            return None
        t_h, j_h = np.nonzero(nb_h < 0)
        on_hull = hs[t_h, (j_h + 1) % 3], hs[t_h, (j_h + 2) % 3]
        if not (dropped[on_hull[0]].any() or dropped[on_hull[1]].any()):
            a_hole, a_fill = _area(self.xy, hs).sum(), _area(self.xy, fill).sum()
            if abs(a_fill - a_hole) > 1e-9 * max(a_hole, 1.0):
                return None
        self._commit(drop, hole, rim, uses, fill, fill_nb, border, border_to, open_new)
        return rim

    def _links(
        self, hole: NDArray[np.int64], fill: NDArray, in_hole: NDArray[np.bool_]
    ) -> tuple[tuple[NDArray, NDArray], NDArray, NDArray, int] | None:
        """Neighbours across the fill's edges and the border's (the live triangles'
        edges onto the holes), matched by their vertex pairs as ``Mesh.patched``
        does: the border slots, the triangle each now faces, the fill's
        neighbours and the count of edges left open; None where it fails."""
        nb_h = self.nbr[hole]
        cand = np.unique(nb_h[nb_h >= 0])
        cand = cand[~in_hole[cand]]
        bnb = self.nbr[cand]
        bk, bj = np.nonzero((bnb >= 0) & in_hole[np.maximum(bnb, 0)])
        sk = self.simp[cand[bk]]
        nb_b, f = bk.size, fill.shape[0]
        ea = np.concatenate([sk[np.arange(nb_b), (bj + 1) % 3], fill[:, [1, 2, 0]].ravel()])
        eb = np.concatenate([sk[np.arange(nb_b), (bj + 2) % 3], fill[:, [2, 0, 1]].ravel()])
        key = np.minimum(ea, eb).astype(np.int64) * self.xy.shape[0] + np.maximum(ea, eb)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        same = ks[1:] == ks[:-1]
        if (same[1:] & same[:-1]).any():
            return None  # an edge in three triangles: overlap
        i, j = order[:-1][same], order[1:][same]
        if ((i < nb_b) & (j < nb_b)).any():
            return None
        # Each edge's triangle: a border slot's live triangle, or a fill triangle's new slot.
        tri = np.concatenate([cand[bk], self.slots + np.arange(f).repeat(3)])
        faces = np.full(nb_b + 3 * f, -1, dtype=np.int64)
        faces[i] = tri[j]
        faces[j] = tri[i]
        unmatched = nb_b + 3 * f - 2 * i.size
        return (cand[bk], bj), faces[:nb_b], faces[nb_b:].reshape(f, 3), unmatched

    def _commit(
        self,
        drop: NDArray[np.int64],
        hole: NDArray[np.int64],
        rim: NDArray,
        uses: NDArray[np.int64],
        fill: NDArray,
        fill_nb: NDArray[np.int64],
        border: tuple[NDArray, NDArray],
        border_to: NDArray[np.int64],
        open_new: int,
    ) -> None:
        """Apply a checked patch: holes dead, fill appended and linked."""
        f = fill.shape[0]
        if self.slots + f > self.live.size:
            self._grow(self.slots + f)
        new = np.arange(self.slots, self.slots + f)
        self.simp[new] = fill
        self.nbr[new] = fill_nb
        self.trans[new] = _transforms(self.xy, fill)
        self.nbr[border] = border_to
        self.live[hole] = False
        self.live[new] = True
        self.vt[self.simp[border[0]].ravel()] = np.repeat(border[0], 3)
        self.vt[fill.ravel()] = np.repeat(new, 3)
        self.alive[drop] = False
        self.uses[rim] = uses
        self.uses[drop] = 0
        self.slots += f
        self.n_alive -= drop.size
        self.m_alive += f - hole.size
        self.open = open_new
        self.changed = True

    def _grow(self, need: int) -> None:
        cap = max(2 * self.live.size, need)
        for name in ("simp", "nbr", "trans", "live", "_in_hole"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[: old.shape[0]] = old  # zeros: the live and hole flags of new slots
            setattr(self, name, new)

    def ids(self) -> NDArray[np.int64]:
        """Ids of the vertices still in the TIN, ascending."""
        return np.flatnonzero(self.alive)

    def tin(self) -> Tin:
        """The current TIN (vertices and triangles in order, as ``Tin.without``'s)."""
        if not self.changed:
            return self._tin
        live = np.flatnonzero(self.live[: self.slots])
        renum = np.full(self.slots + 1, -1, dtype=np.int32)  # the last entry answers -1
        renum[live] = np.arange(live.size)
        new_id = np.cumsum(self.alive, dtype=np.int32) - 1
        mesh = Mesh(new_id[self.simp[live]], renum[self.nbr[live]], self.n_alive)
        tin = Tin._from_mesh(self.xy[self.alive], self.z[self.alive], self.origin, mesh)
        tin._trans = self.trans[live]
        return tin

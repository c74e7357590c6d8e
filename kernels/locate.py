"""Point location in a triangle mesh with a uniform bucket grid (for mesh-to-mesh transfer)."""

import numpy as np

from ._jit import jit
from .pool import parallel_for

__all__ = ["bucket_grid", "locate_points"]


@jit
def _cells(vertices, tri, nbx, nby, x0, y0, dx, dy):
    xmin = xmax = vertices[tri[0], 0]
    ymin = ymax = vertices[tri[0], 1]
    for v in range(1, 3):
        x = vertices[tri[v], 0]
        y = vertices[tri[v], 1]
        xmin = min(xmin, x)
        xmax = max(xmax, x)
        ymin = min(ymin, y)
        ymax = max(ymax, y)
    i0 = min(max(int((xmin - x0) / dx), 0), nbx - 1)
    i1 = min(max(int((xmax - x0) / dx), 0), nbx - 1)
    j0 = min(max(int((ymin - y0) / dy), 0), nby - 1)
    j1 = min(max(int((ymax - y0) / dy), 0), nby - 1)
    return i0, i1, j0, j1


@jit
def bucket_grid(vertices, triangles, nbx, nby, x0, y0, dx, dy):
    """CSR lists of the triangles whose bounding box meets each bucket.

    Bucket ``(i, j)`` (``i`` along x) is number ``j * nbx + i``.

    Returns
    -------
    ptr : int64 (nbx * nby + 1,)
    items : int64
    """
    m = triangles.shape[0]
    ptr = np.zeros(nbx * nby + 1, dtype=np.int64)
    for k in range(m):
        i0, i1, j0, j1 = _cells(vertices, triangles[k], nbx, nby, x0, y0, dx, dy)
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                ptr[j * nbx + i + 1] += 1
    for b in range(nbx * nby):
        ptr[b + 1] += ptr[b]
    items = np.empty(ptr[-1], dtype=np.int64)
    fill = ptr[:-1].copy()
    for k in range(m):
        i0, i1, j0, j1 = _cells(vertices, triangles[k], nbx, nby, x0, y0, dx, dy)
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                b = j * nbx + i
                items[fill[b]] = k
                fill[b] += 1
    return ptr, items


def locate_points(points, vertices, triangles, ptr, items, nbx, nby, x0, y0, dx, dy):
    """Containing triangle and barycentric coordinates of each point.

    A point inside no candidate triangle (outside the mesh, e.g. across a
    curved boundary) gets the candidate it is closest to in barycentric
    terms, with its coordinates clipped to [0, 1] and renormalised.

    Returns
    -------
    tri : int64 (P,)
        -1 when the point's bucket holds no triangle at all.
    bary : float64 (P, 3)
    """
    n = points.shape[0]
    tri = np.full(n, -1, dtype=np.int64)
    bary = np.zeros((n, 3))
    parallel_for(
        _locate_range,
        n,
        points,
        vertices,
        triangles,
        ptr,
        items,
        nbx,
        nby,
        x0,
        y0,
        dx,
        dy,
        tri,
        bary,
    )
    return tri, bary


@jit
def _locate_range(
    lo, hi, points, vertices, triangles, ptr, items, nbx, nby, x0, y0, dx, dy, tri, bary
):
    for p in range(lo, hi):
        px = points[p, 0]
        py = points[p, 1]
        i = min(max(int((px - x0) / dx), 0), nbx - 1)
        j = min(max(int((py - y0) / dy), 0), nby - 1)
        b = j * nbx + i
        best = -np.inf
        for q in range(ptr[b], ptr[b + 1]):
            k = items[q]
            ax = vertices[triangles[k, 0], 0]
            ay = vertices[triangles[k, 0], 1]
            bx = vertices[triangles[k, 1], 0] - ax
            by = vertices[triangles[k, 1], 1] - ay
            cx = vertices[triangles[k, 2], 0] - ax
            cy = vertices[triangles[k, 2], 1] - ay
            det = bx * cy - by * cx
            rx = px - ax
            ry = py - ay
            l1 = (rx * cy - ry * cx) / det
            l2 = (bx * ry - by * rx) / det
            l0 = 1.0 - l1 - l2
            worst = min(l0, min(l1, l2))
            if worst > best:
                best = worst
                tri[p] = k
                bary[p, 0] = l0
                bary[p, 1] = l1
                bary[p, 2] = l2
        if tri[p] >= 0 and best < 0.0:
            s = 0.0
            for v in range(3):
                bary[p, v] = min(max(bary[p, v], 0.0), 1.0)
                s += bary[p, v]
            for v in range(3):
                bary[p, v] /= s

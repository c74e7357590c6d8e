"""Greedy maximal independent set of a vertex graph (coarse vertices of an unstructured mesh)."""

import numpy as np

from ._jit import jit

__all__ = ["independent_set"]


@jit
def independent_set(indptr, indices, order):
    """Maximal independent set of the graph ``(indptr, indices)``, greedy in ``order``.

    A vertex is taken when none of its neighbours was taken before it; every
    vertex left out has a taken neighbour.  Vertices missing from ``order``
    are neither taken nor excluded by themselves.

    Returns
    -------
    bool (n,)
        Mask of the taken vertices.
    """
    n = indptr.size - 1
    state = np.zeros(n, dtype=np.int8)  # 0 free, 1 taken, 2 next to a taken vertex
    for t in range(order.size):
        v = order[t]
        if state[v] != 0:
            continue
        state[v] = 1
        for q in range(indptr[v], indptr[v + 1]):
            w = indices[q]
            if state[w] == 0:
                state[w] = 2
    return state == 1

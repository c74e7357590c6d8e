"""The one place where kernel compilation flags are set."""

import functools

import numba

__all__ = ["FASTMATH", "jit", "pjit"]

# No "nnan"/"ninf": max(0, .) and active-set comparisons need IEEE semantics.
FASTMATH = frozenset({"nsz", "arcp", "contract", "afn", "reassoc"})

jit = functools.partial(numba.njit, cache=True, fastmath=set(FASTMATH), nogil=True)
pjit = functools.partial(numba.njit, cache=True, fastmath=set(FASTMATH), nogil=True, parallel=True)

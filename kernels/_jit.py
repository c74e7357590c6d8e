"""The one place where kernel compilation flags are set.

Numba's cache (``cache=True``) is checked against the modification time of the
file that defines a kernel only: after editing a ``@jit`` helper that kernels of
other modules call (e.g. :func:`fastmem.kernels.cut.nonconformity`, called by
:func:`fastmem.kernels.sums.global_blocks`), touch those modules or delete
``kernels/__pycache__``, or they keep the old helper's code.  An install copies
every file anew, so users never meet this.
"""

import functools

import numba

__all__ = ["FASTMATH", "jit", "jit_divide", "pjit"]

# No "nnan"/"ninf": max(0, .) and active-set comparisons need IEEE semantics.
# No "contract"/"reassoc": with them the flux estimators differed in the last bits
# between a kernel compiled in the running process and the same kernel loaded from
# Numba's cache (LLVM fuses and reorders differently depending on what it inlines),
# so the first run after an install could refine a different adaptive mesh than
# every later run (L-shape, tol 5e-3: 52,677 vs 39,682 vertices).  Without them
# both give the same bits; no speed difference was measurable (n = 512 solve,
# estimate and assembly).
FASTMATH = frozenset({"nsz", "arcp", "afn"})

jit = functools.partial(numba.njit, cache=True, fastmath=set(FASTMATH), nogil=True)
#: The flags without "arcp", for kernels that must divide as NumPy does: with it LLVM
#: turns a division by a loop invariant into a product with its reciprocal (the
#: decoupled triple's ``/ (mu1 + mu2)`` differed from NumPy's in the last bit).
jit_divide = functools.partial(
    numba.njit, cache=True, fastmath=set(FASTMATH - {"arcp"}), nogil=True
)
#: Numba's parallel compiler: no kernel of this version uses it (kernels.pool says
#: why); the baseline kernels that benchmarks load from the project's history do
#: (bench/estimate.py ``base_reconstruct``).
pjit = functools.partial(numba.njit, cache=True, fastmath=set(FASTMATH), nogil=True, parallel=True)

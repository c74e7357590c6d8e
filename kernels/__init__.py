"""Numba kernels of fastmem (installed as ``fastmem.kernels``).

Pure functions over contiguous NumPy arrays and scalars.  They validate
nothing: the ``fastmem`` layer checks every input before calling them.  This
package imports only numpy, numba and the standard library, never ``fastmem``.
"""

from ._jit import FASTMATH

__all__ = ["FASTMATH"]

"""glibc keeps the memory fastmem frees (fastmem.memory.keep_freed_memory, made at import).

glibc maps arrays above its mmap threshold into fresh pages that fault in
again at every allocation; after ``import fastmem`` it takes them from its
heap and keeps what is freed, until :func:`fastmem.release_memory`.  Checked
through glibc's own account (``mallinfo2``: bytes in mmapped chunks) and the
resident memory; the switch ``FASTMEM_REUSE_HEAP=0`` in a fresh process; and
a solve gives the same bits with either allocator setting.
"""

import ctypes
import os
import subprocess
import sys

import numpy as np
import pytest

import fastmem as fm
from fastmem.memory import REUSE_HEAP_ENV, rss_bytes

MB = 1 << 20


class _Mallinfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd",
            "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
        )
    ]  # fmt: skip


def _libc():
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _Mallinfo2
    except (OSError, AttributeError):
        pytest.skip("glibc >= 2.33 (mallinfo2) only: elsewhere the allocator is left alone")
    if os.environ.get(REUSE_HEAP_ENV, "1").strip().lower() in ("0", "no", "false", "off"):
        pytest.skip(f"{REUSE_HEAP_ENV} switches the setting off in this process")
    return libc


def _mmapped(libc) -> int:
    """Bytes glibc holds in mmapped chunks now."""
    return int(libc.mallinfo2().hblkhd)


def _touched(nbytes):
    a = np.empty(nbytes // 8)
    a.fill(1.0)  # resident
    return a


def test_freed_arrays_stay_and_are_reused_until_released():
    libc = _libc()
    before = _mmapped(libc)
    a = _touched(96 * MB)
    assert _mmapped(libc) - before < 8 * MB  # from the heap, not an mmapped chunk
    held = rss_bytes()
    del a
    assert rss_bytes() > held - 24 * MB  # freed, kept for the next array
    b = _touched(96 * MB)  # reuses it: no new memory
    assert rss_bytes() < held + 24 * MB
    del b
    kept = rss_bytes()
    assert fm.release_memory()
    assert rss_bytes() < kept - 64 * MB  # given back


def test_switched_off_by_the_environment_at_import():
    """With FASTMEM_REUSE_HEAP=0, ``import fastmem`` leaves glibc's mmap of large arrays."""
    _libc()
    code = (
        "import ctypes, numpy as np, fastmem\n"
        "class M(ctypes.Structure):\n"
        "    _fields_ = [(n, ctypes.c_size_t) for n in 'abcdefghij']\n"
        "libc = ctypes.CDLL('libc.so.6'); libc.mallinfo2.restype = M\n"
        "h0 = libc.mallinfo2().e\n"
        "a = np.ones(12 << 20)\n"  # 96 MiB
        "print(libc.mallinfo2().e - h0, fastmem.memory.keep_freed_memory())\n"
    )
    out = {}
    for value in ("0", "1"):
        env = dict(os.environ, **{REUSE_HEAP_ENV: value})
        run = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
        )
        assert run.returncode == 0, run.stderr
        delta, kept = run.stdout.split()
        out[value] = (int(delta), kept)
    assert out["0"] == (out["0"][0], "False")
    assert out["0"][0] >= 96 * MB  # mmapped: glibc as it is
    assert out["1"] == (out["1"][0], "True")
    assert out["1"][0] < 8 * MB  # from the heap


def test_a_solve_gives_the_same_bits_with_either_allocator_setting():
    libc = _libc()

    def solve():
        r = fm.solve(fm.Scene(fm.Mesh.square(48), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
        return r.eta, r.u1, r.u2, r.lam

    kept = solve()
    m_mmap_max = -4
    libc.mallopt(ctypes.c_int(m_mmap_max), ctypes.c_int(65536))  # glibc's default again
    try:
        plain = solve()
    finally:
        libc.mallopt(ctypes.c_int(m_mmap_max), ctypes.c_int(0))  # the package's setting back
    assert kept[0] == plain[0]
    for x, y in zip(kept[1:], plain[1:], strict=True):
        np.testing.assert_array_equal(x, y)


def test_fixed_mmap_threshold_where_the_heap_is_not_kept():
    """fix_mmap_threshold (the sweep tasks' setting when FASTMEM_REUSE_HEAP=0): an array
    below the threshold comes from the heap, one above it is mmapped."""
    _libc()
    code = (
        "import ctypes, numpy as np, fastmem.memory as m\n"
        "class M(ctypes.Structure):\n"
        "    _fields_ = [(n, ctypes.c_size_t) for n in 'abcdefghij']\n"
        "libc = ctypes.CDLL('libc.so.6'); libc.mallinfo2.restype = M\n"
        "print(m.fix_mmap_threshold(256 << 20))\n"
        "for words in (12 << 20, 48 << 20):\n"  # 96 MiB, 384 MiB
        "    h0 = libc.mallinfo2().e\n"
        "    a = np.ones(words)\n"
        "    print(libc.mallinfo2().e - h0)\n"
        "    del a\n"
    )
    env = dict(os.environ, **{REUSE_HEAP_ENV: "0"})
    run = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    ok, below, above = run.stdout.split()
    assert ok == "True"
    assert int(below) < 8 * MB  # 96 MiB < 256 MiB: heap
    assert int(above) >= 384 * MB  # mmapped

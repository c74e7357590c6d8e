"""First-run compilation: the helper process of :func:`fastmem.warm_up`, and the
kernels that run without Numba's parallel compiler.

* :func:`fastmem.kernels.flux.precompile` must compile exactly the
  specialisations a real reconstruction uses (otherwise the helper's work is
  wasted and the kernel compiles twice);
* a cold ``fastmem run`` with the helper (empty Numba cache, fresh process)
  gives the same bound as the in-process solve, and says the helper was used;
* a helper that fails leaves the warm-up working (the kernel compiles in the
  calling process);
* the chunked kernels give the same bits for any thread count and chunk size.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading

import numba
import numpy as np
import pytest
from fastmem.kernels import cut as kcut
from fastmem.kernels import flux as kf
from fastmem.kernels import nvb as knvb
from fastmem.kernels import pool as _par
from fastmem.kernels import topology as ktopology
from fresh import compiled_after, run_python

import fastmem as fm
from fastmem.cli import warmup
from fastmem.estimators import bound, flux
from fastmem.mesh import refine


def test_precompile_compiles_the_pipeline_specialisations():
    """precompile() and a real reconstruction + flux estimators share one specialisation."""
    for part in ("callees", "solvers", "coefficients", "estimators", "patches"):
        kf.precompile(part)
    kcut.precompile()  # the helper's first part (fastmem.cli.warmup)
    x = fm.Mesh.square(6)
    mu1 = np.where(x.vertices[x.triangles, 0].mean(axis=1) < 0.5, 1.0, 1e4)
    for mu in ((1.0, 1.0), (mu1, 2.0)):
        scene = fm.Scene(x, mu=mu, f=(-1.0, 1.0), g=0.1)
        res = fm.solve(scene)  # the pipeline's own calls (inexact checks, the bound)
        # and the public functions on a Result's (read-only) arrays
        fluxes = flux.reconstruct(scene, res.u1, res.u2, res.lam)
        bound.flux_terms(scene, res.u1, res.u2, fluxes)
    kernels = (
        kf._reconstruct_chunk,
        kf._reconstruct_chunk_weighted,
        kf._member_chunk,
        kf._patch_loads,
        kf._class_fill,
        kf._class_store,
        kf._reduced_solve1,
        kf._reduced_solve2,
        kf._refine_balance,
        kf._coefficients_chunk,
        kf._estimators_chunk,
        kf.color_vertices,
    )
    # at most one: a kernel loaded from the cache as a callee has none in-process
    counts = {d.__name__: len(d.signatures) for d in kernels}
    assert all(c <= 1 for c in counts.values()), counts
    assert counts["_reconstruct_chunk"] == counts["_estimators_chunk"] == 1, counts
    assert counts["color_vertices"] == 1, counts
    # the contact terms: the helper's specialisation is the one the checks and the bound use
    assert len(kcut._contact_terms_range.signatures) == 1


def test_callees_part_compiles_the_patch_kernels_own_specialisation(tmp_path):
    """Part "callees" (the caller's share of the patch kernel, written-out types) compiles
    the very specialisation the patch kernel's typing asks for: in a fresh process with
    an empty cache, compiling the patch kernel after it adds no second one."""
    script = (
        "from fastmem.kernels import flux\n"
        "flux.precompile('callees')\n"
        "flux.precompile('patches')\n"
        "counts = [len(d.signatures) for d, _ in flux._callee_signatures()]\n"
        "assert counts == [1] * len(counts), counts\n"
        "print('ok')\n"
    )
    out = run_python(script, env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
    assert "ok" in out


def test_precompile_refuses_an_unknown_part():
    with pytest.raises(ValueError, match="'everything'"):
        kf.precompile("everything")


def _eta(text: str) -> float:
    m = re.search(r"error bound eta\s+([0-9.eE+-]+)", text)
    assert m, text
    return float(m.group(1))


def test_cold_run_with_helper_matches_in_process_solve(tmp_path):
    """Empty cache, fresh process: the helper compiles the flux kernel; same eta."""
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
        "FASTMEM_COMPILE_HELPER": "1",
    }
    cmd = [sys.executable, "-m", "fastmem", "run", "--n", "16", "--no-save"]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "compiling Numba kernels (first use) ..." in res.stdout, res.stdout  # nothing cached
    assert "note: kernels compile on first use" in res.stdout, res.stdout
    if warmup._cpus() >= 2:
        assert "in a helper process" in res.stdout, res.stdout
    expected = fm.solve(fm.Scene(fm.Mesh.square(16), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
    assert _eta(res.stdout) == pytest.approx(expected.eta, rel=1e-4)  # printed with 5 digits
    # the helper wrote the flux kernel where the second run finds it
    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "Numba kernels (loading from cache, compiling any not there) ..." in again.stdout
    assert "(0 compiled, " in again.stdout, again.stdout
    assert "helper" not in again.stdout
    assert "note:" not in again.stdout  # said only by a run that compiled
    assert _eta(again.stdout) == _eta(res.stdout)


@pytest.mark.parametrize("adaptive", [False, True])
def test_failing_helper_falls_back_to_compiling_here(monkeypatch, adaptive):
    """A helper that exits with an error: the warm-up still completes, no helper left.

    With ``adaptive`` the helper was also to compile the bisection kernels: the tiny
    adaptive solve's refinement waits for it, then compiles them here.
    """
    monkeypatch.setattr(warmup, "_HELPER_CODE", "raise SystemExit(3)")
    monkeypatch.setattr(warmup, "_cached", lambda d: False)
    monkeypatch.setattr(warmup, "_cpus", lambda: 2)
    monkeypatch.setenv("FASTMEM_COMPILE_HELPER", "1")
    compiled_here = []
    monkeypatch.setattr(warmup.linear, "precompile", lambda: compiled_here.append(1))
    done = warmup.warm_up("inexact", adaptive=adaptive)
    assert done.helper
    assert kf.compile_gate is None
    assert refine.compile_gate is None
    assert warmup._helper is None
    # the linear steps' passes the helper was to compile: here, once
    assert compiled_here == ([1] if adaptive else [])


@pytest.mark.parametrize(
    ("general", "adaptive", "parts"),
    [
        (False, False, ("patches",)),
        (True, False, ("weighted",)),
        (False, True, ("patches", "refinement")),
    ],
)
def test_warm_up_asks_the_helper_for_the_kernels_it_needs(monkeypatch, general, adaptive, parts):
    """Per-triangle tensions (general=True) have their own patch kernel: the helper compiles
    it; a solve to a tolerance also has it compile the bisection kernels."""
    asked = []
    monkeypatch.setattr(warmup, "spawn_compile_helper", lambda *parts: asked.append(parts))
    done = warmup.warm_up("inexact", general=general, adaptive=adaptive)
    assert asked == [parts]
    assert not done.helper  # the stand-in started none: compiled (or loaded) here
    assert refine.compile_gate is None


def test_refine_precompile_compiles_the_loop_specialisations():
    """The helper's ``"refinement"`` part and an adaptive solve share one specialisation
    of each bisection kernel (otherwise the loop compiles them a second time)."""
    refine.precompile()
    scene = fm.Scene(fm.Mesh.lshape(4), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    fm.solve(scene, tol=1e-9, max_levels=3)  # three meshes, two refinements
    kernels = (
        knvb._longest_edge_range,
        knvb.closure,
        knvb._count_children_range,
        knvb._children_range,
        ktopology._refined_new_edges,
        ktopology._surviving_edges_range,
    )
    counts = {d.__name__: len(d.signatures) for d in kernels}
    assert all(c == 1 for c in counts.values()), counts


def test_helper_gets_the_package_and_kernel_folders(monkeypatch):
    """The helper imports ``fastmem.mesh`` through the folder it is given: that of the
    package (an editable install finds it anyway; an installed one only there)."""
    started = []

    class Popen:
        def __init__(self, args, **kwargs):
            started.append(args)

    monkeypatch.setattr(warmup, "_cached", lambda d: False)
    monkeypatch.setattr(warmup, "_cpus", lambda: 2)
    monkeypatch.setenv("FASTMEM_COMPILE_HELPER", "1")
    monkeypatch.setattr(warmup.subprocess, "Popen", Popen)
    assert warmup.spawn_compile_helper("patches", "refinement") is not None
    (args,) = started
    assert args[3] == os.path.dirname(os.path.abspath(fm.__file__))
    assert args[4] == os.path.dirname(os.path.abspath(kf.__file__))
    assert os.path.isfile(os.path.join(args[3], "mesh", "refine.py"))
    assert args[5:] == ["patches", "refinement"]


def test_spawn_compile_helper_wants_a_patch_kernel_first():
    with pytest.raises(ValueError, match="first part"):
        warmup.spawn_compile_helper("refinement")


def test_adaptive_warm_up_covers_the_loop():
    """After fm.warm_up(adaptive=True), in a fresh process, a solve to a tolerance whose
    meshes pass the sizes of the threaded, nested and large-mesh kernels compiles nothing
    (a first ``fastmem run --tol`` compiled 2.5 s of them inside its solve)."""
    work = (
        "scene = fm.Scene(fm.Mesh.square(128), mu=(1, 1), f=(-1, 1), g=0.1)\n"
        "r = fm.solve(scene, tol=5e-3)\n"
        "assert r.mesh.n_triangles > 65536 and r.converged, (r.mesh.n_triangles, r.status)"
    )
    assert compiled_after("fm.warm_up('inexact', adaptive=True)", work) == []


def test_large_warm_up_covers_the_banded_flux():
    """After fm.warm_up(large=True), in a fresh process, a solve on a mesh of 100,000
    vertices and more (patch classes, sweep order, the banded flux estimators) compiles
    nothing: the warm-up calls them with the types a solve passes."""
    work = (
        "from fastmem.estimators import flux\n"
        "mesh = fm.Mesh.square(320)\n"
        "r = fm.solve(fm.Scene(mesh, mu=(1, 1), f=(-1, 1), g=0.1))\n"
        "assert flux.band_plan(mesh) is not None and 'flux_window' in mesh._cache"
    )
    assert compiled_after("fm.warm_up('inexact', large=True)", work) == []


@pytest.mark.parametrize(
    ("large", "general", "cycles", "nested"),
    [(False, False, 0, 0), (False, True, 1, 0), (True, False, 1, 1)],
)
def test_warm_up_compiles_the_threaded_sweeps_only_for_solves_that_use_them(
    monkeypatch, large, general, cycles, nested
):
    calls = {"cycles": 0, "nested": 0}
    monkeypatch.setattr(warmup, "precompile", lambda: calls.__setitem__("cycles", 1))
    monkeypatch.setattr(warmup.gmg, "precompile", lambda: calls.__setitem__("nested", 1))
    warmup._precompile_cycles(large, general)
    assert calls == {"cycles": cycles, "nested": nested}


def test_default_run_never_calls_the_threaded_sweeps(monkeypatch):
    """The premise of skipping them: the default scene (n = 128) stays below their sizes."""
    from fastmem.linalg import amg, gmg, sparse

    called = []

    def spy(name):
        return lambda *a, **k: called.append(name)

    for module in (amg, gmg):
        for name in ("gs_hybrid_range", "csr_matvec_range", "cross_block_dominant"):
            monkeypatch.setattr(module, name, spy(name))
    monkeypatch.setattr(sparse, "csr_matvec_range", spy("csr_matvec_range"))
    r = fm.solve(fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
    assert r.converged
    assert called == []


def test_spawn_compile_helper_refuses_an_unknown_part():
    with pytest.raises(ValueError, match="'everything'"):
        warmup.spawn_compile_helper("patches", "everything")


def test_kernels_cached_refuses_an_unknown_scope():
    with pytest.raises(ValueError, match="'some'"):
        warmup.kernels_cached("some")
    assert warmup.kernels_cached("all") in (True, False)


def test_helper_switched_off(monkeypatch):
    monkeypatch.setattr(warmup, "_cached", lambda d: False)
    monkeypatch.setattr(warmup, "_cpus", lambda: 2)
    monkeypatch.setenv("FASTMEM_COMPILE_HELPER", "0")
    assert warmup.start_compile_helper() is False
    assert not warmup.warm_up("inexact").helper


@pytest.mark.parametrize(
    ("n", "threads", "grain"), [(0, 2, 1), (5, 2, 1), (10, 3, 4), (4096, 2, 4096)]
)
def test_ranges_cover_in_order(n, threads, grain):
    chunks = _par.ranges(n, threads, grain)
    assert chunks[0][0] == 0
    assert chunks[-1][1] == n
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:], strict=False))
    assert len(chunks) <= max(1, threads)
    assert all(hi - lo >= min(grain, n) for lo, hi in chunks)


def test_run_ranges_raises_a_chunk_error():
    def fn(lo, hi):
        if lo > 0:
            raise RuntimeError(f"chunk {lo}")

    with pytest.raises(RuntimeError, match="chunk"):
        _par.run_ranges(fn, [(0, 1), (1, 2), (2, 3)])


def test_flux_bits_independent_of_threads_and_chunks(monkeypatch):
    """Same coefficients with 1 thread, all threads, and chunks of one patch / triangle."""
    mesh = fm.Mesh.square(12)
    scene = fm.Scene(mesh, mu=(1.0, 3.0), f=(-1.0, 1.0), g=0.1)
    res = fm.solve(scene, method="exact")
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = flux.reconstruct(scene, res.u1, res.u2, res.lam).coef
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = flux.reconstruct(scene, res.u1, res.u2, res.lam).coef
        monkeypatch.setattr(kf, "PATCH_GRAIN", 1)
        monkeypatch.setattr(kf, "TRIANGLE_GRAIN", 1)
        tiny = flux.reconstruct(scene, res.u1, res.u2, res.lam).coef
        monkeypatch.setattr(kf, "PATCH_PIECES", 1)  # one fixed chunk per thread
        fixed = flux.reconstruct(scene, res.u1, res.u2, res.lam).coef
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(one, many)
    assert np.array_equal(one, tiny)
    assert np.array_equal(one, fixed)


@pytest.mark.parametrize(("pieces", "threads"), [(0, 2), (1, 2), (7, 1), (7, 3), (40, 2)])
def test_run_pieces_calls_every_piece_once(pieces, threads):
    calls, lock = [], threading.Lock()
    seen_threads = set()

    def fn(lo, hi):
        with lock:
            calls.append((lo, hi))
            seen_threads.add(threading.get_ident())

    chunks = [(k, k + 1) for k in range(pieces)]
    _par.run_pieces(fn, chunks, threads)
    assert sorted(calls) == chunks
    assert len(seen_threads) <= max(1, threads)


def test_run_pieces_raises_a_piece_error():
    def fn(lo, hi):
        if lo == 5:
            raise RuntimeError(f"piece {lo}")

    with pytest.raises(RuntimeError, match="piece 5"):
        _par.run_pieces(fn, [(k, k + 1) for k in range(8)], 2)

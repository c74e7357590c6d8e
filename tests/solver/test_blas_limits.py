"""The BLAS limit of the solver phases: applied in the block, undone after, scanned once."""

import sys
import types

import pytest
import threadpoolctl

from fastmem import config


def _blas_threads():
    return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]


def test_blas_is_limited_in_the_block_and_restored_after():
    before = _blas_threads()
    if not before:
        pytest.skip("no BLAS library loaded")
    with config.blas_limits(1):
        assert _blas_threads() == [1] * len(before)
    assert _blas_threads() == before


def test_the_library_scan_is_kept_until_a_module_is_imported(monkeypatch):
    built = []

    class Counting(threadpoolctl.ThreadpoolController):
        def __init__(self):
            built.append(1)
            super().__init__()

    monkeypatch.setattr(config, "ThreadpoolController", Counting)
    monkeypatch.setitem(config._blas, "controller", None)
    for _ in range(3):
        with config.blas_limits(1):
            pass
    assert len(built) == 1
    # an import since the scan (here a stand-in module): scanned again, then kept
    monkeypatch.setitem(sys.modules, "fastmem_test_new_module", types.ModuleType("x"))
    for _ in range(2):
        with config.blas_limits(1):
            pass
    assert len(built) == 2

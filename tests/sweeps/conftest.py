"""Fixtures of the sweep tests."""

import pytest

from fastmem.sweeps import study as sweeps
from fastmem.sweeps import task


@pytest.fixture
def job_for(tmp_path):
    """Build the worker-side job of one run, ``factory(**params)``, in a study at tmp_path."""

    def make(factory, params):
        name = sweeps.run_name(params)
        (tmp_path / sweeps.RUNS_DIR).mkdir(exist_ok=True)
        return task._Job(
            factory=factory,
            params=params,
            name=name,
            archive=str(tmp_path / sweeps.RUNS_DIR / f"{name}.h5"),
            solve_options={},
            log=str(tmp_path / sweeps.WRITE_LOG),
            threads={},
        )

    return make

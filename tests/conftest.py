import os

# Subprocesses of the tests import the installed fastmem, as the tests do: with the
# working directory (the repository root) first on their sys.path, ``python -c`` and
# ``python -m fastmem`` imported the source tree instead, whose kernels compile into a
# second Numba cache (kernels/__pycache__) that the suite's own warm-up never fills:
# a cold suite spent about 40 s compiling there (clean clone, 2 cores, 2026-12-03:
# 299 s -> 260 s). Python >= 3.11; older ones ignore it and import the tree as before.
# The benchmarks' subprocesses (python -m bench...) get bench/ alone on their path
# (fresh.bench_env).
os.environ["PYTHONSAFEPATH"] = "1"

import numpy as np
import pytest
from meshes import circle_mesh

#: Tests that run only with ``pytest -m slow`` (or all of them with FASTMEM_SLOW=1):
#: the README's ``pytest -q`` must stay within 5 minutes on a fresh 2-core machine,
#: Numba compilation included, and ``.ci/run`` runs these after it.  Keys are node
#: ids below tests/: a file, a test (all its parameters) or one parametrized case.
#: The seconds are those measured on the 2-core machine with a warm kernel cache
#: (issue 32); every layer keeps a fast test of the same property in the default run.
SLOW = {
    "package/test_bench.py": 92.6,  # every benchmark's --quick run, in subprocesses
    # every command line of the README (its contact lines but the figures stay in the
    # default run; tests/cli/test_plot.py draws the figures)
    "package/test_readme.py::test_readme_every_cli_command_runs_in_order": 20.0,
    # 2026-12-02, the suite at 5 min 54 s - 6 min 3 s from a cold kernel cache: the patch
    # classes compile 15 s of kernels that no default-run mesh reaches (they start at
    # 100,000 vertices; the flux tests of the default run check the same fluxes without
    # them; warm_up(large=True) compiles them too), and a fresh process's warm_up compiles
    # what the suite's own solves do not (fast sibling: cli/test_coldstart.py's warm-ups)
    "estimators/test_patch_classes.py": 16.3,
    "obstacle/test_reference_problems.py::test_warm_up_of_an_obstacle_covers_its_solve": 0.5,
    "package/test_newuser.py::test_warm_up_counts_kernels": 13.7,
    # 2026-12-03: whole solves at one and two threads, bit for bit, on meshes that take
    # every threaded path (the kernel tests of the default run check each kernel so)
    "solver/test_thread_count.py": 8.4,
    # 2026-12-03 (twelfth session; the suite at 5 min 14 s in a slow hour's CI): whole
    # n = 256 solves, twice each, that guard a refactoring bit for bit. The mu = (1, 1)
    # case of the one-pass checks stays; the vector kernels' fast siblings are in
    # linalg/test_smooth.py (each kernel against NumPy)
    "solver/test_inexact.py::test_one_pass_checks_change_no_result[mu1]": 5.3,
    "solver/test_inexact.py::test_vector_kernels_change_no_result": 4.4,
    # 2026-12-02, once the suite's time included its kernel warm-up (about 5 min in CI):
    # two of the four checkerboard effectivity rows (the other two stay), one of the two
    # small-angle Piola cases ([stretched] stays), the default-scene example (the README's
    # fastmem run and test_cli.py run it) and the quiet sweep command in a subprocess
    # (test_cluster_has_no_dashboard_and_quiet_workers keeps the quiet workers)
    "estimators/test_bound.py::test_checkerboard_effectivity[0.001-f3]": 1.7,
    "estimators/test_bound.py::test_checkerboard_effectivity[1000.0-f0]": 1.6,
    "estimators/test_rt1_reference.py::test_piola_matches_quadrature[tiny-offset]": 1.3,
    "package/test_examples.py::test_example[default_scene]": 2.5,
    "sweeps/test_sweep_console.py::test_quiet_command_prints_no_info_line": 5.0,
    # and, after a clean CI run of 5 min 1 s with the warm-up counted: the "exact" row of
    # the adaptive bound ("exact-amg" stays), the obstacle min_growth loop (the contact
    # one stays), the singularity at the resolution limit (the limit test stays), the
    # obtuse exact-arithmetic Piola case (the others stay), the unmasked Galerkin kernel
    # (the masked one stays) and the --dpi option (test_cli_default_output keeps sizes)
    "adapt/test_afem.py::test_exact_methods_get_a_bound_on_every_level[exact]": 4.0,
    "adapt/test_adapt_landing.py::test_min_growth_in_the_obstacle_loop": 3.0,
    "adapt/test_afem_resolution.py::test_a_true_singularity_stops_at_the_limit_with_a_sane_bound": 2.1,  # noqa: E501
    "estimators/test_rt1_reference.py::test_piola_matches_exact_arithmetic[obtuse]": 2.7,
    "linalg/test_gmg.py::test_galerkin_kernel_matches_scipy[False]": 2.2,
    "cli/test_plot.py::test_cli_dpi": 1.8,
    # the n = 16 row of the ball's edge integrals (the n = 8 row stays)
    "obstacle/test_reference_data.py::test_ball_energy_error_edge_integrals_match_2d_quadrature[16]": 1.4,  # noqa: E501
    "adapt/test_adapt_landing.py::test_landing_does_not_overshoot_and_still_converges": 17.0,
    "package/test_examples.py::test_example[gallery]": 16.1,  # every figure of docs/gallery.md
    "package/test_scaling.py::test_merge_keeps_the_other_sizes_and_refits": 12.2,
    "cli/test_coldstart.py::test_cold_run_with_helper_matches_in_process_solve": 8.9,
    "cli/test_coldstart.py::test_callees_part_compiles_the_patch_kernels_own_specialisation": 7.0,
    # a fresh process: warm_up(adaptive=True), then a solve to a tolerance past 65,536
    # triangles (fast siblings: the helper's parts and refine.precompile's specialisations)
    "cli/test_coldstart.py::test_adaptive_warm_up_covers_the_loop": 6.0,
    "cli/test_coldstart.py::test_large_warm_up_covers_the_banded_flux": 6.0,
    # a fresh process: warm_up(large=True), then a 66k-vertex solve (about 20 s cold)
    "linalg/test_gmg.py::test_warm_up_compiles_the_nested_multigrid": 2.6,
    # these two offset the default run's share of issue 33's tests (about 10 s): the
    # layer bound above the error stays in test_layer_bound_guaranteed_and_sharp (n = 8),
    # a quiet sweep in test_sweep_console.py::test_cluster_has_no_dashboard_and_quiet_workers
    "estimators/test_layers.py::test_split_form_wins_and_stays_above_the_error": 7.3,
    "sweeps/test_sweep_spawn.py::test_script_with_guard_sweeps_quietly": 5.2,
    # the suite took 5 min 47 s in a clean CI run on 2026-12-01 (a slow day for that
    # machine); these keep fast siblings: the static import graph (no cycles, kernels
    # import nothing from fastmem), test_cli_show (an --output path and a shown figure),
    # test_script_without_guard_gives_one_clear_error (a refused sweep)
    "package/test_imports.py::test_module_imports_alone": 25.5,  # its fixture: 3 processes
    "cli/test_plot.py::test_cli_output_option": 1.7,
    "cli/test_plot.py::test_plot_result_show_uses_pyplot": 1.7,
    "sweeps/test_sweep_spawn.py::test_spawned_process_refuses_to_start_a_sweep": 3.2,
    "sweeps/test_sweep_claims.py::test_orphan_of_killed_client_is_not_solved_again": 8.8,
    "sweeps/test_sweep.py::test_client_killed_and_restarted": 8.0,
    "package/test_imports.py::test_module_imports_alone[bench]": 7.5,
    "package/test_hostile.py::test_corruption_inside_datasets_is_detected": 4.6,
    "estimators/test_cross_point.py::test_checkerboard_effectivity_with_correction[32]": 4.3,
    "package/test_examples.py::test_example[parameter_study]": 4.3,
    "adapt/test_afem.py::test_last_mesh_is_solved_tighter": 3.1,
    "package/test_examples.py::test_example[solve_to_tolerance]": 2.8,
    "package/test_hostile.py::test_load_arbitrary_bytes": 2.3,
    "cli/test_cache.py::test_user_wide_cache_fallback": 2.3,
    "sweeps/test_sweep.py::test_cluster_after_config_block_around_first_distributed_import": 2.0,
    "package/test_hostile.py::test_random_byte_corruption_anywhere": 1.6,
    # 2026-12-02 (third session), the README suite at 4 min 53 s in a clean CI run after
    # the adaptive chain's and the topology paths' tests: two of the three guard-less
    # sweep scripts ([top-level-call] stays), the hypothesis archive round trip
    # (tests/io/test_archive.py keeps the round trips) and the adaptive loop on the chain
    # (test_geometric_multigrid_on_the_adaptive_chain_converges_fast stays)
    "sweeps/test_sweep_spawn.py::test_script_without_guard_gives_one_clear_error[main-without-guard]": 1.6,  # noqa: E501
    "sweeps/test_sweep_spawn.py::test_script_without_guard_gives_one_clear_error[from-a-thread]": 1.8,  # noqa: E501
    "package/test_hostile.py::test_archive_round_trip": 2.0,
    "adapt/test_adapt_chain.py::test_loop_uses_the_chain_and_meets_the_tolerance": 1.1,
    # and after run I (4 min 59 s, the machine slower again): the guard-less script read
    # from stdin ([top-level-call] above stays), one of the two remaining checkerboard
    # rows ([1000.0-f1] stays), the second tension pair of the P1 rate (mu=(1,1) stays),
    # the geometric-against-algebraic solve (the CG and V-cycle tests of test_gmg.py
    # stay), the one-round min_growth loop and the fewer-meshes comparison of two
    # rounds (test_min_growth_above_two_with_two_bisections stays), and two of the
    # three hypothesis runs on hostile meshes (test_valid_meshes_solve stays)
    "sweeps/test_sweep_spawn.py::test_script_read_from_stdin_gives_one_clear_error": 1.6,
    "estimators/test_bound.py::test_checkerboard_effectivity[0.001-f2]": 1.9,
    "fem/test_convergence.py::test_energy_error_rate_is_one[mu=(1,10) kappa=0]": 1.2,
    "linalg/test_gmg.py::test_solve_geometric_against_algebraic": 1.3,
    "adapt/test_adapt_landing.py::test_min_growth_makes_fewer_larger_meshes": 1.1,
    "adapt/test_adapt_chain.py::test_two_bisections_make_fewer_meshes": 1.6,
    "package/test_hostile.py::test_holed_meshes_accepted_or_refused": 1.5,
    "package/test_hostile.py::test_hostile_data": 1.4,
    "package/test_examples.py::test_example[heterogeneous_mu]": 1.6,
    "cli/test_plot.py::test_cli_uniform_archives": 1.6,
    "cli/test_plot.py::test_plot_result_format_from_suffix": 1.5,
    "package/test_hostile.py::test_killed_writer_never_leaves_half_archive": 1.5,
    "estimators/test_rt1_reference.py::test_piola_matches_exact_arithmetic[random]": 1.4,
    "package/test_examples.py::test_example[gmsh_mesh]": 1.4,
    "sweeps/test_sweep.py::test_methods_and_tolerances": 1.3,
    "package/test_examples.py::test_example[read_archive_h5py]": 1.2,
    # 2026-12-02 (second session), the suite at 4 min 32 s - 4 min 49 s in clean CI runs:
    # the square8 rows of the dense flux reference (the same checks stay on square4,
    # square5-right, perturbed, lshape and circle; 7.2 s)
    "estimators/test_flux.py::test_reference_patch_optimality[perturbed-mu-per-triangle-square8]": 1.3,  # noqa: E501
    "estimators/test_flux.py::test_reference_patch_zero_flux[perturbed-callable-square8]": 1.0,
    "estimators/test_flux.py::test_reference_patch_zero_flux[default-square8]": 0.8,
    "estimators/test_flux.py::test_reference_conforming_and_equilibrated[square8-callable]": 0.9,
    "estimators/test_flux.py::test_reference_conforming_and_equilibrated[square8-perturbed]": 0.9,
    "estimators/test_flux.py::test_reference_conforming_and_equilibrated[square8-nodal-f]": 0.9,
    "estimators/test_flux.py::test_reference_conforming_and_equilibrated[square8-mu1-10]": 0.8,
    "estimators/test_flux.py::test_reference_reproduces_linear_flux[square8]": 0.6,
    # the n = 16 rows of the layer bound (the n = 8 rows of the same checks stay)
    "estimators/test_layers.py::test_layer_bound_guaranteed_and_sharp[16-0.001-f7-2.02-CONNECTED_BAND-0.519]": 1.1,  # noqa: E501
    "estimators/test_layers.py::test_layer_bound_guaranteed_and_sharp[16-1e-06-f5-1.71-CUT_CROSS_POINTS-90.0]": 1.0,  # noqa: E501
    "estimators/test_layers.py::test_layer_bound_guaranteed_and_sharp[16-1e-06-f1-1.33-LAYER_BOUND-20.0]": 0.9,  # noqa: E501
    "estimators/test_layers.py::test_layer_bound_guaranteed_and_sharp[16-0.001-f6-2.04-CONNECTED_BAND-0.207]": 0.8,  # noqa: E501
}


def _slow_key(nodeid: str) -> str | None:
    rel = nodeid.split("tests/", 1)[-1]
    for key in (rel, rel.split("[", 1)[0], rel.split("::", 1)[0]):
        if key in SLOW:
            return key
    return None


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`SLOW`; leave out every slow test unless asked for."""
    for item in items:
        if _slow_key(item.nodeid) is not None:
            item.add_marker(pytest.mark.slow)
    if config.option.markexpr or os.environ.get("FASTMEM_SLOW", "") not in ("", "0"):
        return  # -m given (e.g. -m slow), or FASTMEM_SLOW=1: run what was asked
    keep, slow = [], []
    for item in items:
        (slow if item.get_closest_marker("slow") else keep).append(item)
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = keep


@pytest.hookimpl(hookwrapper=True)  # (old-style: the test extra allows pytest >= 7)
def pytest_sessionstart(session):
    """On a cold kernel cache, compile the solver's kernels first, as ``fastmem run`` does.

    ``fm.warm_up`` compiles the flux patch kernel in a helper process while this one
    compiles the rest (fastmem.cli.warmup), so a fresh install's first ``pytest`` waits
    for the longest of the two instead of their sum; the tests then load the kernels
    from the cache.  Nothing changes on a warm cache.  ``FASTMEM_TEST_WARM_UP=0`` turns
    it off (each test then compiles what it needs, one kernel at a time).  A wrapper that
    compiles after the other session-start hooks: the time pytest reports (the terminal
    reporter starts its clock there) includes the compilation.
    """
    yield
    if os.environ.get("FASTMEM_TEST_WARM_UP", "1").strip().lower() in ("0", "no", "off", "false"):
        return
    from fastmem.cli import warmup

    if warmup.kernels_cached("pipeline") is not False:
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line("fastmem: compiling the solver's kernels first (cold Numba cache) ...")
    # many tests have per-triangle tensions: the helper process compiles their patch
    # kernel after the default one (the warm-up waits for both)
    warmup.start_compile_helper(("patches", "weighted"))
    done = warmup.warm_up("inexact", adaptive=True)
    if reporter is not None:
        reporter.write_line(f"fastmem: {done}")


@pytest.fixture
def seed():
    return 20261121


@pytest.fixture
def rng(seed):
    return np.random.default_rng(seed)


@pytest.fixture(scope="module")
def unstructured_mesh():
    """An unstructured mesh of the unit disk from scikit-fem (independent generator)."""
    return circle_mesh(3)


@pytest.fixture
def job_for(tmp_path):
    """Build the worker-side job of one sweep run, ``factory(**params)``, in a study at tmp_path."""
    from fastmem.sweeps import study as sweeps
    from fastmem.sweeps import task

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

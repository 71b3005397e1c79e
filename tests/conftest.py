import gc
import os

# The suite's time goes mostly to compiling XLA programs, and two settings halve that without
# changing what the tests check (values, which neither changes beyond rounding): LLVM's
# optimisation of the machine code is skipped, and fusions are emitted by XLA's older emitters
# (on CPU its newer fusion emitters took half the backend's compile time: 10.1 -> 4.9 s in
# the joint fit's three-presses test, 142 -> 99 s for three test files on two workers).
# Processes the tests start inherit them. Benchmarks and users keep XLA's defaults; a setting
# given in XLA_FLAGS is kept.
_TEST_XLA_FLAGS = {"xla_backend_optimization_level": "0", "xla_cpu_use_fusion_emitters": "false"}
_flags = os.environ.get("XLA_FLAGS", "")
for _name, _value in _TEST_XLA_FLAGS.items():
    if _name not in _flags:
        _flags = f"{_flags} --{_name}={_value}".strip()
os.environ["XLA_FLAGS"] = _flags

import jax
import jax.numpy as jnp
import numpy as np
import pytest

# diffeit computes in float64; the tests say so explicitly, as a program using diffeit should.
jax.config.update("jax_enable_x64", True)

import diffeit as de


def pytest_configure(config: pytest.Config) -> None:
    """Compiled XLA programs persist between runs in pytest's cache folder (`make clean` removes
    it): most of a quick run's time went to compiling the same small programs again. A folder
    named by JAX_COMPILATION_CACHE_DIR is used instead; with -p no:cacheprovider nothing persists."""
    cache = getattr(config, "cache", None)
    if cache is None or jax.config.jax_compilation_cache_dir:
        return
    jax.config.update("jax_compilation_cache_dir", str(cache.mkdir("jax-compilation-cache")))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# Every compiled XLA program keeps its machine code in memory mappings of its own, and JAX keeps
# every program it compiled. The whole suite compiles enough of them to pass Linux's limit of
# mappings a process (vm.max_map_count, 65,530 by default), and the next compilation then
# crashes inside LLVM (a segmentation fault, first seen in test_float32 in clean clones). Within
# this many mappings of the limit JAX's caches are emptied between tests (the programs of later
# tests trace and compile again, from the persistent cache where they can): a test added at
# most 2,658 in a suite run, and every clearing costs the later tests their shared programs
# (at 30,000 mappings, a fixed count before, the caches were emptied 2 to 3 times a worker).
_MAPPINGS_LEFT = 15_000


def _mapping_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as limit:
            return int(limit.read())
    except (OSError, ValueError):
        return 65_530


_MAPPINGS_BEFORE_CLEARING = _mapping_limit() - _MAPPINGS_LEFT


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    try:
        with open("/proc/self/maps") as maps:
            mappings = sum(1 for _ in maps)
    except OSError:  # not Linux: no such limit to keep under
        return
    if mappings > _MAPPINGS_BEFORE_CLEARING:
        jax.clear_caches()
        gc.collect()


# An L-shaped sheet (metres) whose electrodes sit every 0.5 m from vertex 0: six of them straddle
# corners (the reflex one included) and electrode 0 wraps around vertex 0.
L_SHAPE = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)


@pytest.fixture(scope="session")
def small_disc() -> de.Mesh:
    return de.mesh.disc(16, electrode_width=0.2, h=0.15)


@pytest.fixture(scope="session")
def small_model(small_disc) -> de.ForwardModel:
    return de.ForwardModel(small_disc, de.protocol.adjacent(16), contact_impedance=0.01)


@pytest.fixture
def rough_conductivity(small_disc):
    """A seeded, strongly non-uniform conductivity (S/sq) around 1."""
    return _rough_conductivity(small_disc)


def _rough_conductivity(mesh: de.Mesh) -> jnp.ndarray:
    rng = np.random.default_rng(1234)
    return jnp.asarray(np.exp(rng.normal(0.0, 0.5, mesh.n_elements)))


@pytest.fixture(scope="session", params=["disc", pytest.param("rectangle", marks=pytest.mark.slow), "l_shape"])
def sheet(request, small_disc) -> de.Mesh:
    """Small 16-electrode sheets of each generator, for identities that must hold on any shape."""
    if request.param == "disc":
        return small_disc
    if request.param == "rectangle":
        return de.mesh.rectangle(2.0, 1.0, 16, electrode_width=0.15, h=0.15)
    return de.mesh.polygon(L_SHAPE, 16, electrode_width=0.2, h=0.2, electrode_centres=0.5 * np.arange(16))


@pytest.fixture(scope="session")
def sheet_model(sheet, small_disc, small_model) -> de.ForwardModel:
    if sheet is small_disc:
        return small_model
    return de.ForwardModel(sheet, de.protocol.adjacent(16), contact_impedance=0.01)


@pytest.fixture
def sheet_conductivity(sheet):
    """A seeded, strongly non-uniform conductivity (S/sq) around 1 on `sheet`."""
    return _rough_conductivity(sheet)

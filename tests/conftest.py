"""Test-wide settings: hypothesis profiles and strict JAX numerics.

Profiles (select with HYPOTHESIS_PROFILE=<name>; the "ci" profile is the default when the CI
environment variable is set):

* ``default``: 100 examples per property, fresh random draws each run (finds new cases).
* ``ci``: 60 examples, derandomized, so a CI run is reproducible and its time predictable.

``deadline=None`` in both: the first example of a test pays for XLA compilation, which would
otherwise trip hypothesis' per-example deadline.
"""

from __future__ import annotations

import gc
import os
import shutil
import tempfile
import warnings

# Under pytest-xdist every worker is its own JAX process; on a GPU machine the default
# preallocation (75% of the memory per process) would leave the second worker nothing.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# The eant2 command keeps compiled programs in a cache folder (EANT2_CACHE_DIR, default under
# ~/.cache). The suite runs it in-process and in children: give it one folder for the pytest
# session, so that the suite never writes to the user's cache. The first process that loads
# this file makes it (the xdist controller, before it starts the workers, which inherit it
# through the environment; or the single process of -n 0) and removes it at the end
# (pytest_unconfigure). A test that studies the cache names its own folder.
_MADE_CACHE = "EANT2_CACHE_DIR" not in os.environ
if _MADE_CACHE:
    os.environ["EANT2_CACHE_DIR"] = tempfile.mkdtemp(prefix="eant2-test-cache-")
# Results that one test session computes once for all its workers (tests/shared.py), made
# and removed the same way.
_MADE_SHARED = "EANT2_TEST_SHARED_DIR" not in os.environ
if _MADE_SHARED:
    os.environ["EANT2_TEST_SHARED_DIR"] = tempfile.mkdtemp(prefix="eant2-test-shared-")

# Compiling is most of this suite's time, and XLA:CPU's older LLVM emitters compile the
# engine's programs faster than its fusion emitters (README: the test suite). The suite
# compiles with the older emitters, in-process and in the commands it starts (children
# inherit the environment); a caller's own choice of the flag in XLA_FLAGS is kept.
_EMITTERS = "--xla_cpu_use_fusion_emitters"
if _EMITTERS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_EMITTERS}=false".strip()

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402
from jax.experimental.compilation_cache import compilation_cache  # noqa: E402

# When a property fails, hypothesis' pytest plugin imports libcst (to write a patch of the
# failing example); libcst's import emits a DeprecationWarning, which "warnings are errors"
# turns into an INTERNALERROR that ends the whole session and hides the failure. Import it
# once here, with that warning silenced, so that failures are reported normally.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    try:
        import libcst  # noqa: F401
    except ImportError:
        pass

# EANT2_TEST_COMPILE_PROFILE=DIR: JAX's compile time per test and program (compile_profile.py).
# Loaded only then: without the variable the suite runs without it.
if os.environ.get("EANT2_TEST_COMPILE_PROFILE"):
    pytest_plugins = ["compile_profile"]

# Workers, and the commands the tests start, compile many of the same programs: they share the
# session's cache folder (above) as JAX's persistent compilation cache, so that a program is
# compiled once per session, not once per process: the library's own switch, as the eant2
# command turns it on (EANT2_CACHE_DIR, every program kept). EANT2_TEST_SHARED_CACHE=0: off.
if os.environ.get("EANT2_TEST_SHARED_CACHE", "1") != "0":
    from eant2_jax import enable_compilation_cache

    enable_compilation_cache()

# Implicit rank promotion hides shape bugs (a [H] bias broadcast against [G, H] by accident);
# the library and these tests pass with it as an error, as equinox's tests run.
jax.config.update("jax_numpy_rank_promotion", "raise")

settings.register_profile("default", deadline=None, max_examples=100, print_blob=True)
settings.register_profile(
    "ci", deadline=None, max_examples=60, derandomize=True, print_blob=True, database=None
)
settings.load_profile(
    os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "default")
)


def pytest_unconfigure(config):
    if _MADE_CACHE:
        shutil.rmtree(os.environ["EANT2_CACHE_DIR"], ignore_errors=True)
    if _MADE_SHARED:
        shutil.rmtree(os.environ["EANT2_TEST_SHARED_DIR"], ignore_errors=True)


@pytest.fixture(autouse=True)
def _x64_restored():
    """A test that runs a float64 command in-process (``eant2_jax.enable_x64()``, as the
    condition bench does) would leave 64-bit mode on for every later test of its worker."""
    before = jax.config.jax_enable_x64
    yield
    if jax.config.jax_enable_x64 != before:
        jax.config.update("jax_enable_x64", before)


@pytest.fixture(autouse=True)
def _cache_setting_restored():
    """The eant2 command turns JAX's persistent compilation cache on for its process (as
    an application may); run in-process by a test, it would stay on for every later test
    of this worker, in a folder that test removed. Turn it back as it was, and let the next
    compile decide again from the setting (a test that set the folder and put it back
    itself leaves JAX's cache object behind)."""
    before = jax.config.jax_compilation_cache_dir
    yield
    if jax.config.jax_compilation_cache_dir != before:
        jax.config.update("jax_compilation_cache_dir", before)
    compilation_cache.reset_cache()


def _memory_maps() -> int:
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux: no such limit to watch
        return 0


def _max_map_count() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return 65530  # Linux's default


_MAPS_LIMIT = _max_map_count()


def _free_compiled_programs() -> None:
    from eant2_jax.programs import REGISTRY

    with REGISTRY.lock:
        REGISTRY.ahead.clear()
        REGISTRY.ran.clear()
    jax.clear_caches()
    gc.collect()


@pytest.fixture(autouse=True, scope="module")
def _compiled_programs_bounded():
    """Free the worker's compiled programs before it runs out of memory mappings.

    Every program XLA compiles for the CPU stays mapped while JAX's caches hold it (about a
    thousand mappings for one engine program). A worker that runs several hundred tests
    reached the kernel's limit (vm.max_map_count, 65,530 by default); XLA's compiler then
    failed to map the next program ("LLVM compilation error: Cannot allocate memory") and
    the worker died with SIGSEGV or SIGABRT, in CI inside test_pruning. After a test file,
    past half the limit, empty JAX's caches and the programs compiled ahead: later files
    compile again (within a file, tests may count on programs its fixtures compiled).
    docs/reliability.md: Long-lived processes."""
    yield
    if _memory_maps() > _MAPS_LIMIT // 2:
        _free_compiled_programs()


@pytest.fixture(autouse=True)
def _compiled_programs_bounded_within_a_file():
    """The same, within a file whose programs alone fill most of the limit."""
    yield
    if _memory_maps() > _MAPS_LIMIT * 4 // 5:
        _free_compiled_programs()

import atexit
import os
import pathlib
import shutil
import sys
import tempfile

# The suite is dominated by compilation: one compilation cache per test run serves every
# worker and subprocess (the CLI tests), and XLA compiles as the command line has it
# (`jaxtissue.cache.use_fast_compilation`; XLA's optimisation level stays at its
# default: the tests check the programs users run). The process that makes the folder
# (under xdist, the controller) removes it at exit.
# The command's runs in the tests share programs with the library's through that cache:
# they save no executables of their own (a program named after its key would be compiled
# again in every process), except where tests/test_cache.py checks them.
os.environ.setdefault("JAXTISSUE_NO_SAVED_PROGRAMS", "1")
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxtissue-tests-cache-")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.2"  # the command's setting (`cache.enable_compilation_cache`)
    atexit.register(shutil.rmtree, os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)

import jax  # noqa: E402
from jaxtyping import install_import_hook  # noqa: E402

jax.config.update("jax_enable_x64", True)

# runtime shape checks of the annotated arrays (`jaxtissue._custom_types`), as diffrax's
# tests do: these modules are imported through jaxtyping's hook with beartype
install_import_hook(["jaxtissue.operators", "jaxtissue.state", "jaxtissue.growth_jacobian", "jaxtissue.numerics._banded"],
                    "beartype.beartype")

# after the hook, since it imports jaxtissue
from jaxtissue.cache import collect_less, use_fast_compilation  # noqa: E402

use_fast_compilation()  # in XLA_FLAGS, which the CLI tests' subprocesses inherit
collect_less()  # as the command line: tracing makes many short-lived objects

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the independent SciPy reference, shared helpers

# The files that take longest start first: two workers (`--dist loadfile`) then finish
# together instead of one running a long file alone at the end.
LONGEST_FIRST = ("test_posterior_study.py", "test_posterior.py", "test_coupling.py", "test_solver.py", "test_beam.py",
                 "test_gradients.py", "test_growth.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order

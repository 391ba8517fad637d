import os
import pathlib
import sys
import tempfile

# The suite is dominated by compilation: one compilation cache per test run serves every
# worker and subprocess (the CLI tests). (XLA's backend stays at its default
# optimisation level: the tests check the programs users run.)
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxtissue-tests-cache-")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"

import jax  # noqa: E402
from jaxtyping import install_import_hook  # noqa: E402

jax.config.update("jax_enable_x64", True)

# runtime shape checks of the annotated arrays (`jaxtissue._custom_types`), as diffrax's
# tests do: these modules are imported through jaxtyping's hook with beartype
install_import_hook(["jaxtissue.operators", "jaxtissue.state", "jaxtissue.growth_jacobian", "jaxtissue.numerics._banded"],
                    "beartype.beartype")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the independent SciPy reference, shared helpers

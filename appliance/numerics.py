"""Settings shared by the compiled (numba) kernels, and scipy's BLAS and LAPACK for them without
the rest of scipy.linalg.

Numba calls BLAS and LAPACK through scipy's Cython modules scipy.linalg.cython_blas and
scipy.linalg.cython_lapack: it imports the first when its CPU target loads (to learn whether a BLAS
is there) and the second when a kernel first calls LAPACK at run time (np.linalg.solve in
:func:`appliance.estimator.parallax.linearised_fit`).  Imported by name, each brings the whole
package scipy.linalg with it (0.2-0.25 s, scipy's array-API layer and numpy.f2py among it), which
nothing on an estimate's path uses.  :func:`load_scipy_cython_linalg` loads the two extension
modules from their files under their own names instead (a few ms); numba's imports then find them
loaded and make their own checks (the BLAS integer width) as before.  The kernels call the very
same LAPACK functions, so their results are the same bit for bit.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path

#: Fast-math without the "no NaN, no inf" assumptions: the kernels test for NaN and use inf.
FAST_FINITE = {"nsz", "arcp", "contract", "afn", "reassoc"}

#: scipy's Cython BLAS and LAPACK modules, in the order they are loaded.
CYTHON_LINALG = ("cython_blas", "cython_lapack")


def _extension_file(folder: Path, name: str) -> Path | None:
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        f = folder / f"{name}{suffix}"
        if f.is_file():
            return f
    return None


def load_scipy_cython_linalg() -> list[str]:
    """Load scipy.linalg.cython_blas and scipy.linalg.cython_lapack from their files, without
    running scipy.linalg's ``__init__``; returns the names loaded.

    Does nothing when scipy.linalg is loaded already (its modules come with it), and leaves a module
    whose file is missing, or that fails to load, to numba's own import (which then behaves as it
    always has: an ImportError is "no BLAS").  scipy.linalg imported later is the whole package as
    usual and finds these two modules loaded."""
    if "scipy.linalg" in sys.modules:
        return []
    try:
        import scipy  # the package itself: its BLAS and LAPACK libraries, no subpackage
    except ImportError:
        return []
    spec = scipy.__spec__
    if spec is None or not spec.submodule_search_locations:
        return []
    loaded = []
    for name in CYTHON_LINALG:
        full = f"scipy.linalg.{name}"
        if full in sys.modules:
            continue
        for root in spec.submodule_search_locations:
            f = _extension_file(Path(root) / "linalg", name)
            if f is None:
                continue
            mod_spec = importlib.util.spec_from_file_location(full, f)
            if mod_spec is None or mod_spec.loader is None:
                break
            module = importlib.util.module_from_spec(mod_spec)
            try:
                mod_spec.loader.exec_module(module)
            except Exception:  # numba's own import then reports it, or finds no BLAS
                break
            sys.modules[full] = module
            loaded.append(full)
            break
    return loaded


load_scipy_cython_linalg()

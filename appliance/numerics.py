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

Loading a kernel from numba's cache needs none of numba's compiler: the cache holds the kernel's
machine code, which is linked as it is.  Numba nevertheless loads all of its compiler's typing and
lowering registries before it looks in the cache (0.15-0.3 s: numba.np.arraymath, npyimpl, the
typed containers and more).  :func:`load_cached_kernels_without_compiler` makes a cache load start
the memory-management runtime the kernels call (all that those registries' loading does for a
load) and no more; a kernel that is not in the cache is compiled exactly as before (numba's
compiler loads the registries itself).  It applies to the numba versions in
:data:`CACHE_LOAD_TESTED` only; under another, numba loads its cache its own way.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import sys
import typing
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

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
    usual, with these two modules loaded as its own (:class:`_AttachToPackage`)."""
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
    if loaded:
        sys.meta_path.insert(0, _AttachToPackage())
    return loaded


class _AttachToPackage(importlib.abc.MetaPathFinder):
    """When scipy.linalg itself is imported after :func:`load_scipy_cython_linalg`, the modules that
    loaded become its attributes (``scipy.linalg.cython_lapack``), as importing them by name makes
    them; the package is found and run as usual.  Used once, then out of the way."""

    def __init__(self) -> None:
        self.used = False

    def find_spec(self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
                  ) -> importlib.machinery.ModuleSpec | None:
        if self.used or fullname != "scipy.linalg":
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or spec.loader is None:
            return None
        self.used = True
        loader = spec.loader
        run = loader.exec_module

        def exec_module(module: ModuleType) -> None:
            if self in sys.meta_path:
                sys.meta_path.remove(self)
            run(module)
            for name in CYTHON_LINALG:
                child = sys.modules.get(f"scipy.linalg.{name}")
                if child is not None and not hasattr(module, name):
                    setattr(module, name, child)

        loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


#: The numba versions (major, minor) whose cache loading :func:`load_cached_kernels_without_compiler`
#: was checked against: numba.core.caching.Cache.load_overload is ``target_context.refresh()`` then
#: ``self._load_overload(sig, target_context)``, and the refresh's only part a load needs is
#: ``rtsys.initialize(target_context)``.
CACHE_LOAD_TESTED = frozenset({(0, 68)})


def load_cached_kernels_without_compiler() -> bool:
    """Make numba load cached kernels without first loading its compiler's registries (see the
    module's notes); returns whether it is in place (False under an untested numba)."""
    import numba
    from numba.core import caching
    from numba.core.runtime import nrt

    version = tuple(int(v) for v in numba.__version__.split(".")[:2])
    if version not in CACHE_LOAD_TESTED:
        return False
    real = caching.Cache.load_overload
    if getattr(real, "without_compiler", False):
        return True

    def load_overload(self: caching.Cache, sig: object, target_context: object) -> object:
        nrt.rtsys.initialize(target_context)
        with self._guard_against_spurious_io_errors():
            return self._load_overload(sig, target_context)
        return None  # the guard swallowed an error (as numba's own load does)

    load_overload.without_compiler = True  # type: ignore[attr-defined]
    caching.Cache.load_overload = load_overload  # type: ignore[method-assign]
    return True


load_scipy_cython_linalg()
load_cached_kernels_without_compiler()


def load_cached_kernels(prefix: str = "appliance.", parallel: bool = False) -> int:
    """Load, without running them, the machine code numba's cache holds for the kernels of the
    loaded modules under ``prefix``: each signature of a kernel's cache index that is fresh (same
    byte code, same machine).  The calls that follow start at once.  Nothing is compiled.
    Parallel kernels only with ``parallel``: loading one loads numba's threading layer, and GNU
    OpenMP's then ends any process forked afterwards.  Returns the count loaded; 0 under a numba
    outside :data:`CACHE_LOAD_TESTED`."""
    import numba
    from numba.core.registry import CPUDispatcher

    version = tuple(int(v) for v in numba.__version__.split(".")[:2])
    if version not in CACHE_LOAD_TESTED:
        return 0
    loaded = 0
    for name, module in list(sys.modules.items()):
        if not name.startswith(prefix) or module is None:
            continue
        for kernel in list(vars(module).values()):
            if not isinstance(kernel, CPUDispatcher) or (kernel.targetoptions.get("parallel") and not parallel):
                continue
            cache = getattr(kernel, "_cache", None)
            if cache is None:
                continue
            codegen = typing.cast(typing.Any, kernel.targetctx).codegen()  # the CPU target's context
            for key in cache._cache_file._load_index():
                sig = key[0]
                if cache._index_key(sig, codegen) == key and sig not in kernel.overloads:
                    kernel.compile(sig)
                    loaded += 1
    return loaded

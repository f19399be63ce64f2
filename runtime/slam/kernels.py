"""The compiled-kernel decorator of the SLAM package (numba, on-disk cache kept fresh)."""

from __future__ import annotations

import hashlib
import inspect
from pathlib import Path

import numba

# Source files each kernel made by compiled_kernel is built from (its own and its callees').
_KERNEL_SOURCES: dict = {}


def compiled_kernel(*callees, fastmath: bool | set = False):
    """Decorator: ``numba.njit(cache=True, error_model="numpy")`` for a kernel of this package,
    which may call the compiled functions ``callees`` of other modules.

    numba's on-disk cache is invalidated only when the kernel's own file changes, yet a kernel's
    machine code contains its callees: after an edit to, say, a lens model in
    kinematics/camera.py, the cached measurement kernel would go on projecting with the old one.
    So the cache's freshness stamp is extended with the content of every file the kernel is built
    from (its own, its callees', and theirs, transitively). The stamp is numba's internal API; if
    this numba has none, kernels with callees elsewhere are compiled without an on-disk cache
    (correct, only slower to start). ``error_model="numpy"``: a division by zero gives inf/NaN
    instead of raising, as in numpy. ``fastmath``: let LLVM reassociate sums (vectorised
    reductions) in kernels whose results do not depend on the order of a sum's terms; a set
    of numba's flags (e.g. ``{"contract", "reassoc"}``) keeps NaN and inf semantics.
    """
    def decorate(fn):
        files = {inspect.getsourcefile(fn)}
        for c in callees:
            files |= _KERNEL_SOURCES.get(c) or {inspect.getsourcefile(c.py_func)}
        kernel = numba.njit(cache=True, error_model="numpy", fastmath=fastmath)(fn)
        if len(files) > 1:
            cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
            if hasattr(cache_file, "_source_stamp"):
                digest = hashlib.sha256(b"".join(Path(f).read_bytes() for f in sorted(files))).hexdigest()
                cache_file._source_stamp = (cache_file._source_stamp, digest)
            else:
                kernel = numba.njit(error_model="numpy", fastmath=fastmath)(fn)
        _KERNEL_SOURCES[kernel] = frozenset(files)
        return kernel
    return decorate

"""A minimal ctypes binding of Intel MKL PARDISO for symmetric positive-definite systems.

Why not ``pypardiso``: its public API redoes the symbolic analysis on every factorisation;
Gauss-Newton keeps one sparsity pattern for many factorisations, so we keep the PARDISO
handle and run phase 11 (analysis) once, then phase 22 (numeric) and 33 (solve) per step.
The MKL runtime comes from the ``mkl`` wheel (x86-64 only); where it is missing jaxslam uses
CHOLMOD or SuperLU instead.

Threads: MKL's default (all cores). Set ``MKL_NUM_THREADS`` before the process starts to
change it: a multithreaded factorisation degrades badly when another process holds a core
(an OpenMP barrier waits for a descheduled thread). Changing MKL's thread count while
PARDISO handles exist crashed once here, so jaxslam never does it at run time.

Matrix input: the *upper* triangle in CSR with 0-based indices, which is exactly jaxslam's
lower-triangle CSC arrays read row-wise (``H`` is symmetric).
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import site
import sys
from ctypes.util import find_library

import numpy as np

_LIB: ctypes.CDLL | None = None
_I32P = ctypes.POINTER(ctypes.c_int32)
_F64P = ctypes.POINTER(ctypes.c_double)
_I64P = ctypes.POINTER(ctypes.c_int64)


def _load() -> ctypes.CDLL | None:
    global _LIB
    if _LIB is not None:
        return _LIB
    candidates = [p for p in (os.environ.get("JAXSLAM_MKL_RT"), find_library("mkl_rt")) if p]
    for base in (sys.prefix, site.getuserbase()):
        candidates += sorted(glob.glob(f"{base}/lib/libmkl_rt.so*"), key=len)
    for path in candidates:
        if not path:
            continue
        try:
            lib = ctypes.CDLL(path)
            lib.pardiso.restype = None
            lib.pardiso.argtypes = [
                _I64P,
                _I32P,
                _I32P,
                _I32P,
                _I32P,
                _I32P,
                _F64P,
                _I32P,
                _I32P,
                _I32P,
                _I32P,
                _I32P,
                _I32P,
                _F64P,
                _F64P,
                _I32P,
            ]
            _LIB = lib
            return lib
        except (OSError, AttributeError):
            continue
    return None


def pardiso_available() -> bool:
    return _load() is not None


class PardisoNotPositiveDefinite(RuntimeError):
    pass


class Pardiso:
    """PARDISO for one SPD sparsity pattern: ``analyze`` once, ``factorize``/``solve`` many."""

    MTYPE_SPD = 2

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int):
        lib = _load()
        if lib is None:
            raise ImportError("MKL runtime (libmkl_rt) not found: pip install mkl")
        self._lib = lib
        self.n = n
        self.indptr = np.ascontiguousarray(indptr, dtype=np.int32)
        self.indices = np.ascontiguousarray(indices, dtype=np.int32)
        self.pt = np.zeros(64, dtype=np.int64)
        self.iparm = np.zeros(64, dtype=np.int32)
        self.iparm[0] = 1  # we set iparm ourselves
        self.iparm[1] = 2  # METIS nested-dissection ordering
        self.iparm[9] = 8  # pivot perturbation 1e-8 (unused for SPD)
        self.iparm[17] = -1  # report nnz(L)
        self.iparm[18] = 0
        self.iparm[26] = 0  # no matrix checker (we build the pattern ourselves)
        self.iparm[34] = 1  # 0-based indices
        self._analyzed = False
        self._data: np.ndarray | None = None

    def _call(self, phase: int, data: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        err = ctypes.c_int32(0)
        one = ctypes.c_int32(1)
        rhs = np.zeros(self.n) if b is None else np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(rhs)
        perm = np.zeros(1, dtype=np.int32)
        self._lib.pardiso(
            self.pt.ctypes.data_as(_I64P),
            ctypes.byref(one),
            ctypes.byref(one),
            ctypes.byref(ctypes.c_int32(self.MTYPE_SPD)),
            ctypes.byref(ctypes.c_int32(phase)),
            ctypes.byref(ctypes.c_int32(self.n)),
            data.ctypes.data_as(_F64P),
            self.indptr.ctypes.data_as(_I32P),
            self.indices.ctypes.data_as(_I32P),
            perm.ctypes.data_as(_I32P),
            ctypes.byref(one),
            self.iparm.ctypes.data_as(_I32P),
            ctypes.byref(ctypes.c_int32(0)),
            rhs.ctypes.data_as(_F64P),
            x.ctypes.data_as(_F64P),
            ctypes.byref(err),
        )
        if err.value == -4:
            raise PardisoNotPositiveDefinite("zero or negative pivot")
        if err.value != 0:
            raise RuntimeError(f"PARDISO phase {phase} failed with error {err.value}")
        return x

    def factorize(self, data: np.ndarray) -> None:
        data = np.ascontiguousarray(data, dtype=np.float64)
        if not self._analyzed:
            self._call(11, data)
            self._analyzed = True
        self._call(22, data)
        self._data = data  # PARDISO keeps a pointer to the values until the solve

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._data is None:
            raise RuntimeError("factorize before solve")
        return self._call(33, self._data, b)

    @property
    def nnz_factor(self) -> int:
        return int(self.iparm[17])

    def release(self) -> None:
        if self._analyzed:
            with contextlib.suppress(RuntimeError):
                self._call(-1, np.zeros(max(len(self.indices), 1)))
            self._analyzed = False

    def __del__(self) -> None:  # pragma: no cover - best effort
        with contextlib.suppress(Exception):
            self.release()

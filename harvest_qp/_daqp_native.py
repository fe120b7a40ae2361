"""DAQP's C API called directly (from Python through ctypes, from numba-compiled code), for the
QP step's hot path.

``daqp.Model`` (the Cython class of the ``daqp`` wheel) costs ~8 us of Python and Cython glue per
level and step inside the episode (``update`` converts six arrays and takes six memoryviews;
``solve`` builds a dict and copies two arrays). :class:`NativeModel` keeps its own DAQP workspace
and makes **the same C calls with the same data** as ``daqp.Model`` (``setup_daqp_main`` on a
workspace with the default settings, ``daqp_update_ldp`` with the same update mask and problem
pointers, ``daqp_solve`` into a result struct), so its answers are bit for bit those of
``daqp.Model``; :func:`update_solve` and :func:`update_solve_check_clip_rate` do a level's update
and solve (and, on the last level, the check, the clip and the acceleration) in one compiled call.

Safety (the C structs are laid out by hand here, so a mismatch would write past memory):

* Only for the exact ``daqp`` version whose headers this was written against
  (:data:`VALIDATED_VERSION`, from the PyPI sdist's ``csrc/include/types.h`` and ``api.h``), on a
  64-bit little-endian build with 8-byte ``double``; the offsets below were confirmed with
  ``sizeof``/``offsetof`` from a C program compiled against those headers.
* The workspace lives in a zeroed buffer of 4096 bytes (``sizeof(DAQPWorkspace)`` is 328): a
  wrong size cannot make DAQP write past it. The problem and result structs are numpy buffers of
  their exact size, written only here.
* Before first use a self-test (:func:`available`) checks the layout against what DAQP itself
  wrote (``n``, ``m``, ``ms``, the problem pointer, the settings equal to
  ``daqp_default_settings``'s, DAQP's copy of ``sense``) and solves fixed QPs (bounds, equality
  slots, inequality rows, an infeasible one, an update that keeps the rows) through ``daqp.Model``
  and through this module's Python and compiled paths: every answer, exit flag and cost must be
  the same bits. Each :meth:`NativeModel.setup` repeats the layout checks.
* Anything else (another version, missing symbols, a failed check) disables the module: the
  backend then uses ``daqp.Model`` (:func:`new_model`), never crashing. ``HARVEST_QP_NATIVE_DAQP=0``
  in the environment, or :func:`set_enabled` (tests, benchmarks), disables it too.
"""

from __future__ import annotations

import ctypes
import os
import sys
import weakref
from importlib import metadata

import numpy as np
from numba import njit, types

from harvest_qp.exceptions import HarvestQPError
from harvest_qp.qp_kernels import (
    assemble_load_1,
    assemble_load_2,
    assemble_load_3,
    check_clip_rate,
    handover_1_1,
    handover_1_2,
    handover_1_3,
    handover_1_4,
    handover_2_1,
    handover_2_2,
    handover_2_3,
    handover_2_4,
    handover_3_1,
    handover_3_2,
    handover_3_3,
    handover_3_4,
)

#: The one ``daqp`` version whose C struct layouts this module was written for.
VALIDATED_VERSION = "0.11.0"

# Layouts of daqp 0.11.0 (LP64), confirmed with sizeof/offsetof against the sdist's headers.
_WORK_BYTES = 4096  # the workspace buffer; sizeof(DAQPWorkspace) == 328
_WORK_N_BYTE, _WORK_M_BYTE, _WORK_MS_BYTE = 8, 12, 16  # int n, m, ms
_WORK_SENSE_WORD = 8  # int *sense at byte 64
_WORK_SETTINGS_WORD = 28  # DAQPSettings *settings at byte 224
_SETTINGS_BYTES = 136  # sizeof(DAQPSettings)
_PROBLEM_WORDS = 10  # sizeof(DAQPProblem) == 80: n, m | ms | H, f, A, bupper, blower, sense, break_points | nh, type
_RESULT_WORDS = 8  # sizeof(DAQPResult) == 64: x, lam, fval, soft_slack, exitflag | iter, nodes, times
_UPDATE_RINV, _UPDATE_M, _UPDATE_V, _UPDATE_D, _UPDATE_SENSE = 1, 2, 4, 8, 16
#: A shape or stride the compiled calls refuse (nothing was passed to DAQP).
LAYOUT_REFUSED = -1000

_SYMBOLS = ("setup_daqp_main", "daqp_update_ldp", "daqp_solve", "allocate_daqp_settings",
            "free_daqp_workspace", "free_daqp_ldp", "daqp_default_settings")
_PREFIX = "harvest_qp_"  # the names numba links against (never a bare DAQP name)

_update_ldp_c = types.ExternalFunction(
    _PREFIX + "daqp_update_ldp", types.int32(types.int32, types.voidptr, types.voidptr)
)
_solve_c = types.ExternalFunction(_PREFIX + "daqp_solve", types.void(types.voidptr, types.voidptr))


_FLOAT64 = np.dtype(np.float64)
_INTC = np.dtype(np.intc)


class NativeLayoutError(HarvestQPError, RuntimeError):
    """DAQP's workspace does not look as this module expects (the native path is then disabled)."""


class _State:
    checked = False
    ok = False
    reason = "not checked yet"
    lib = None
    enabled = os.environ.get("HARVEST_QP_NATIVE_DAQP", "1") != "0"


def set_enabled(enabled: bool) -> None:
    """Use (True, the default) or never use (False) the native path for models made from now on."""
    _State.enabled = bool(enabled)


def disable(reason: str) -> None:
    """Stop using the native path for models made from now on (a check failed at run time)."""
    _State.checked, _State.ok, _State.reason = True, False, reason


def disabled_reason() -> str | None:
    """Why the native path is not used (None when it is)."""
    if not _State.enabled:
        return "disabled (set_enabled(False) or HARVEST_QP_NATIVE_DAQP=0)"
    available()
    return None if _State.ok else _State.reason


def _load():
    """The ctypes library with its argument types, or raises with the reason."""
    if sys.maxsize != 2**63 - 1 or sys.byteorder != "little" or ctypes.sizeof(ctypes.c_int) != 4:
        raise NativeLayoutError("not a 64-bit little-endian build with 4-byte int")
    import daqp

    version = metadata.version("daqp")
    if version != VALIDATED_VERSION or getattr(daqp, "__version__", version) != VALIDATED_VERSION:
        raise NativeLayoutError(f"daqp {version} installed, layouts validated for {VALIDATED_VERSION} only")
    lib = ctypes.CDLL(daqp.__file__)
    vp, ci = ctypes.c_void_p, ctypes.c_int
    for name in _SYMBOLS:
        if not hasattr(lib, name):
            raise NativeLayoutError(f"daqp's module does not export {name}")
    lib.setup_daqp_main.argtypes, lib.setup_daqp_main.restype = [vp, vp, vp, ci], ci
    lib.daqp_update_ldp.argtypes, lib.daqp_update_ldp.restype = [ci, vp, vp], ci
    lib.daqp_solve.argtypes, lib.daqp_solve.restype = [vp, vp], None
    for name in ("allocate_daqp_settings", "free_daqp_workspace", "free_daqp_ldp", "daqp_default_settings"):
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = [vp], None
    import llvmlite.binding as llvm

    for name in ("daqp_update_ldp", "daqp_solve"):
        llvm.add_symbol(_PREFIX + name, ctypes.cast(getattr(lib, name), vp).value)
    return lib


def available() -> bool:
    """Whether :class:`NativeModel` may be used: loaded, version checked and self-tested (once)."""
    if not _State.enabled:
        return False
    if not _State.checked:
        _State.checked = True
        try:
            _State.lib = _load()
            _self_test()
            _State.ok, _State.reason = True, ""
        except Exception as err:  # any failure: the Python daqp path is used instead
            _State.ok, _State.reason = False, f"{type(err).__name__}: {err}"
    return _State.ok


def new_model(daqp_module):
    """A :class:`NativeModel` when :func:`available`, else ``daqp_module.Model()``."""
    if available():
        return NativeModel()
    return daqp_module.Model()


def _free(work, lib) -> None:
    # As daqp.Model.__dealloc__ (the buffer itself is numpy's).
    address = work.ctypes.data
    lib.free_daqp_workspace(address)
    lib.free_daqp_ldp(address)


def _default_settings_bytes(lib) -> bytes:
    buf = np.zeros(128, dtype=np.int64)  # 1024 bytes against sizeof(DAQPSettings) == 136
    lib.daqp_default_settings(buf.ctypes.data)
    return buf.view(np.uint8)[:_SETTINGS_BYTES].tobytes()


class NativeModel:
    """``daqp.Model``'s ``setup`` / ``update`` / ``solve`` (the same C calls on the same data) on a
    workspace this object owns; freed when the object goes."""

    def __init__(self) -> None:
        lib = _State.lib
        if lib is None:
            raise NativeLayoutError("the native DAQP path is not available")
        self._lib = lib
        self._work = np.zeros(_WORK_BYTES // 8, dtype=np.int64)  # calloc'ed in daqp.Model
        self._problem = np.zeros(_PROBLEM_WORDS, dtype=np.int64)
        self._result = np.zeros(_RESULT_WORDS, dtype=np.int64)
        lib.allocate_daqp_settings(self._work.ctypes.data)
        self._finalizer = weakref.finalize(self, _free, self._work, lib)
        # Not at interpreter exit: a daemon thread may still be solving on this workspace then
        # (an audit saw SIGSEGV at exit in 8 of 28 runs); daqp.Model's __dealloc__ never runs
        # for live objects at exit either, and the OS takes the memory back.
        self._finalizer.atexit = False
        self._has_model = False
        self._has_solved = False
        self._keep: dict[str, np.ndarray] = {}
        #: ``(work, problem, result, x, lam)`` as the compiled calls take them, set by ``setup``
        #: (the solver's fused cascade passes them without five attribute reads per level).
        self._call_args: tuple[np.ndarray, ...] | None = None

    def __reduce_ex__(self, protocol):
        # As daqp.Model: no copy or pickle (a copy would share, and free twice, DAQP's memory).
        raise TypeError("no default __reduce__ due to non-trivial __cinit__")

    # --- the problem struct (ints packed two to a word, little endian)
    def _ints(self) -> np.ndarray:
        return self._problem.view(np.int32)

    def setup(self, H, f, A, bupper, blower=None, sense=None):
        """As ``daqp.Model.setup`` without break points, warm starts or AVI: ``(exitflag, 0.0)``."""
        A = np.ascontiguousarray(A)
        mA, n = np.shape(A)
        m = np.size(bupper)
        ms = m - mA
        if blower is None:
            blower = np.full(m, -1e30)
        if sense is None:
            sense = np.zeros(m, dtype=np.intc)
        keep = self._keep
        keep["H"] = np.ascontiguousarray(np.asarray(H), dtype=np.double)
        keep["f"] = np.ascontiguousarray(np.asarray(f), dtype=np.double)
        keep["A"] = np.ascontiguousarray(np.asarray(A), dtype=np.double)
        keep["bupper"] = np.ascontiguousarray(np.asarray(bupper), dtype=np.double)
        keep["blower"] = np.ascontiguousarray(np.asarray(blower), dtype=np.double)
        keep["sense"] = np.ascontiguousarray(np.asarray(sense), dtype=np.intc)
        if keep["H"].shape != (n, n) or keep["f"].shape != (n,) or keep["bupper"].shape != (m,) \
                or keep["blower"].shape != (m,) or keep["sense"].shape != (m,) or mA > m:
            raise NativeLayoutError(f"setup shapes do not agree (n {n}, m {m}, rows {mA})")
        self._x = np.zeros(n, dtype=np.double)
        self._lam = np.zeros(m, dtype=np.double)
        self._call_args = (self._work, self._problem, self._result, self._x, self._lam)
        lib, address = self._lib, self._work.ctypes.data
        if self._has_model:  # as daqp.Model: free the old internals (settings too), then fresh settings
            lib.free_daqp_workspace(address)
            lib.free_daqp_ldp(address)
            lib.allocate_daqp_settings(address)
        ints, problem = self._ints(), self._problem
        problem[:] = 0
        ints[0], ints[1], ints[2] = n, m, ms
        problem[2] = keep["H"].ctypes.data
        problem[3] = keep["f"].ctypes.data
        problem[4] = keep["A"].ctypes.data if mA else 0
        problem[5] = keep["bupper"].ctypes.data if m else 0
        problem[6] = keep["blower"].ctypes.data if m else 0
        problem[7] = keep["sense"].ctypes.data if m else 0
        setup_time = ctypes.c_double(0.0)
        flag = lib.setup_daqp_main(problem.ctypes.data, address, ctypes.addressof(setup_time), 0)
        if flag < 0:
            lib.allocate_daqp_settings(address)  # setup_daqp_main freed them on failure
            self._has_model = False
            problem[:] = 0  # n = m = 0: the compiled calls refuse every array for this model
            self._call_args = None
            return flag, setup_time.value
        self._check_layout(n, m, ms)
        self._has_model = True
        self._has_solved = False
        return flag, setup_time.value

    def _check_layout(self, n: int, m: int, ms: int) -> None:
        """What DAQP wrote where this module expects it (else NativeLayoutError)."""
        work = self._work
        ints = work.view(np.int32)
        if (int(work[0]) != self._problem.ctypes.data or int(ints[_WORK_N_BYTE // 4]) != n
                or int(ints[_WORK_M_BYTE // 4]) != m or int(ints[_WORK_MS_BYTE // 4]) != ms):
            raise NativeLayoutError("DAQPWorkspace qp/n/m/ms not where daqp 0.11.0 keeps them")
        settings = int(work[_WORK_SETTINGS_WORD])
        if settings == 0 or ctypes.string_at(settings, _SETTINGS_BYTES) != _default_settings_bytes(self._lib):
            raise NativeLayoutError("DAQPWorkspace settings not where daqp 0.11.0 keeps them")
        if int(work[_WORK_SENSE_WORD]) == 0:
            raise NativeLayoutError("DAQPWorkspace sense not where daqp 0.11.0 keeps it")

    def update(self, H=None, f=None, A=None, bupper=None, blower=None, sense=None):
        """As ``daqp.Model.update`` (without break points): the exit flag of ``daqp_update_ldp``."""
        if not self._has_model:
            raise RuntimeError("Model has not been set up. Call setup() first.")
        ints, problem, keep = self._ints(), self._problem, self._keep
        n, m, ms = int(ints[0]), int(ints[1]), int(ints[2])
        mA = m - ms
        mask = 0
        if H is not None:
            arr = np.ascontiguousarray(H, dtype=np.double)
            if arr.shape == (n, n):
                keep["H"], problem[2], mask = arr, arr.ctypes.data, mask | _UPDATE_RINV
        if A is not None:
            arr = np.ascontiguousarray(A, dtype=np.double)
            if arr.shape == (mA, n):
                keep["A"], problem[4], mask = arr, arr.ctypes.data, mask | _UPDATE_M
        if f is not None:
            arr = np.ascontiguousarray(f, dtype=np.double)
            if arr.shape == (n,):
                keep["f"], problem[3], mask = arr, arr.ctypes.data, mask | _UPDATE_V
        if bupper is not None:
            arr = np.ascontiguousarray(bupper, dtype=np.double)
            if arr.shape == (m,):
                keep["bupper"], problem[5], mask = arr, arr.ctypes.data, mask | _UPDATE_D
        if blower is not None:
            arr = np.ascontiguousarray(blower, dtype=np.double)
            if arr.shape == (m,):
                keep["blower"], problem[6], mask = arr, arr.ctypes.data, mask | _UPDATE_D
        if sense is not None:
            arr = np.ascontiguousarray(sense, dtype=np.intc)
            if arr.shape == (m,):
                keep["sense"], problem[7], mask = arr, arr.ctypes.data, mask | _UPDATE_SENSE
        if sense is None and mask & (_UPDATE_RINV | _UPDATE_M):
            # daqp.Model: DAQP's own sense after a solve (its warm start), else the one set up
            if self._has_solved:
                problem[7] = self._work[_WORK_SENSE_WORD]
            else:
                problem[7] = keep["sense"].ctypes.data if m else 0
            mask |= _UPDATE_SENSE
        return self._lib.daqp_update_ldp(mask, self._work.ctypes.data, problem.ctypes.data)

    def solve(self):
        """As ``daqp.Model.solve``: ``(x, fval, exitflag, info)``, ``x`` a fresh array."""
        if not self._has_model:
            raise RuntimeError("Model has not been set up. Call setup() first.")
        result = self._result
        result[:] = 0
        result[0] = self._x.ctypes.data
        result[1] = self._lam.ctypes.data if self._lam.shape[0] else 0
        self._lib.daqp_solve(result.ctypes.data, self._work.ctypes.data)
        self._has_solved = True
        ints = result.view(np.int32)
        info = {
            "solve_time": float(result.view(np.float64)[6]),
            "setup_time": 0.0,
            "iterations": int(ints[9]),
            "nodes": int(ints[10]),
            "lam": self._lam.copy(),
        }
        return self._x.copy(), float(result.view(np.float64)[2]), int(ints[8]), info


    def update_solve(self, H, f, A, bupper, blower, sense):
        """``update(H, f, A, bupper, blower, sense)`` then ``solve()``, in one compiled call:
        ``(x, exitflag)`` (the same bits; the Python methods when a shape does not fit)."""
        if not self._has_model:  # DAQP's workspace is freed after a failed setup
            raise RuntimeError("Model has not been set up. Call setup() first.")
        if not (type(H) is np.ndarray and type(f) is np.ndarray and type(A) is np.ndarray
                and type(bupper) is np.ndarray and type(blower) is np.ndarray and type(sense) is np.ndarray
                and H.dtype == _FLOAT64 and f.dtype == _FLOAT64 and A.dtype == _FLOAT64
                and bupper.dtype == _FLOAT64 and blower.dtype == _FLOAT64 and sense.dtype == _INTC):
            # Another dtype (integers, big-endian floats): the compiled call would hand DAQP the
            # raw bytes; the Python methods convert, as daqp.Model does.
            self.update(H, f, A, bupper, blower, sense)
            x, _, flag, _ = self.solve()
            return x, flag
        keep = self._keep
        keep["H"], keep["f"], keep["A"], keep["bupper"], keep["blower"], keep["sense"] = H, f, A, bupper, blower, sense
        x, flag = update_solve(self._work, self._problem, self._result, self._x, self._lam, H, f, A, bupper, blower,
                               sense)
        if flag == LAYOUT_REFUSED:  # not the arrays set up for: daqp.Model's own handling
            self.update(H, f, A, bupper, blower, sense)
            x, _, flag, _ = self.solve()
            return x, flag
        self._has_solved = True
        return x, flag


# ----------------------------------------------------------------- compiled paths


@njit(cache=True)
def _update_solve_raw(work, problem, result, x_buf, lam_buf, H, f, A_buf, upper, lower, sense):
    """``Model.update(H, f, A_buf, upper, lower, sense)`` then ``Model.solve()``'s C calls; the exit
    flag, or LAYOUT_REFUSED (nothing called) when a shape or stride is not the set-up one."""
    n = problem[0] & 0xFFFFFFFF
    m = problem[0] >> 32
    ms = problem[1] & 0xFFFFFFFF
    if (H.shape[0] != n or H.shape[1] != n or H.strides[1] != 8 or H.strides[0] != 8 * n
            or f.shape[0] != n or f.strides[0] != 8 or x_buf.shape[0] != n or lam_buf.shape[0] != m
            or A_buf.shape[0] != m - ms or A_buf.shape[1] != n or A_buf.strides[1] != 8
            or A_buf.strides[0] != 8 * n or upper.shape[0] != m or upper.strides[0] != 8
            or lower.shape[0] != m or lower.strides[0] != 8 or sense.shape[0] != m or sense.strides[0] != 4
            or work.shape[0] * 8 < 4096 or result.shape[0] != 8 or problem.shape[0] != 10):
        return -1000
    problem[2] = H.ctypes.data
    problem[3] = f.ctypes.data
    problem[4] = A_buf.ctypes.data
    problem[5] = upper.ctypes.data
    problem[6] = lower.ctypes.data
    problem[7] = sense.ctypes.data
    _update_ldp_c(31, work.ctypes.data, problem.ctypes.data)  # Rinv | M | v | d | sense
    result[0] = x_buf.ctypes.data
    result[1] = lam_buf.ctypes.data
    for i in range(2, 8):
        result[i] = 0
    _solve_c(result.ctypes.data, work.ctypes.data)
    return (result[4] << 32) >> 32  # exitflag: the low int of the word, sign-extended


@njit(cache=True)
def update_solve(work, problem, result, x_buf, lam_buf, H, f, A_buf, upper, lower, sense):
    """One level on a set-up :class:`NativeModel` (its ``_work``, ``_problem``, ``_result``,
    ``_x``, ``_lam``): ``Model.update(H, f, A_buf, upper, lower, sense)`` and ``Model.solve()``
    in one call. ``(x, flag)``: ``x`` a fresh copy of DAQP's answer, ``flag`` DAQP's exit flag
    (:data:`LAYOUT_REFUSED` when a shape does not fit the model)."""
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, H, f, A_buf, upper, lower, sense)
    return x_buf.copy(), flag


@njit(cache=True)
def update_solve_check_clip_rate(work, problem, result, x_buf, lam_buf, H, f, A_buf, upper, lower, sense,
                                 box_lower, box_upper, A, b, G, h, tol, previous, dt):
    """:func:`update_solve`, then (flag >= 0) ``check_clip_rate``: ``(x, flag, rate)``, ``rate``
    empty when the flag is negative or the answer is rejected (``x`` then as DAQP returned it)."""
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, H, f, A_buf, upper, lower, sense)
    x = x_buf.copy()
    if flag < 0:
        return x, flag, np.empty(0)
    return x, flag, check_clip_rate(x, box_lower, box_upper, A, b, G, h, tol, previous, dt)


# ----------------------------------------------------------------- self-test


def _test_problems():
    """Fixed QPs in DaqpBackend's layout (n bounds, n equality slots, inequality rows)."""
    rng = np.random.default_rng(20261202)
    out = []
    for n, n_in, n_eq in ((3, 2, 1), (5, 4, 2), (7, 6, 0), (6, 3, 3)):
        cases = []
        for k in range(4):
            M = rng.standard_normal((n, n))
            H = M @ M.T + 0.1 * np.eye(n)
            f = rng.standard_normal(n)
            A = np.zeros((n + n_in, n))
            upper = np.full(2 * n + n_in, 1e30)
            lower = np.full(2 * n + n_in, -1e30)
            sense = np.zeros(2 * n + n_in, dtype=np.int32)
            upper[:n], lower[:n] = 2.0, -2.0
            A[:n_eq] = rng.standard_normal((n_eq, n))
            b = 0.1 * rng.standard_normal(n_eq)
            upper[n:n + n_eq] = b
            lower[n:n + n_eq] = b
            sense[n:n + n_eq] = 5
            A[n:] = rng.standard_normal((n_in, n))
            upper[2 * n:] = 0.2 * rng.standard_normal(n_in)
            if k == 3:  # infeasible: a row asks for more than the box allows
                A[n] = 0.0
                A[n, 0] = 1.0
                upper[2 * n] = -5.0
            cases.append((H, f, A, upper, lower, sense))
        out.append(cases)
    return out


def _same(a, b) -> bool:
    # (x, fval, exitflag) as daqp.Model.solve returns them: every bit
    return (a[0].tobytes() == b[0].tobytes() and np.float64(a[1]).tobytes() == np.float64(b[1]).tobytes()
            and int(a[2]) == int(b[2]))


def _self_test() -> None:
    """Raises NativeLayoutError unless every answer of the native paths is daqp.Model's, bit for bit."""
    import daqp

    if _default_settings_bytes(_State.lib)[:8] != np.float64(1e-6).tobytes():
        raise NativeLayoutError("daqp_default_settings does not start with primal_tol 1e-6")
    for cases in _test_problems():
        H0, f0, A0, u0, l0, s0 = cases[0]
        reference, native, compiled = daqp.Model(), NativeModel(), NativeModel()
        results = [m.setup(H0, f0, A0, u0, l0, s0)[0] for m in (reference, native, compiled)]
        if len(set(results)) != 1 or results[0] < 0:
            raise NativeLayoutError(f"setup flags differ: {results}")
        for H, f, A, upper, lower, sense in cases:
            ref = reference.solve()[:3]
            nat = native.solve()[:3]
            if not _same(ref, nat):
                raise NativeLayoutError("NativeModel.solve differs from daqp.Model.solve")
            # the update that keeps the rows (DAQP's own sense), then the full one
            reference.update(H=H, f=f, bupper=upper, blower=lower)
            native.update(H=H, f=f, bupper=upper, blower=lower)
            if not _same(reference.solve()[:3], native.solve()[:3]):
                raise NativeLayoutError("NativeModel.update without rows differs from daqp.Model's")
            reference.update(H, f, A, upper, lower, sense)
            native.update(H, f, A, upper, lower, sense)
            ref = reference.solve()[:3]
            if not _same(ref, native.solve()[:3]):
                raise NativeLayoutError("NativeModel.update differs from daqp.Model.update")
            if compiled._has_solved is False:
                compiled.solve()
            x, flag = update_solve(compiled._work, compiled._problem, compiled._result, compiled._x, compiled._lam,
                                   H, f, A, upper, lower, sense)
            compiled._has_solved = True
            fval = float(compiled._result.view(np.float64)[2])
            if not _same(ref, (x, fval, int(flag))):
                raise NativeLayoutError(f"compiled update_solve differs from daqp.Model (flag {flag} vs {ref[2]})")
            if np.asarray(x).shape != (H.shape[0],):
                raise NativeLayoutError("compiled update_solve returned a wrong shape")
        if reference.solve()[2] >= 0:
            raise NativeLayoutError("the infeasible test QP was not reported infeasible")


# ----------------------------------------------------------------- two levels in one call
# The episode's cascade (two DAQP levels, both NativeModels, inequality rows present) in one
# compiled call per tick (``Solver._solve_step``): the upper level's ``assemble_load_<k>``, DAQP
# update + solve, ``handover_<k>_<l>`` (check, clip, equalities, the lower level's assembly),
# the lower level's DAQP update + solve and ``check_clip_rate``: the same calls in the same
# order as the level-by-level path. It stops at the first step that path would leave the fast
# path at; ``stage`` says where (the caller resumes there with the same code):
#   0: the upper level's DAQP flag < 0 (or LAYOUT_REFUSED: nothing passed to DAQP; the level is
#      assembled and loaded), 1: the upper answer rejected by the check (the lower level untouched),
#   2: the lower level's DAQP flag < 0 (or LAYOUT_REFUSED) or its answer rejected, 3: done.
# Returns (stage, n_eq_upper, x_upper, flag_upper, rows, rhs, n_eq_lower, x_lower, flag_lower, rate).


@njit(cache=True)
def cascade2_1_1(block, reg, J0, w0, v0, work, problem, result, x_buf, lam_buf, A_buf, buf_upper, buf_lower, sense,
                 n_eq_before, block2, K0, u0, y0, work2, problem2, result2, x_buf2, lam_buf2, A_buf2, buf_upper2,
                 buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper, tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (1 task(s) above, 1 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_1(block, reg, J0, w0, v0, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower, upper,
                           n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_1_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block2, reg,
                                              K0, u0, y0, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_1_2(block, reg, J0, w0, v0, work, problem, result, x_buf, lam_buf, A_buf, buf_upper, buf_lower, sense,
                 n_eq_before, block2, K0, u0, y0, K1, u1, y1, work2, problem2, result2, x_buf2, lam_buf2, A_buf2,
                 buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper, tol, eq_tol, stack, previous,
                 dt, inf):
    """Two DAQP levels (1 task(s) above, 2 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_1(block, reg, J0, w0, v0, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower, upper,
                           n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_1_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block2, reg,
                                              K0, u0, y0, K1, u1, y1, A_buf2, buf_upper2, buf_lower2, sense2,
                                              n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_1_3(block, reg, J0, w0, v0, work, problem, result, x_buf, lam_buf, A_buf, buf_upper, buf_lower, sense,
                 n_eq_before, block2, K0, u0, y0, K1, u1, y1, K2, u2, y2, work2, problem2, result2, x_buf2, lam_buf2,
                 A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper, tol, eq_tol, stack,
                 previous, dt, inf):
    """Two DAQP levels (1 task(s) above, 3 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_1(block, reg, J0, w0, v0, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower, upper,
                           n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_1_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block2, reg,
                                              K0, u0, y0, K1, u1, y1, K2, u2, y2, A_buf2, buf_upper2, buf_lower2,
                                              sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_1_4(block, reg, J0, w0, v0, work, problem, result, x_buf, lam_buf, A_buf, buf_upper, buf_lower, sense,
                 n_eq_before, block2, K0, u0, y0, K1, u1, y1, K2, u2, y2, K3, u3, y3, work2, problem2, result2,
                 x_buf2, lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper,
                 tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (1 task(s) above, 4 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_1(block, reg, J0, w0, v0, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower, upper,
                           n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_1_4(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block2, reg,
                                              K0, u0, y0, K1, u1, y1, K2, u2, y2, K3, u3, y3, A_buf2, buf_upper2,
                                              buf_lower2, sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_2_1(block, reg, J0, w0, v0, J1, w1, v1, work, problem, result, x_buf, lam_buf, A_buf, buf_upper,
                 buf_lower, sense, n_eq_before, block2, K0, u0, y0, work2, problem2, result2, x_buf2, lam_buf2,
                 A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper, tol, eq_tol, stack,
                 previous, dt, inf):
    """Two DAQP levels (2 task(s) above, 1 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_2(block, reg, J0, w0, v0, J1, w1, v1, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower,
                           upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_2_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block2,
                                              reg, K0, u0, y0, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2,
                                              inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_2_2(block, reg, J0, w0, v0, J1, w1, v1, work, problem, result, x_buf, lam_buf, A_buf, buf_upper,
                 buf_lower, sense, n_eq_before, block2, K0, u0, y0, K1, u1, y1, work2, problem2, result2, x_buf2,
                 lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper, tol,
                 eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (2 task(s) above, 2 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_2(block, reg, J0, w0, v0, J1, w1, v1, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower,
                           upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_2_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block2,
                                              reg, K0, u0, y0, K1, u1, y1, A_buf2, buf_upper2, buf_lower2, sense2,
                                              n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_2_3(block, reg, J0, w0, v0, J1, w1, v1, work, problem, result, x_buf, lam_buf, A_buf, buf_upper,
                 buf_lower, sense, n_eq_before, block2, K0, u0, y0, K1, u1, y1, K2, u2, y2, work2, problem2, result2,
                 x_buf2, lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper,
                 tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (2 task(s) above, 3 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_2(block, reg, J0, w0, v0, J1, w1, v1, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower,
                           upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_2_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block2,
                                              reg, K0, u0, y0, K1, u1, y1, K2, u2, y2, A_buf2, buf_upper2, buf_lower2,
                                              sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_2_4(block, reg, J0, w0, v0, J1, w1, v1, work, problem, result, x_buf, lam_buf, A_buf, buf_upper,
                 buf_lower, sense, n_eq_before, block2, K0, u0, y0, K1, u1, y1, K2, u2, y2, K3, u3, y3, work2,
                 problem2, result2, x_buf2, lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G,
                 h, lower, upper, tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (2 task(s) above, 4 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_2(block, reg, J0, w0, v0, J1, w1, v1, A_buf, buf_upper, buf_lower, sense, A, b, G, h, lower,
                           upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_2_4(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block2,
                                              reg, K0, u0, y0, K1, u1, y1, K2, u2, y2, K3, u3, y3, A_buf2, buf_upper2,
                                              buf_lower2, sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_3_1(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, work, problem, result, x_buf, lam_buf, A_buf,
                 buf_upper, buf_lower, sense, n_eq_before, block2, K0, u0, y0, work2, problem2, result2, x_buf2,
                 lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper, tol,
                 eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (3 task(s) above, 1 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_3(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, A_buf, buf_upper, buf_lower, sense, A, b,
                           G, h, lower, upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_3_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2,
                                              block2, reg, K0, u0, y0, A_buf2, buf_upper2, buf_lower2, sense2,
                                              n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_3_2(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, work, problem, result, x_buf, lam_buf, A_buf,
                 buf_upper, buf_lower, sense, n_eq_before, block2, K0, u0, y0, K1, u1, y1, work2, problem2, result2,
                 x_buf2, lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G, h, lower, upper,
                 tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (3 task(s) above, 2 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_3(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, A_buf, buf_upper, buf_lower, sense, A, b,
                           G, h, lower, upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_3_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2,
                                              block2, reg, K0, u0, y0, K1, u1, y1, A_buf2, buf_upper2, buf_lower2,
                                              sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_3_3(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, work, problem, result, x_buf, lam_buf, A_buf,
                 buf_upper, buf_lower, sense, n_eq_before, block2, K0, u0, y0, K1, u1, y1, K2, u2, y2, work2,
                 problem2, result2, x_buf2, lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A, b, G,
                 h, lower, upper, tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (3 task(s) above, 3 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_3(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, A_buf, buf_upper, buf_lower, sense, A, b,
                           G, h, lower, upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_3_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2,
                                              block2, reg, K0, u0, y0, K1, u1, y1, K2, u2, y2, A_buf2, buf_upper2,
                                              buf_lower2, sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


@njit(cache=True)
def cascade2_3_4(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, work, problem, result, x_buf, lam_buf, A_buf,
                 buf_upper, buf_lower, sense, n_eq_before, block2, K0, u0, y0, K1, u1, y1, K2, u2, y2, K3, u3, y3,
                 work2, problem2, result2, x_buf2, lam_buf2, A_buf2, buf_upper2, buf_lower2, sense2, n_eq_before2, A,
                 b, G, h, lower, upper, tol, eq_tol, stack, previous, dt, inf):
    """Two DAQP levels (3 task(s) above, 4 below) in one call (see the comment above)."""
    n = block.shape[1]
    n_eq = assemble_load_3(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, A_buf, buf_upper, buf_lower, sense, A, b,
                           G, h, lower, upper, n_eq_before, inf)
    flag = _update_solve_raw(work, problem, result, x_buf, lam_buf, block[:n], block[n], A_buf, buf_upper, buf_lower,
                             sense)
    x = x_buf.copy()
    if flag < 0:
        return 0, n_eq, x, flag, np.empty((0, n)), np.empty(0), -1, x, 0, np.empty(0)
    accepted, rows, rhs, n_eq2 = handover_3_4(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2,
                                              block2, reg, K0, u0, y0, K1, u1, y1, K2, u2, y2, K3, u3, y3, A_buf2,
                                              buf_upper2, buf_lower2, sense2, n_eq_before2, inf)
    if not accepted:
        return 1, n_eq, x, flag, rows, rhs, -1, x, 0, np.empty(0)
    flag2 = _update_solve_raw(work2, problem2, result2, x_buf2, lam_buf2, block2[:n], block2[n], A_buf2, buf_upper2,
                              buf_lower2, sense2)
    x2 = x_buf2.copy()
    if flag2 < 0:
        return 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, np.empty(0)
    rate = check_clip_rate(x2, lower, upper, rows, rhs, G, h, tol, previous, dt)
    return 3 if rate.shape[0] else 2, n_eq, x, flag, rows, rhs, n_eq2, x2, flag2, rate


#: ``cascade2_<k>_<l>`` by (tasks above, tasks below).
CASCADE2 = {
    (1, 1): cascade2_1_1, (1, 2): cascade2_1_2, (1, 3): cascade2_1_3, (1, 4): cascade2_1_4,
    (2, 1): cascade2_2_1, (2, 2): cascade2_2_2, (2, 3): cascade2_2_3, (2, 4): cascade2_2_4,
    (3, 1): cascade2_3_1, (3, 2): cascade2_3_2, (3, 3): cascade2_3_3, (3, 4): cascade2_3_4,
}

"""The native DAQP path (``harvest_qp._daqp_native``: DAQP's C API called directly) against
daqp's own Python class ``daqp.Model``, bit for bit, and the fallback to ``daqp.Model``.

The oracle throughout is ``daqp.Model`` (the Cython wrapper shipped with daqp, which this path
replaces) given the same sequence of set-ups, updates and solves, or a whole solver whose DAQP
models are ``daqp.Model`` (made while the native path is disabled).
"""

import copy
import pickle
from importlib import metadata

import daqp
import numpy as np
import pytest

import harvest_qp.solver as solver_module
from harvest_qp import Configuration, TaskController
from harvest_qp import _daqp_native as native
from harvest_qp.backends import DaqpBackend
from harvest_qp.robot.description import HOME_Q
from tests.core.test_qp_speed_paths import _levels_problem  # tasks on levels 1, 2, ... and collision rows


@pytest.fixture
def native_state():
    """Restores the module's switch and check results after a test that changes them."""
    saved = {k: getattr(native._State, k) for k in ("checked", "ok", "reason", "lib", "enabled")}
    yield native._State
    for k, v in saved.items():
        setattr(native._State, k, v)


def _qp(rng, n, n_in, n_eq, *, infeasible=False):
    """One QP in DaqpBackend's layout (n bounds, n equality slots with sense 5, inequality rows)."""
    M = rng.normal(size=(n, n))
    H = M @ M.T + 0.05 * np.eye(n)
    f = rng.normal(size=n)
    A = np.zeros((n + n_in, n))
    upper = np.full(2 * n + n_in, 1e30)
    lower = np.full(2 * n + n_in, -1e30)
    sense = np.zeros(2 * n + n_in, dtype=np.int32)
    upper[:n], lower[:n] = rng.uniform(0.5, 2.0, n), -rng.uniform(0.5, 2.0, n)
    A[:n_eq] = rng.normal(size=(n_eq, n))
    b = 0.05 * rng.normal(size=n_eq)
    upper[n:n + n_eq], lower[n:n + n_eq], sense[n:n + n_eq] = b, b, 5
    A[n:] = rng.normal(size=(n_in, n))
    upper[2 * n:] = rng.uniform(0.02, 0.5, n_in)  # x = 0 meets them: feasible unless made not to be
    if infeasible:  # an equality that the box cannot meet
        A[0] = 0.0
        A[0, 0] = 1.0
        upper[n], lower[n], sense[n] = 10.0, 10.0, 5
    return H, f, A, upper, lower, sense


def _bits(answer):
    x, fval, flag = answer[0], answer[1], answer[2]
    return x.tobytes(), np.float64(fval).tobytes(), int(flag)


@pytest.mark.parametrize("n, n_in", [(2, 0), (4, 3), (12, 32), (7, 1)])
def test_native_model_equals_daqp_model_bit_for_bit(n, n_in):
    """Oracle: ``daqp.Model`` given the same calls. Over 12 QPs (0 to n equalities, every third one
    infeasible) each updated in full and solved, then updated without its rows (DAQP's own sense,
    read from the workspace) and solved: ``NativeModel``'s answer, cost and exit flag, and the
    compiled ``update_solve``'s on a third model, are the same bits.

    Bugs caught: the update mask without the sense bit (planted in ``NativeModel.update`` and seen
    failing: the equality slots of a new QP not activated; the import self-test refuses it too),
    the exit flag read from the wrong word of the result, the warm sense pointer read from the
    wrong workspace offset."""
    assert native.available(), native.disabled_reason()
    rng = np.random.default_rng(n * 100 + n_in)
    qps = [_qp(rng, n, n_in, k % (n + 1), infeasible=(k % 3 == 2)) for k in range(12)]
    reference, model, compiled = daqp.Model(), native.NativeModel(), native.NativeModel()
    flags = [m.setup(*qps[0])[0] for m in (reference, model, compiled)]
    assert flags[0] == flags[1] == flags[2] == 1
    seen = set()
    for H, f, A, upper, lower, sense in qps:
        reference.update(H, f, A, upper, lower, sense)
        model.update(H, f, A, upper, lower, sense)
        expected = reference.solve()
        assert _bits(model.solve()) == _bits(expected)
        x, flag = compiled.update_solve(H, f, A, upper, lower, sense)
        fval = float(compiled._result.view(np.float64)[2])
        assert _bits((x, fval, flag)) == _bits(expected)
        seen.add(int(expected[2]) > 0)
        # The update that keeps the rows (sense omitted: DAQP's warm sense), new cost and bounds.
        H2, f2 = H + 0.1 * np.eye(n), f[::-1].copy()
        for m in (reference, model):
            m.update(H=H2, f=f2, bupper=upper, blower=lower)
        assert _bits(model.solve()) == _bits(reference.solve())
    assert seen == {True, False}  # both solved and infeasible QPs were compared


def test_compiled_call_refuses_arrays_that_do_not_fit_the_model():
    """Oracle: by construction (shapes) and ``daqp.Model``. A Hessian of the wrong size, a strided
    Hessian view or a short sense vector is refused with LAYOUT_REFUSED and nothing reaches DAQP
    (the next solve equals daqp.Model's, which never saw them); ``NativeModel.update_solve`` then
    does what daqp.Model does with such arrays (ignores them).
    Bug caught (planted and seen failing): the shape checks bypassed (DAQP would read past the arrays)."""
    assert native.available(), native.disabled_reason()
    rng = np.random.default_rng(5)
    H, f, A, upper, lower, sense = _qp(rng, 5, 4, 2)
    reference, model = daqp.Model(), native.NativeModel()
    reference.setup(H, f, A, upper, lower, sense)
    model.setup(H, f, A, upper, lower, sense)
    bad = [
        (np.eye(6), f, A, upper, lower, sense),
        (np.eye(10)[::2, ::2], f, A, upper, lower, sense),
        (H, f, A, upper, lower, sense[:-1].copy()),
    ]
    for args in bad:
        x, flag = native.update_solve(model._work, model._problem, model._result, model._x, model._lam, *args)
        assert flag == native.LAYOUT_REFUSED
    assert _bits(model.solve()) == _bits(reference.solve())
    for args in bad:
        expected = (reference.update(*args), reference.solve())[1]
        x, flag = model.update_solve(*args)
        assert x.tobytes() == expected[0].tobytes() and flag == expected[2]


def test_available_only_for_the_validated_daqp(native_state, monkeypatch):
    """Oracle: the installed daqp's version (importlib.metadata) and the validated one. The
    installed 0.11.0 passes the self-test; a reported other version, a missing C symbol or a
    failing self-test disables the path (with the reason) and DaqpBackend then makes daqp.Model.
    Bug caught (planted and seen failing): the version check skipped (a 0.12 would be driven
    with 0.11's struct layouts)."""
    installed = metadata.version("daqp")
    native_state.checked = False
    assert native.available() == (installed == native.VALIDATED_VERSION)
    for breaker in ("version", "self_test"):
        native_state.checked, native_state.lib = False, None
        with monkeypatch.context() as m:
            if breaker == "version":
                m.setattr(native.metadata, "version", lambda name: "0.12.0")
            else:
                m.setattr(native, "_self_test", lambda: (_ for _ in ()).throw(native.NativeLayoutError("planted")))
            assert not native.available()
            reason = native.disabled_reason()
            assert ("0.12.0" in reason) if breaker == "version" else ("planted" in reason)
            assert type(native.new_model(daqp)) is daqp.Model
    native_state.checked = False
    native_state.enabled = False
    assert not native.available() and "disabled" in native.disabled_reason()
    assert type(native.new_model(daqp)) is daqp.Model
    native_state.enabled = True
    native_state.checked = False
    assert native.available() == (installed == native.VALIDATED_VERSION)


def _outcome(call):
    try:
        return call()
    except Exception as err:  # noqa: BLE001 - compared between the two paths
        return type(err), str(err)


def _same(a, b):
    """Two ``(solution, acceleration)`` outcomes (or two errors) alike, bit for bit."""
    assert type(a) is type(b)
    if isinstance(a[0], type):
        assert a == b
        return
    (sa, acc_a), (sb, acc_b) = a, b
    assert np.array_equal(sa.qdot, sb.qdot) and sa.qdot.tobytes() == sb.qdot.tobytes()
    assert (acc_a is None) == (acc_b is None)
    if acc_a is not None:
        assert acc_a.tobytes() == acc_b.tobytes()
    assert sa.retries == sb.retries and sa.relaxed == sb.relaxed and sa.conflicts == sb.conflicts
    for name in ("box_relaxation", "row_relaxation"):
        x, y = getattr(sa, name), getattr(sb, name)
        assert (x is None and y is None) or np.array_equal(x, y), name
    assert [p.level for p in sa.problems] == [p.level for p in sb.problems]
    for pa, pb in zip(sa.problems, sb.problems):
        for name in ("H", "f", "A", "b", "lower", "upper", "G", "h"):
            assert getattr(pa, name).tobytes() == getattr(pb, name).tobytes(), name


def _twin_solvers(native_state, config, tasks, limits):
    """A solver whose DAQP models will be NativeModels and one whose models will be daqp.Model."""
    fast, python = (TaskController(config, tasks, limits).solver for _ in range(2))
    for s in (fast, python):
        s.fallback_backends = ("quadprog",)  # proxsuite is not bit-for-bit repeatable
    return fast, python


def _solve_both(native_state, fast, python, config, tasks, limits, previous, dt=0.002):
    native_state.enabled = True
    a = _outcome(lambda: fast._solve_step(config, tasks, limits, dt, previous))
    native_state.enabled = False  # models this solver makes now are daqp.Model
    b = _outcome(lambda: python._solve_step(config, tasks, limits, dt, previous))
    native_state.enabled = True
    return a, b


def _spy_stages(monkeypatch):
    stages = []
    wrapped = {}
    for key, kernel in native.CASCADE2.items():
        def spy(*args, _kernel=kernel):
            out = _kernel(*args)
            stages.append(int(out[0]))
            return out
        wrapped[key] = spy
    monkeypatch.setattr(solver_module, "CASCADE2", wrapped)
    return stages


def _model_types(solver):
    return {type(b._model) for b in solver._backends.values() if isinstance(b, DaqpBackend) and b._model is not None}


@pytest.mark.parametrize("counts", [(2, 3), (1, 4), (3, 1), (2, 2), (1, 3, 1)])
def test_fused_native_cascade_equals_the_python_daqp_path_bit_for_bit(native_state, monkeypatch, counts):
    """Oracle: the same solver code with ``daqp.Model`` (native path disabled when its models are
    made). ``_solve_step`` with both levels in one compiled call (``cascade2_*``) gives the same
    command, acceleration, problems (H, f, A, b, ...), DAQP buffers and equality counts bit for bit
    over 12 states; a spy checks the fused call ran and ended with both levels accepted. Three
    levels (no fused call; each level's native update and solve in one call) agree too.

    Bugs caught (planted and seen failing): the lower level solved with the upper level's ``f``
    in the fused kernel (4 of these tests and the resume test failed); a lower level that DAQP
    failed resumed with the upper level's answer (the (2, 3) case, where DAQP fails once)."""
    assert native.available(), native.disabled_reason()
    rng = np.random.default_rng(sum(counts) * 7 + counts[0])
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _levels_problem(config, rng, counts)
    limits = TaskController(config, tasks, limits).limits
    fast, python = _twin_solvers(native_state, config, tasks, limits)
    stages = _spy_stages(monkeypatch)
    for _ in range(12):
        q = HOME_Q + rng.normal(0, 0.15, 12)
        previous = rng.normal(0, 0.005, 12)
        config.update(q)
        a, b = _solve_both(native_state, fast, python, config, tasks, limits, previous)
        _same(a, b)
        for key, backend in fast._backends.items():
            other = python._backends[key]
            if isinstance(backend, DaqpBackend):
                for name in ("_A", "_upper", "_lower", "_sense"):
                    assert getattr(backend, name).tobytes() == getattr(other, name).tobytes(), name
                assert backend._n_eq == other._n_eq
    assert _model_types(fast) == {native.NativeModel} and _model_types(python) == {daqp.Model}
    if len(counts) == 2:  # (a DAQP failure sets its model up again: that tick is not fused)
        assert stages.count(3) >= 6, stages
    else:  # three levels: each level's native update and solve in one call, no fused cascade
        assert not stages


def test_fused_native_cascade_resumes_like_the_python_daqp_path(native_state, monkeypatch):
    """Oracle: the Python daqp path (as above). Where the fused call stops early the loop resumes
    from its results: DAQP reporting infeasibility (fuzz-like states that end relaxed or with a
    fallback: stages 0 and 2) and every answer rejected by the fused check (the tolerance set
    below zero for the fast check only: stages 1 and 2, each then accepted by ``_checked``): the
    same outcome bit for bit, retries and relaxations included, or the same error.

    Bug caught (planted and seen failing): an upper answer the fused check rejected handed to the
    loop as accepted (the lower level then solved on its equalities without the recovery)."""
    assert native.available(), native.disabled_reason()
    rng = np.random.default_rng(11)
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _levels_problem(config, rng, (2, 3))
    limits = TaskController(config, tasks, limits).limits
    fast, python = _twin_solvers(native_state, config, tasks, limits)
    stages = _spy_stages(monkeypatch)
    relaxed = 0
    for k in range(48):
        q = np.clip(HOME_Q + rng.normal(0, 0.6, 12), config.lower_limits, config.upper_limits)
        previous = rng.uniform(-0.5, 0.5, 12) * config.velocity_limits
        config.update(q)
        with monkeypatch.context() as m:
            if k % 4 == 3:  # every fused check rejects; _checked (backends' tolerance) then accepts
                m.setattr(solver_module, "FEASIBILITY_TOLERANCE", -1.0)
            a, b = _solve_both(native_state, fast, python, config, tasks, limits, previous)
        _same(a, b)
        relaxed += not isinstance(a[0], type) and a[0].box_relaxation is not None
    assert relaxed >= 2
    assert {0, 1, 3} <= set(stages), sorted(set(stages))


def test_native_model_cannot_be_copied_or_pickled_like_daqp_model():
    """Oracle: ``daqp.Model`` (copy, deepcopy and pickle raise TypeError). A copied NativeModel
    would hold the same DAQP pointers as the original and free them twice.
    Bug caught (planted and seen failing): no ``__reduce_ex__`` guard (copy.copy succeeds)."""
    assert native.available(), native.disabled_reason()
    model = native.NativeModel()
    model.setup(*_qp(np.random.default_rng(3), 3, 2, 1))
    for action in (copy.copy, copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError) as expected:
            action(daqp.Model())
        with pytest.raises(TypeError) as got:
            action(model)
        assert str(got.value) == str(expected.value)


def test_call_arguments_follow_a_repeated_setup():
    """Oracle: ``daqp.Model`` set up on a 3-variable QP, then again on a 5-variable one. The fused
    cascade passes ``NativeModel._call_args`` (work, problem, result, x, lam) instead of reading the
    five attributes: after each setup they must be the model's current buffers, and the compiled
    ``update_solve`` given them must answer as ``daqp.Model`` does (not refuse the layout).

    Bug caught (planted and seen failing): ``_call_args`` set once and not renewed by a second
    ``setup`` (the 3-long x and lam of the first problem handed over: the call refuses the layout)."""
    assert native.available(), native.disabled_reason()
    rng = np.random.default_rng(11)
    model, reference = native.NativeModel(), daqp.Model()
    assert model._call_args is None  # never set up: the solver takes its own path
    for n, n_in, n_eq in ((3, 2, 1), (5, 4, 2)):
        qp = _qp(rng, n, n_in, n_eq)
        model.setup(*qp)
        reference.setup(*qp)
        args = model._call_args
        assert [a is b for a, b in zip(args, (model._work, model._problem, model._result, model._x, model._lam))] \
            == [True] * 5
        H, f = qp[0] + 0.2 * np.eye(n), qp[1][::-1].copy()
        x, flag = native.update_solve(*args, H, f, *qp[2:])
        reference.update(H, f, *qp[2:])
        expected = reference.solve()
        assert flag != native.LAYOUT_REFUSED
        assert (x.tobytes(), int(flag)) == (expected[0].tobytes(), int(expected[2]))


_EXIT_WHILE_SOLVING = """
import sys, threading, time
import numpy as np
from harvest_qp import _daqp_native as native
from harvest_qp.backends import make_backend
from harvest_qp.solver import QPProblem
assert native.available(), native.disabled_reason()
n = 12
rng = np.random.default_rng(0)
M = rng.normal(size=(n, n))
p = QPProblem(H=M @ M.T + np.eye(n), f=rng.normal(size=n), lower=-np.ones(n), upper=np.ones(n),
              A=rng.normal(size=(3, n)), b=np.zeros(3), G=rng.normal(size=(60, n)), h=np.ones(60))
def loop():
    backend = make_backend("daqp")
    while True:
        backend.solve(p)
threads = [threading.Thread(target=loop, daemon=True) for _ in range(2)]
for t in threads:
    t.start()
time.sleep(0.3)
sys.exit(0)
"""


def test_interpreter_exit_while_daemon_threads_solve_does_not_crash():
    """Two daemon threads keep solving while the main thread exits, 8 times: exit code 0 each
    time (as with daqp.Model). Bug caught: the models' memory freed by weakref.finalize's exit
    hook while a thread was still inside DAQP (an audit saw SIGSEGV in 8 of 28 such exits;
    planted here by keeping ``atexit``: failed)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    codes = [
        subprocess.run([sys.executable, "-c", _EXIT_WHILE_SOLVING], cwd=root, capture_output=True, timeout=120).returncode
        for _ in range(8)
    ]
    assert codes == [0] * 8, codes


def test_non_float64_arrays_are_converted_as_daqp_model_converts_them():
    """A public QPProblem with integer f (and big-endian H) solved three times by one DAQP backend:
    the float64 problem's answer every time. Bug caught: the compiled update handed the integer
    bytes to DAQP as doubles from the second solve on (answers of 5e-324, accepted as solved)."""
    from harvest_qp.backends import make_backend
    from harvest_qp.solver import QPProblem

    n = 3
    kwargs = dict(lower=-np.ones(n), upper=np.ones(n), A=np.zeros((0, n)), b=np.zeros(0),
                  G=np.array([[0.0, 0.0, 1.0]]), h=np.array([0.9]))
    expected = make_backend("daqp").solve(QPProblem(H=2.0 * np.eye(n), f=np.array([1.0, 2.0, 3.0]), **kwargs))
    np.testing.assert_allclose(expected, [-0.5, -1.0, -1.0], atol=1e-12)  # hand-computed: clipped at the box
    for H, f in ((2.0 * np.eye(n), np.array([1, 2, 3])), ((2.0 * np.eye(n)).astype(">f8"), np.array([1.0, 2.0, 3.0]))):
        backend = make_backend("daqp")
        for _ in range(3):
            assert _bits(backend.solve(QPProblem(H=H, f=f, **kwargs))) == _bits(expected)


def test_update_solve_after_a_failed_setup_raises_like_daqp_model():
    """A setup DAQP rejects (a lower bound above its upper bound) frees DAQP's workspace; the
    next update_solve raises RuntimeError as daqp.Model.update does. Bug caught: update_solve ran
    DAQP on the freed workspace (segmentation fault)."""
    if not native.available():
        pytest.fail(f"native DAQP unavailable: {native.disabled_reason()}")
    n = 3
    H, f = np.eye(n), np.ones(n)
    A = np.zeros((1, n))
    A[0, 0] = 1.0
    upper, lower = np.array([1.0, 1.0, 1.0, 1.0]), np.array([-1.0, -1.0, -1.0, 2.0])
    sense = np.zeros(4, np.intc)
    reference = daqp.Model()
    model = native.NativeModel()
    assert model.setup(H, f, A, upper, lower, sense)[0] == reference.setup(H, f, A, upper, lower, sense)[0] < 0
    with pytest.raises(RuntimeError, match="set up"):
        reference.update(H, f, A, upper, lower, sense)
    with pytest.raises(RuntimeError, match="set up"):
        model.update_solve(H, f, A, upper, lower, sense)

"""The one optimizer: batched damped Newton over independent rows."""

import ast
import pathlib

import numpy as np
import pytest

from emccdcal._optimize import declined_step, dense_step, maximize

SRC = pathlib.Path(__file__).parents[1] / "src" / "emccdcal"


def _quadratic(centre, curvature):
    """Rows ``−½ (x − c)ᵀ A (x − c)``: objective, gradient and information."""

    def evaluate(rows, x):
        d = x - centre[rows]
        A = curvature[rows]
        return (-0.5 * np.einsum("pi,pij,pj->p", d, A, d), -np.einsum("pij,pj->pi", A, d), A)

    return evaluate


def test_rows_reach_their_own_maxima_and_stop_on_bounds():
    rng = np.random.default_rng(0)
    P = 50
    centre = rng.normal(0, 3, (P, 3))
    M = rng.normal(size=(P, 3, 3))
    curvature = M @ np.swapaxes(M, 1, 2) + 0.5 * np.eye(3)
    upper = np.array([np.inf, 1.0, np.inf])
    opt = maximize(
        _quadratic(centre, curvature),
        np.zeros((P, 3)),
        lower=-np.inf,
        upper=upper,
        tol=1e-12,
        max_step=np.inf,
    )
    assert opt.done.all() and not opt.stuck.any()
    # The reference: the same problem by a dense solver with the bound as a constraint.
    from scipy.optimize import minimize

    for p in range(P):
        ref = minimize(
            lambda x: 0.5 * (x - centre[p]) @ curvature[p] @ (x - centre[p]),
            np.zeros(3),
            jac=lambda x: curvature[p] @ (x - centre[p]),
            bounds=[(None, None), (None, 1.0), (None, None)],
            method="L-BFGS-B",
            options={"ftol": 1e-15, "gtol": 1e-12},
        )
        np.testing.assert_allclose(opt.x[p], ref.x, atol=1e-5)
    held = centre[:, 1] > 1.0
    assert held.any() and np.all(opt.x[held, 1] == 1.0)
    # a quadratic is one Newton step away: few iterations, never the limit
    assert opt.iterations.max() <= 8


def test_a_row_without_a_finite_start_is_not_moved_and_stuck():
    centre, curvature = np.zeros((2, 1)), np.ones((2, 1, 1))
    good = _quadratic(centre, curvature)

    def evaluate(rows, x):
        obj, g, info = good(rows, x)
        obj = np.where(rows == 1, np.nan, obj)
        return obj, g, info

    opt = maximize(evaluate, np.ones((2, 1)), lower=-np.inf, upper=np.inf, tol=1e-12)
    assert opt.done.tolist() == [True, False] and opt.stuck.tolist() == [False, True]
    assert opt.x[1, 0] == 1.0 and opt.iterations[1] == 0


def test_stuck_rows_count_as_done_only_below_stuck_tol():
    # A peak the trials can never beat: every step away from 0 is refused.
    def evaluate(rows, x):
        n = len(rows)
        return -1e-9 * (x[:, 0] != 0), np.ones((n, 1)), np.ones((n, 1, 1))

    # the undamped step there promises ½·1·1 = 0.5
    for stuck_tol, stuck in ((0.0, True), (1.0, False), (0.1, True)):
        res = maximize(
            evaluate,
            np.zeros((1, 1)),
            lower=-np.inf,
            upper=np.inf,
            tol=1e-12,
            accept_rtol=0.0,
            stuck_tol=stuck_tol,
            max_step=np.inf,
        )
        assert res.stuck[0] == stuck and res.done[0] == (not stuck)
        assert res.x[0, 0] == 0.0


def test_rtol_stops_on_a_fraction_of_the_objective():
    centre, curvature = np.full((1, 1), 1.0), np.ones((1, 1, 1))
    quad = _quadratic(centre, curvature)

    def offset(rows, x):  # the same quadratic, its objective shifted far from zero
        obj, g, info = quad(rows, x)
        return obj - 1e6, g, info

    # the first step promises ½ (of 1e6): stop at once with rtol 1e-3, not with 1e-15
    assert (
        maximize(
            offset, np.zeros((1, 1)), lower=-np.inf, upper=np.inf, tol=0.0, rtol=1e-3
        ).iterations[0]
        == 0
    )
    assert maximize(offset, np.zeros((1, 1)), lower=-np.inf, upper=np.inf, tol=0.0, rtol=1e-15).x[
        0, 0
    ] == pytest.approx(1.0, abs=1e-6)


def test_steps_that_overshoot_a_ridge_are_damped_until_the_row_settles():
    """An information matrix that understates the curvature along one direction (here by
    1.97×, as a pixel's expected information did against its 50 frames at 25×) makes
    each undamped step overshoot to the other side of the ridge: every step gains a
    little, so none is refused, and before the gain-ratio rule the row zig-zagged to the
    iteration limit. A step that gains under a quarter of its promise raises the damping."""
    A = np.array([[4.0, 3.9], [3.9, 4.0]])  # a ridge: two strongly correlated parameters
    w, v = np.linalg.eigh(A)
    info = (v * (w / np.array([1.97, 1.0]))) @ v.T  # the ridge's curvature understated

    def evaluate(rows, x):
        obj = -0.5 * np.einsum("pf,fg,pg->p", x, A, x)
        return obj, -x @ A, np.broadcast_to(info, (len(rows), 2, 2)).copy()

    x0 = np.array([[1.0, -1.0], [0.5, -0.4]])
    opt = maximize(evaluate, x0, lower=-10.0, upper=10.0, tol=1e-12, max_iter=100)
    assert opt.done.all() and not opt.stuck.any()
    assert (opt.iterations < 60).all(), opt.iterations
    np.testing.assert_allclose(opt.x, 0.0, atol=1e-5)


def _quartic(centre):
    """Rows ``−Σ (d²/2 + d⁴/12)``, d = x − c: objective, gradient and its exact Hessian
    (negated), and a record of the rows asked for their information at each call."""
    asked = []

    def evaluate(rows, x, information=None):
        asked.append(np.ones(len(rows), bool) if information is None else information.copy())
        d = x - centre[rows]
        obj = -np.sum(d**2 / 2 + d**4 / 12, axis=1)
        return obj, -(d + d**3 / 3), (1.0 + d**2)[:, :, None] * np.eye(d.shape[1])

    return evaluate, asked


def test_a_kept_information_is_asked_for_again_only_after_a_step_that_missed():
    """With ``keep_information`` a row's information is computed at the start and then
    only at trials after a step that gained other than it promised (by more than half):
    a row whose curvature hardly changes keeps its first, one far from its maximum gets
    it anew, and every row reaches its maximum."""
    centre = np.array([[0.0], [1.0], [-2.0]])
    x0 = centre + np.array([[0.3], [2.0], [4.0]])  # near, farther, far
    kept, asked = _quartic(centre)
    opt = maximize(kept, x0, lower=-10, upper=10, tol=1e-14, max_step=10, keep_information=True)
    assert opt.done.all()
    np.testing.assert_allclose(opt.x, centre, atol=1e-6)
    assert asked[0].all()  # the start
    trials = np.concatenate(asked[1:])
    assert 0 < trials.sum() < trials.size  # some trials kept it, some were asked for it
    # calls with all three rows still moving: the near row never asks again (its
    # curvature 1 + d² changes by under 10 %), the far one (1 + 16 at its start) does
    together = [a for a in asked[1:] if a.size == 3]
    assert together and not any(a[0] for a in together)
    assert any(a[2] for a in together)


def test_the_declined_step_lands_on_a_quadratics_maximum():
    """A row stopped by a loose tolerance is one undamped step from a quadratic's
    maximum: :func:`declined_step` takes it (not past a bound it is held at), where the
    step is no larger than ``largest`` (beyond, the row stays: a flat direction)."""
    rng = np.random.default_rng(3)
    P = 20
    centre = rng.normal(0, 1, (P, 2))
    M = rng.normal(size=(P, 2, 2))
    curvature = M @ np.swapaxes(M, 1, 2) + 0.5 * np.eye(2)
    upper = np.array([np.inf, 0.5])
    opt = maximize(_quadratic(centre, curvature), centre + 0.3, lower=-np.inf, upper=upper, tol=0.1)
    free = centre[:, 1] < 0.5
    assert np.abs(opt.x[free] - centre[free]).max() > 1e-3  # stopped short
    x = declined_step(opt, -np.inf, upper, largest=1.0)
    np.testing.assert_allclose(x[free], centre[free], atol=1e-12)
    assert np.all(x[:, 1] <= 0.5)
    far = np.abs(opt.x - x).max(axis=1) > 1e-3
    assert far.any()
    np.testing.assert_array_equal(declined_step(opt, -np.inf, upper)[far], opt.x[far])


def test_a_structured_step_gives_the_dense_step():
    rng = np.random.default_rng(1)
    M = rng.normal(size=(4, 3, 3))
    info = M @ np.swapaxes(M, 1, 2) + np.eye(3)
    grad, damping = rng.normal(size=(4, 3)), np.full(4, 0.1)
    held = np.zeros((4, 3), bool)
    held[0, 1] = True
    calls = []

    def step(i, g, d, h):
        calls.append(1)
        return dense_step(i, g, d, h)

    d = dense_step(info, grad, damping, held)
    assert d[0, 1] == 0.0
    A = info[1] + 0.1 * np.diag(np.diag(info[1]))
    np.testing.assert_allclose(d[1], np.linalg.solve(A, grad[1]), rtol=1e-12)
    centre = rng.normal(size=(4, 3))
    a = maximize(
        _quadratic(centre, info),
        np.zeros((4, 3)),
        lower=-np.inf,
        upper=np.inf,
        tol=1e-12,
        step=step,
        max_step=np.inf,
    )
    np.testing.assert_allclose(a.x, centre, atol=1e-6)
    assert calls


#: Every loop that repeats a step until something holds (``for _ in range(n)``, ``while``)
#: outside the optimizer and the root finders (``_optimize.py``, ``_roots.py``), and why
#: it is neither. Found by the loop's shape, not by its variables' names: a new loop
#: fails :func:`test_every_iteration_loop_is_the_optimizers_the_root_finders_or_named`
#: until it goes through them or is named here with its reason.
ITERATIONS = {
    ("model/cascade.py", "single_electron_moments"): "the register's recursion, stage by stage",
    ("model/cascade.py", "_register_transform"): "the register's recursion, stage by stage",
    ("model/cascade_sampling.py", "_pgf_minus_one"): "the register's recursion, stage by stage",
    ("_chebyshev.py", "evaluate_rows"): "the Chebyshev polynomials' three-term recurrence",
    ("model/cascade.py", "_build_table"): "a table's axes refined until its coefficients "
    "converge (Chebyshev interpolation)",
    ("model/cascade_sampling.py", "_sample_stages"): "one binomial draw per stage",
    ("model/cascade_sampling.py", "sample_register_cic"): "electrons leaving the register by stage",
    ("model/cascade_sampling.py", "_invert"): "a guide table's forward steps (sampling)",
    ("model/cascade_sampling.py", "_max_block_exponent"): "counting the table sizes that fit",
    ("model/cascade_sampling.py", "_TableCache.get"): "evicting a cache",
    ("model/_engine.py", "evaluate"): "rounds of windows until every count has its value",
    ("model/pointwise.py", "logpmf_rows"): "runs of rows within a memory budget",
    ("model/shared_register.py", "SharedRegister._build"): "the terms of a power series",
    ("fit/gof.py", "gof_pvalues"): "blocks of rows within a memory budget",
    ("fit/comb.py", "_envelope_fit"): "a grid moved to its parabola's vertex, a few rounds "
    "at most (the ripples' envelope)",
    ("fit/mv.py", "_fit_line"): "a fixed number of re-weightings (weighted least squares)",
    ("fit/darkgain.py", "_core_start"): "two trimmed-moment passes: a start",
    ("fit/profile.py", "profile_bounds"): "the profile deviance's level: every evaluation is a "
    "constrained refit, whose own warm starts the steps keep",
    ("fit/posterior.py", "_sample_pixel"): "Markov chains run on until they converge",
    ("beads/validation/metric.py", "blinking_level"): "EM iterations of a two-level mixture",
    ("beads/cots_bias.py", "_pseudo_true"): "a 2-D system per frame, halved steps keeping v* > 0",
    (
        "beads/cots.py",
        "_corrected_truth",
    ): "a 2-D chord-Newton system, frames left out between tries",
    ("beads/cots.py", "_recentred_fit"): "moving each frame's box onto its spot",
    ("acquire/plan.py", "_allocate"): "greedy allocation of frames, then its trim",
    ("acquire/plan.py", "_brightest"): "doubling to a bracket that _roots.bisect then narrows",
    ("simulate/beads.py", "_place_beads"): "rejection sampling of positions",
    (
        "calibration/schedulers.py",
        "_worker_start.watch",
    ): "a tile worker watching for its parent's death (plumbing)",
    (
        "calibration/schedulers.py",
        "_reach",
    ): "reading a scheduler's first bytes from a socket (plumbing)",
}
#: Where such loops are plumbing, not numerics (files, locks, queues, devices, parsing).
_PLUMBING = (
    "_files.py",
    "_output/files.py",
    "_output/verb.py",
    "_output/results.py",
    "_output/text.py",
    "_util.py",
    "acquire/devices.py",
    "acquire/mm.py",
    "acquire/record.py",
    "data/quality/drift.py",
    "data/quality/stacks.py",
    "data/quality/series.py",
    "data/stacks.py",
)


def _iteration_loops():
    """(file, enclosing function, line) of every ``while`` and ``for _ in range(...)``."""
    found = []

    def visit(node, path, where):
        for child in ast.iter_child_nodes(node):
            name = where
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{where}.{child.name}" if where else child.name
            repeats = isinstance(child, ast.While) or (
                isinstance(child, ast.For)
                and isinstance(child.target, ast.Name)
                and child.target.id.startswith("_")
                and isinstance(child.iter, ast.Call)
                and getattr(child.iter.func, "id", None) == "range"
            )
            if repeats:
                found.append((path, name, child.lineno))
            visit(child, path, name)

    for path in sorted(SRC.rglob("*.py")):
        visit(ast.parse(path.read_text()), path.relative_to(SRC).as_posix(), "")
    return found


def test_every_iteration_loop_is_the_optimizers_the_root_finders_or_named():
    """Roots are found by _roots (bisection, safeguarded and plain Newton), maxima by
    _optimize; any other repeating loop in the numerics is named in ITERATIONS with why."""
    loops = _iteration_loops()
    assert {("_roots.py", "bisect"), ("_optimize.py", "maximize")} <= {f[:2] for f in loops}
    unnamed = [
        f"{path}:{line} in {where}"
        for path, where, line in loops
        if path not in ("_roots.py", "_optimize.py", *_PLUMBING) and (path, where) not in ITERATIONS
    ]
    assert not unnamed, unnamed
    stale = set(ITERATIONS) - {f[:2] for f in loops}
    assert not stale, stale


def test_one_newton_loop_in_the_package():
    """Only the optimizer raises and lowers a damping: no module keeps its own loop."""
    loops = []
    for path in SRC.rglob("*.py"):
        if path.name == "_optimize.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.AugAssign) and isinstance(node.op, (ast.Mult, ast.Div)):
                target = ast.unparse(node.target)
                if any(w in target for w in ("lam", "damp", "mu[")):
                    loops.append(f"{path.relative_to(SRC)}:{node.lineno} {target}")
    assert not loops, loops


def test_chebyshev_tables_interpolate_to_round_off_and_say_when_they_do():
    """The interpolant of an analytic function on a rectangle's Lobatto grid matches it
    to round-off between the nodes once its last coefficients are small, and says it is
    unresolved while they are not."""
    from emccdcal import _chebyshev

    f = lambda x, y: np.exp(1j * x * y) / (2.0 + np.cos(y))  # noqa: E731
    xr, yr = (0.5, 1.5), (-1.0, 3.0)
    rng = np.random.default_rng(3)
    x = rng.uniform(*xr, 40)
    y = rng.uniform(*yr, (40, 7))
    for n_x, n_y, resolved in (
        (5, 9, (False, False)),
        (17, 33, (True, False)),
        (17, 65, (True, True)),
    ):
        nodes = np.meshgrid(
            _chebyshev.lobatto(n_x, *xr), _chebyshev.lobatto(n_y, *yr), indexing="ij"
        )
        coef = _chebyshev.coefficients(f(*nodes))
        assert _chebyshev.resolved(coef, 1e-13) == resolved
        got = _chebyshev.evaluate_rows(coef, xr, yr, x, y)
        err = np.max(np.abs(got - f(x[:, None], y)))
        assert (err < 1e-13) == all(resolved), err
        both = _chebyshev.evaluate_rows(np.stack([coef, 2j * coef], axis=-1), xr, yr, x, y)
        np.testing.assert_allclose(both, np.stack([got, 2j * got], axis=-1), rtol=1e-14)

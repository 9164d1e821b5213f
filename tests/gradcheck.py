"""The central-difference check of an adjoint gradient along one direction, shared by the
gradient tests (tests/test_diff_grid.py, tests/test_diff_mpm.py; their module docstrings derive
the bound for their solvers).

D(e) = (L(p + e r) - L(p - e r)) / 2e differs from <g, r> by a truncation c e^2 + O(e^4) and by
at most 2 delta / 2e, delta the error of one evaluation of L. The truncation is measured, not
guessed: D(e) - D(2e) = -3 c e^2 + O(e^4), so |D(2e) - D(e)| bounds it three times over. A check
passes when |<g, r> - D(e)| <= |D(2e) - D(e)| + 2 delta / e.
"""

import numpy as np

U = np.finfo(float).eps / 2


def check_directional(loss, base, direction, adjoint, e, where, *, rounding=1e3 * U, typical=None,
                      relative=1e-3):
    """Asserts <adjoint, direction> against D(e) of ``loss`` at ``base`` along ``direction``.

    ``loss(p)`` returns (L(p), S) with delta = ``rounding`` S bounding the error of one
    evaluation (S = sum |W| |state| for L = <W, state>). The check must be informative: the bound
    at most ``relative`` |D(e)|, or, when ``typical`` is given, at most ``typical`` |g| |r| /
    sqrt(n), the size of <g, r> for a random r (a particular r may make <g, r> itself small).
    ``where`` names the check in the failure message."""
    def D(step):
        lp, sp = loss(base + step * direction)
        lm, sm = loss(base - step * direction)
        return (lp - lm) / (2 * step), max(sp, sm)

    d1, scale = D(e)
    d2, _ = D(2 * e)
    bound = abs(d2 - d1) + 2 * rounding * scale / e
    got = float(np.sum(adjoint * direction))
    assert abs(got - d1) <= bound, (f"{where}: adjoint {got:.12g} vs central difference {d1:.12g} "
                                    f"(|diff| {abs(got - d1):.3g} > bound {bound:.3g}; D(2e) {d2:.12g})")
    if typical is not None:
        size = np.linalg.norm(adjoint) * np.linalg.norm(direction) / np.sqrt(np.size(direction))
        assert bound <= typical * size, f"{where}: bound {bound:.3g} is not small against |g| |r| / sqrt(n) = {size:.3g}"
    else:
        assert bound <= relative * abs(d1), f"{where}: bound {bound:.3g} is not small against |D| = {abs(d1):.3g}"


def step_adjoint_at_thread_counts(sim, dt, control, seed, counts):
    """One `_diff_step` of `sim` from its current state, then its `_diff_step_adjoint` for random
    output gradients (rng `seed`) run once at each thread count in `counts`: the list of
    (grad_before, grad_params, grad_control) results, for bitwise comparisons. The thread count
    is restored afterwards."""
    import kinema as km

    rng = np.random.default_rng(seed)
    before = sim.state()
    sim._diff_step(dt, control, {})
    after = sim.state()
    grads = {n: rng.normal(size=np.shape(after[n])) for n in sim._diff_state_names}
    old = km.get_num_threads()
    try:
        results = []
        for n in counts:
            km.set_num_threads(n)
            results.append(sim._diff_step_adjoint(dt, before, after, control, grads, {}))
        return results
    finally:
        km.set_num_threads(old)

"""The bitwise-resume check shared by the state tests (tests/test_contact.py,
tests/test_contact_pattern.py, tests/test_nbody.py): a simulation restored from ``state()``
continues exactly as the original does, bit for bit, not merely to rounding."""

import numpy as np


def assert_resumes_bitwise(make, step, before, after, names=("x", "v")):
    """Steps a fresh ``make()`` ``before`` times, saves its ``state()`` and steps it ``after``
    times more; a second fresh ``make()`` takes the saved state and steps ``after`` times. The
    attributes ``names`` of the two must be equal to the bit. ``step(sim)`` takes one step and
    returns what the step returns; the returns of the first run's steps before the save are
    returned (e.g. StepStats, to show the saved run did what the test is about)."""
    a = make()
    stats = [step(a) for _ in range(before)]
    saved = a.state()
    for _ in range(after):
        step(a)
    b = make()
    b.set_state(saved)
    for _ in range(after):
        step(b)
    for name in names:
        assert np.array_equal(getattr(a, name), getattr(b, name)), f"{name}: the resumed run differs"
    return stats

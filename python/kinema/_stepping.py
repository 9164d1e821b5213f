"""The fixed-step driver shared by the particle simulations' ``advance``."""

from __future__ import annotations

from kinema._checks import non_negative, positive


def advance(sim, duration, dt, callback=None):
    """Calls sim.step(h) with h = dt up to sim.time + duration, the last step shortened to land
    on it; callback(sim) after every step. Returns sim."""
    duration = non_negative(duration, "duration")
    dt = positive(dt, "dt")
    end = sim.time + duration
    while sim.time < end:
        h = min(dt, end - sim.time)
        if h <= 1e-14 * max(1.0, abs(end)):
            break
        sim.step(h)
        if callback is not None:
            callback(sim)
    return sim

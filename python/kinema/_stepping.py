"""The fixed-step driver shared by the particle simulations' ``advance`` (km.nbody, km.vortex),
with the one advance rule of every method (cpp/core/advance.h)."""

from __future__ import annotations

from kinema._checks import non_negative, positive


def advance(sim, duration, dt, callback=None):
    """Calls sim.step(h) with h = dt up to sim.time + duration; callback(sim) after every step.

    The last step lands exactly on the end; when a full step would leave a sliver of less than
    dt/10, that step is stretched to the end instead (as cpp/core/advance.h: a sliver costs a
    whole step for nothing). Returns sim."""
    duration = non_negative(duration, "duration")
    dt = positive(dt, "dt")
    end = sim.time + duration
    while sim.time < end:
        remaining = end - sim.time
        last = dt >= remaining or remaining - dt < 0.1 * dt
        sim.step(remaining if last else dt)
        if last:
            sim.time = end  # no round-off drift past or short of the end
        if callback is not None:
            callback(sim)
    return sim

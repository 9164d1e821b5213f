"""Shared test helpers."""

import os
import signal
import threading
import time

import pytest


@pytest.fixture
def ctrl_c_delay():
    """``ctrl_c_delay(run, after=0.5)`` calls ``run()``, sends this process SIGINT ``after``
    seconds later, expects KeyboardInterrupt and returns the seconds from the signal to the
    exception. Fails if ``run`` returns before the signal was sent. ``clock`` (default
    time.perf_counter, wall seconds) may be time.process_time: the CPU seconds the process spent
    between the two, which other processes' load does not stretch.

    ``on_cpu=True`` sends the signal after ``after`` CPU seconds of this process (the kernel's
    profiling timer, SIGPROF) and measures in CPU seconds: for a call that holds the GIL in a C
    loop, during which a timer thread cannot run to send the signal at all (it would fire only
    when the loop returns, and the delay would read zero however long the loop ran on)."""

    def measure(run, after=0.5, clock=time.perf_counter, on_cpu=False):
        fired = []

        def interrupt():
            fired.append(clock())
            os.kill(os.getpid(), signal.SIGINT)

        # Background shells start with SIGINT ignored: install Python's handler, as a terminal has.
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        if on_cpu:
            clock = time.process_time
            due = clock() + after

            def on_profile_timer(signum, frame):
                fired.append(due)  # the kernel fired at that CPU time; Python runs this later
                os.kill(os.getpid(), signal.SIGINT)

            previous_prof = signal.signal(signal.SIGPROF, on_profile_timer)
            signal.setitimer(signal.ITIMER_PROF, after)
        else:
            timer = threading.Timer(after, interrupt)
            timer.start()
        try:
            with pytest.raises(KeyboardInterrupt):
                run()
            caught = clock()
        finally:
            if on_cpu:
                signal.setitimer(signal.ITIMER_PROF, 0)
                signal.signal(signal.SIGPROF, previous_prof)
            else:
                timer.cancel()
            signal.signal(signal.SIGINT, previous)
        assert fired, "the call returned before the interrupt was sent"
        return caught - fired[0]

    return measure

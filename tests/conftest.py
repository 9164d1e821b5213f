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
    between the two, which other processes' load does not stretch."""

    def measure(run, after=0.5, clock=time.perf_counter):
        fired = []

        def interrupt():
            fired.append(clock())
            os.kill(os.getpid(), signal.SIGINT)

        # Background shells start with SIGINT ignored: install Python's handler, as a terminal has.
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        timer = threading.Timer(after, interrupt)
        timer.start()
        try:
            with pytest.raises(KeyboardInterrupt):
                run()
            caught = clock()
        finally:
            timer.cancel()
            signal.signal(signal.SIGINT, previous)
        assert fired, "the call returned before the interrupt was sent"
        return caught - fired[0]

    return measure

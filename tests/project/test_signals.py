"""Signals are acted on in the dispatcher thread, never inside the handler (fog_driver.signals).

A handler that takes a lock deadlocks when the signal lands while the main thread holds that lock
(a daemon once never exited: SIGTERM arrived inside ``Event.wait``).  These tests hold the lock the
action needs while the signal is delivered, deterministically: ``os.kill`` on the own process runs
the Python-level handler before it returns, in this thread.
"""

from __future__ import annotations

import os
import signal
import threading

import pytest

from fog_driver.signals import SignalDispatcher, stop_on_signals

GUARD_S = 10.0  # a hang guard only


def test_the_action_runs_in_the_dispatcher_while_the_main_thread_holds_its_lock():
    lock = threading.Lock()
    seen: list[tuple[int, bool, bool]] = []
    ran = threading.Event()

    def on_signal(signum: int) -> None:
        # Run inside the handler, this acquire could only time out: the main thread holds the lock.
        got = lock.acquire(timeout=GUARD_S)
        if got:
            lock.release()
        seen.append((signum, threading.current_thread() is threading.main_thread(), got))
        ran.set()

    with SignalDispatcher([signal.SIGUSR1], on_signal):
        with lock:
            os.kill(os.getpid(), signal.SIGUSR1)  # the Python-level handler has run when this returns
            assert not ran.is_set()  # the action waits for the lock this thread holds
        assert ran.wait(GUARD_S)
    assert seen == [(signal.SIGUSR1, False, True)]


def test_a_burst_is_a_queue_of_actions_never_a_reentry():
    active = 0
    overlaps = 0
    count = 0
    done = threading.Event()
    n = 50

    def on_signal(signum: int) -> None:
        nonlocal active, overlaps, count
        active += 1
        overlaps += active > 1
        for _ in range(10000):  # an action that takes a while, as a reload does
            pass
        active -= 1
        count += 1
        if count == n:
            done.set()

    with SignalDispatcher([signal.SIGUSR1], on_signal):
        for _ in range(n):
            os.kill(os.getpid(), signal.SIGUSR1)
            # Each kill is handled before the next: none coalesce, all reach the wake-up socket.
        assert done.wait(GUARD_S)
    assert count == n and overlaps == 0


def test_handlers_and_the_wakeup_descriptor_are_restored():
    before = signal.getsignal(signal.SIGUSR1)
    fd_before = signal.set_wakeup_fd(-1)
    signal.set_wakeup_fd(fd_before)
    with SignalDispatcher([signal.SIGUSR1], lambda s: None):
        assert signal.getsignal(signal.SIGUSR1) is not before
    assert signal.getsignal(signal.SIGUSR1) is before
    assert signal.set_wakeup_fd(fd_before) == fd_before


def test_a_failing_action_does_not_end_signal_handling():
    calls: list[int] = []
    second = threading.Event()

    def on_signal(signum: int) -> None:
        calls.append(signum)
        if len(calls) == 1:
            raise RuntimeError("the first action fails")
        second.set()

    with SignalDispatcher([signal.SIGUSR1], on_signal):
        os.kill(os.getpid(), signal.SIGUSR1)
        os.kill(os.getpid(), signal.SIGUSR1)
        assert second.wait(GUARD_S)
    assert calls == [signal.SIGUSR1, signal.SIGUSR1]


def test_stop_on_signals_sets_stop_then_a_second_signal_forces_keyboardinterrupt():
    stop = threading.Event()
    with stop_on_signals(stop, [signal.SIGUSR1]):
        os.kill(os.getpid(), signal.SIGUSR1)
        assert stop.wait(GUARD_S)
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGUSR1)


def test_a_first_signal_never_forces_even_when_stop_is_already_set():
    """The dispatcher thread gets the wake-up byte at once and may set ``stop`` before the main thread runs
    the Python handler of the same signal: a handler that read ``stop`` turned a single SIGTERM into an
    interrupt (exit 130; a CI failure of `simulate --serve`).  Here ``stop`` is set first, as the
    dispatcher (or anything else) may have done."""
    stop = threading.Event()
    stop.set()
    with stop_on_signals(stop, [signal.SIGUSR1]):
        os.kill(os.getpid(), signal.SIGUSR1)  # the first: a clean stop, never KeyboardInterrupt
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGUSR1)  # the second forces


@pytest.fixture
def hangups_restored(monkeypatch):
    """``defer_hangups`` in this process: SIGHUP's handler and the count given back after the test."""
    from fog_driver import signals

    previous = signal.getsignal(signal.SIGHUP)
    monkeypatch.setattr(signals, "_hangups", None)
    yield
    signal.signal(signal.SIGHUP, previous)


def test_sighups_before_the_dispatcher_are_counted_and_one_action_is_delivered(hangups_restored):
    """What ``run`` does with SIGHUPs that come while it starts: counted (not its default action, the end of
    the process), then one action queued in the dispatcher once it is in place."""
    from fog_driver.signals import defer_hangups, deferred_hangups

    assert deferred_hangups() is None
    defer_hangups()
    os.kill(os.getpid(), signal.SIGHUP)  # the Python-level handler has run when this returns
    os.kill(os.getpid(), signal.SIGHUP)
    defer_hangups()  # again (the command line's two steps): the count goes on
    assert deferred_hangups() == 2
    counting = signal.getsignal(signal.SIGHUP)
    seen: list[tuple[int, bool]] = []
    done = threading.Event()

    def on_signal(signum: int) -> None:
        seen.append((signum, threading.current_thread() is threading.main_thread()))
        done.set()

    with SignalDispatcher([signal.SIGHUP], on_signal) as dispatcher:
        dispatcher.deliver(signal.SIGHUP)
        assert done.wait(GUARD_S)
    assert seen == [(signal.SIGHUP, False)]
    assert signal.getsignal(signal.SIGHUP) is counting  # given back: a SIGHUP at the exit is counted, not fatal


def test_a_dispatcher_for_a_process_that_ends_leaves_its_signals_ignored():
    """``run``'s: a second Ctrl-C once the stop is done (the process exiting) must not end it by SIGINT."""
    before = signal.getsignal(signal.SIGUSR1)
    try:
        with SignalDispatcher([signal.SIGUSR1], lambda s: None, ignore_after=True):
            pass
        assert signal.getsignal(signal.SIGUSR1) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGUSR1, before)

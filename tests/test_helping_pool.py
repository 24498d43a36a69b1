"""The pool whose waiters work (common/helping_pool.py): nested jobs, results in order, errors."""
import threading
import time

import pytest

from common.helping_pool import HelpingPool, PoolClosed

pytestmark = pytest.mark.timeout(30)


def test_nested_jobs_on_a_full_pool_finish():
    """Each job submits jobs to the pool it runs on and waits for them: an ordinary pool of two
    threads would wait on itself here."""
    pool = HelpingPool(2)
    try:
        def leaf(k):
            time.sleep(0.001)
            return k * k

        def fit(k):
            inner = [pool.submit(leaf, 10 * k + j) for j in range(4)]
            return [job.result() for job in inner]

        outer = [pool.submit(fit, k) for k in range(5)]
        assert [job.result() for job in outer] == [[(10 * k + j) ** 2 for j in range(4)] for k in range(5)]
    finally:
        pool.shutdown()


def test_both_threads_work_and_the_waiter_is_one():
    """Two threads in all: the worker and the thread that waits run the jobs between them."""
    pool = HelpingPool(2, "t")
    seen, lock = set(), threading.Lock()
    try:
        def job(_):
            with lock:
                seen.add(threading.current_thread().name)
            time.sleep(0.02)

        pool.map(job, range(6))
    finally:
        pool.shutdown()
    assert seen == {"MainThread", "t-0"}


def test_errors_reach_the_waiter_and_the_pool_goes_on():
    pool = HelpingPool(3)
    try:
        def fail(k):
            raise KeyError(k)

        job = pool.submit(fail, 7)
        with pytest.raises(KeyError, match="7"):
            job.result()
        assert pool.map(lambda k: k + 1, range(4)) == [1, 2, 3, 4]
    finally:
        pool.shutdown()


def test_shut_pool_refuses_jobs():
    pool = HelpingPool(2)
    pool.shutdown()
    with pytest.raises(PoolClosed):
        pool.submit(print, "never")


def test_jobs_left_queued_at_shutdown_fail_their_waiters():
    pool = HelpingPool(2)
    started, release = threading.Event(), threading.Event()

    def block():
        started.set()
        release.wait(10)

    running = pool.submit(block)  # the only worker takes it
    assert started.wait(10)
    queued = pool.submit(lambda: "late")
    pool.shutdown(wait=False)
    with pytest.raises(PoolClosed):
        queued.result()
    release.set()
    assert running.result() is None


def test_a_pool_needs_two_threads():
    with pytest.raises(ValueError, match="at least 2"):
        HelpingPool(1)

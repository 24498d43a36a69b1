"""A thread pool whose waiters work: jobs may submit jobs to the pool they run on.

A single-process fit runs a round's whole fits side by side, and each whole fit hands its limb
solves out in turn. On an ordinary pool a fit waiting for its limbs holds a thread, so a full
pool would wait on itself, and a round of three fits on two threads leaves one thread idle for a
whole fit. Here a thread that waits for results runs queued jobs meanwhile: its own first (the
newest first), else whichever job was queued last, so every thread keeps working until the
round is done. With ``threads`` threads in all, the pool starts ``threads - 1`` workers: the
thread that submits and then waits is the other.

Which thread runs a job never changes what it returns, so results do not depend on the number
of threads as long as the jobs are pure functions of their inputs.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any, Callable, Iterable


class PoolClosed(RuntimeError):
    """A job submitted to, or left queued in, a pool that was shut down."""


class Job:
    """One submitted call: ``result()`` waits for it, running queued jobs meanwhile."""

    def __init__(self, pool: "HelpingPool", function: Callable, args: tuple, kwargs: dict):
        self._pool, self._call = pool, (function, args, kwargs)
        self._done, self._value, self._error = False, None, None
        self._submitter = threading.get_ident()

    def _run(self) -> None:
        function, args, kwargs = self._call
        try:
            value, error = function(*args, **kwargs), None
        except BaseException as exc:  # handed to whoever waits for the result
            value, error = None, exc
        with self._pool._changed:
            self._value, self._error, self._done = value, error, True
            self._call = None
            self._pool._changed.notify_all()

    def result(self) -> Any:
        self._pool._help_until(self)
        if self._error is not None:
            raise self._error
        return self._value


class HelpingPool:
    """``threads`` threads in all (at least 2): ``threads - 1`` workers plus the waiter."""

    def __init__(self, threads: int, name: str = "pool"):
        if threads < 2:
            raise ValueError(f"a pool needs at least 2 threads, got {threads}")
        self._changed = threading.Condition()  # a job queued or finished, or the pool shut
        self._queue: deque[Job] = deque()
        self._shut = False
        self._workers = [threading.Thread(target=self._work, name=f"{name}-{k}", daemon=True)
                         for k in range(threads - 1)]
        for worker in self._workers:
            worker.start()

    def submit(self, function: Callable, /, *args, **kwargs) -> Job:
        job = Job(self, function, args, kwargs)
        with self._changed:
            if self._shut:
                raise PoolClosed("submit to a pool that was shut down")
            self._queue.append(job)
            self._changed.notify_all()
        return job

    def map(self, function: Callable, items: Iterable) -> list:
        """[function(item) for item in items], side by side, in order."""
        jobs = [self.submit(function, item) for item in items]
        return [job.result() for job in jobs]

    def _work(self) -> None:
        while True:
            with self._changed:
                while not self._queue and not self._shut:
                    self._changed.wait()
                if not self._queue:
                    return
                job = self._queue.popleft()  # the oldest: a round's jobs in the order given
            job._run()

    def _help_until(self, job: Job) -> None:
        me = threading.get_ident()
        while True:
            with self._changed:
                if job._done:
                    return
                task = next((j for j in reversed(self._queue) if j._submitter == me), None)
                if task is None and self._queue:
                    task = self._queue[-1]  # the newest: most often a limb of a fit in flight
                if task is None:
                    self._changed.wait()
                    continue
                self._queue.remove(task)
            task._run()

    def shutdown(self, wait: bool = True) -> None:
        """Stop taking jobs; queued jobs are dropped (their waiters get PoolClosed)."""
        with self._changed:
            self._shut = True
            for job in self._queue:
                job._error, job._done, job._call = PoolClosed("the pool was shut down before this job ran"), True, None
            self._queue.clear()
            self._changed.notify_all()
        if wait:
            for worker in self._workers:
                worker.join()
